"""Refining many robot motions (``humimic refine FOLDER``, a training library's clips): each
in a worker process with the manifest, resume and failure isolation of
:mod:`humimic.pipeline.dataset`."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from humimic.configs import DynamicsConfig
from humimic.pipeline.batch import output_paths
from humimic.pipeline.dataset import (
    DatasetSummary,
    DatasetTask,
    plan_tasks,
    run_tasks,
    settings_digest,
    task_outcome,
)

REFINE_HEADLINE = ("frames", "kinematic_mpjpe_mm", "dynamics_mpjpe_mm", "kinematic_fell",
                   "dynamics_fell")  # fmt: skip
"""The figures a refine record keeps (the full report is the motion's ``.json``)."""


def refine_task(
    task: DatasetTask,
    dyn: DynamicsConfig,
    robustness: int,
    backend: str,
    device: str,
    fps: float | None = None,
) -> dict:
    """Refine one robot motion (in a worker process; first resampled to ``fps`` if given and
    other than its own) and write it with its report; its outcome as a record (``humimic
    refine`` of a folder, a training library's clips)."""
    from humimic.io import json_ready
    from humimic.motion import load_motion
    from humimic.pipeline.batch import save_with_report
    from humimic.retarget.dynamics import refine
    from humimic.tracking.task import load_reference

    def work() -> dict[str, Any]:
        motion = load_motion(task.source)
        if fps is not None:
            motion = load_reference(task.source, motion.robot, fps)
        refined, report = refine(motion, dyn, robustness=robustness, backend=backend,  # type: ignore[arg-type]
                                 device=device)  # fmt: skip
        report = json_ready(report)
        save_with_report(refined, task.motion_path, report, task.report_path)
        k, d = report["kinematic_replay"], report["dynamics_replay"]
        values = (refined.num_frames, k["mpjpe_mm"], d["mpjpe_mm"], k["fell"], d["fell"])
        return dict(zip(REFINE_HEADLINE, values, strict=True))

    return task_outcome(work)


def refine_motions(
    files: list[tuple[Path, Path]],
    out: Path,
    dyn: DynamicsConfig,
    *,
    robustness: int,
    backend: str = "cpu",
    device: str = "cpu",
    workers: int | None = None,
    ray: str | None = None,
    quiet: bool = False,
    fps: float | None = None,
    t0: float | None = None,
) -> DatasetSummary:
    """Refine robot motions (each with its output name under ``out``; ``humimic refine
    FOLDER --out OUT`` passes :func:`~humimic.pipeline.dataset.motion_files`) with the
    manifest, resume and failure isolation of :func:`~humimic.pipeline.dataset.run_dataset`:
    a motion refined before from the same bytes with the same settings (``fps`` included: each
    motion resampled to it first) is not refined again."""
    t0 = time.perf_counter() if t0 is None else t0
    outs = output_paths(tuple(f for f, _ in files), files, out, None, {}, folder=True)
    digest = settings_digest({"dyn": dyn, "robustness": robustness, "backend": backend,
                              "device": device, "kind": "refine",
                              **({} if fps is None else {"fps": fps})})  # fmt: skip
    tasks, skipped, manifest = plan_tasks(files, outs, out, digest)
    return run_tasks(tasks, skipped, manifest, digest, refine_task,
                     (dyn, robustness, backend, device, fps), workers=workers, ray=ray,
                     quiet=quiet, t0=t0)  # fmt: skip


__all__ = ["REFINE_HEADLINE", "refine_motions", "refine_task"]
