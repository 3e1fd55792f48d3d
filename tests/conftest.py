"""Shared pytest fixtures."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# The robots a user added on this machine (humimic robots add) stay out of the tests: every
# test process reads an empty robots folder of its own unless a test sets another.
os.environ["HUMIMIC_ROBOTS_DIR"] = tempfile.mkdtemp(prefix="humimic-test-robots-")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real data folder beside the repository (``../shared/data``): CMU BVH, holosoma climb.

    Fails (never skips) when it is missing, so a broken checkout cannot pass silently.
    """
    if not (SHARED_DATA / "cmu").is_dir() or not (SHARED_DATA / "holosoma_climb").is_dir():
        pytest.fail(
            f"shared test data not found at {SHARED_DATA}: expected the folders cmu/ and "
            "holosoma_climb/ there (the 'shared' folder beside the repository)"
        )
    return SHARED_DATA


@pytest.fixture(scope="module")
def motion_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The G1 standing, one arm swinging: 1.5 s at 30 fps (the trainer resamples to 50).
    Test modules that need another motion define their own ``motion_file``."""
    import numpy as np

    from humimic.motion import motion_from_qpos, save_motion
    from humimic.robots import get_robot, nominal_model

    m = nominal_model(get_robot("g1"))
    fps, T = 30.0, 46
    q = np.tile(m.key_qpos[0], (T, 1))
    adr = m.jnt_qposadr[m.joint("left_shoulder_pitch_joint").id]
    q[:, adr] += 0.3 * np.sin(2 * np.pi * np.arange(T) / fps)
    path = tmp_path_factory.mktemp("motion") / "stand.npz"
    save_motion(motion_from_qpos(m, q, fps, "g1"), path)
    return path


_LONG_FIRST = (
    "test_real2sim_diagnose.py",
    "test_real2sim_floating.py",
    "test_real2sim.py",
    "test_loop.py",
    "test_imitate.py",
    "test_browser.py",
    "test_tracking_train.py",
    "test_dynamics.py",
)
"""Modules whose tests take 15-60 s each (the diagnoses, end-to-end trainings, the browser)."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long modules' tests run first, the many short ones after: two workers
    (pytest-xdist) then share the short ones at the end instead of one waiting on the other's
    last minute-long diagnosis. Order within a module is kept."""
    del config
    rank = {name: i for i, name in enumerate(_LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(_LONG_FIRST)))
