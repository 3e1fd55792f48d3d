"""Datasets on Ray (issue 57): a local Ray instance of 2 CPUs the test starts runs the same
folder as the process pool, with the same motions and the same manifest records; a bad clip
fails alone there too. Slow (a Ray start and two workers' imports) and needs the ray extra
(``pip install ray==2.60.0``)."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

from humimic.motion import load_motion
from humimic.pipeline.batch import ClipOptions
from humimic.pipeline.dataset import RAY_PIN, run_dataset
from test_dataset import _folder, _records

pytestmark = pytest.mark.slow


def test_ray_runs_a_folder_as_the_process_pool_does(tmp_path: Path, shared_data: Path) -> None:
    try:
        ray = importlib.import_module("ray")
    except ImportError:
        pytest.fail(f"this test needs Ray: pip install {RAY_PIN}")
    root = _folder(tmp_path / "in", shared_data, {"a": 20, "b": 30, "c": 25})
    np.save(root / "bad.npy", np.full((5, 53, 3), np.nan))
    pool, on_ray = tmp_path / "pool", tmp_path / "ray"
    run_dataset((root,), pool, ClipOptions(), workers=2, quiet=True)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        s = run_dataset((root,), on_ray, ClipOptions(), ray="local", quiet=True)
    finally:
        ray.shutdown()
    assert len(s.done) == 3 and len(s.failed) == 1 and "NaN" in s.failed[0]["error"]
    for name in ("a", "b", "c"):
        np.testing.assert_array_equal(load_motion(pool / f"{name}.npz").qpos,
                                      load_motion(on_ray / f"{name}.npz").qpos)  # fmt: skip
    strip = ("seconds", "finished", "motion", "report")
    a = {r["key"]: {k: v for k, v in r.items() if k not in strip} for r in _records(pool)}
    b = {r["key"]: {k: v for k, v in r.items() if k not in strip} for r in _records(on_ray)}
    assert a == b
