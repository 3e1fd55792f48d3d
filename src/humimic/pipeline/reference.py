"""The reference a training run needs: a kinematic motion refined first when the run's action
base is ``feedforward`` or ``feedback`` (:mod:`humimic.tracking.actions`)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from typing import Any

from humimic.configs.runs import TrainSettings
from humimic.errors import InputError
from humimic.io import check_writable
from humimic.tracking.runs import REFERENCE_FILE


def prepare_reference(
    s: TrainSettings, *, quiet: bool = False, may_refine: bool = True
) -> TrainSettings:
    """The settings a run trains with: ``s`` itself, or, when its action base is
    ``feedforward`` or ``feedback`` and its motion has no stored controls, ``s`` with the
    motion refined by ``humimic refine`` (defaults, no robustness replays) into
    ``RUN/reference.npz``.

    The refined file records the motion it came from; a resumed run (or a new run into the
    same folder) whose motion is that one reuses it instead of refining again. Nothing is
    written if the run's settings or folder are refused (the checks of ``humimic train``
    come first); a run folder this call created is removed again if refining fails.

    Args:
        s: The run's settings. quiet: No progress bar.
        may_refine: Whether this process may refine (not under torchrun: every rank would).

    Raises:
        InputError: Bad settings, a missing or unreadable motion, a refused run folder, or a
            motion that needs refining where ``may_refine`` is false.
    """
    from humimic.motion import load_motion, save_motion
    from humimic.tracking.actions import STORED_BASES, has_stored_controls
    from humimic.tracking.task import is_library, load_reference, task_config
    from humimic.tracking.train import check_run_settings

    s = s.sized()
    check_run_settings(s)
    task = task_config(s.robot, s.dr, s.seed, s.physics, s.task)  # Checks DR and physics.
    if task.action_base not in STORED_BASES:
        return s
    if is_library(s.motion):
        _check_refined_library(s, task.action_base)
        return s
    if not s.motion.is_file():
        raise InputError(f"--motion {s.motion}: no such file")
    source = str(s.motion.resolve())
    ref = s.out / REFERENCE_FILE
    if ref.resolve() == s.motion.resolve():
        return s
    if ref.is_file():
        kept = load_motion(ref)
        if (kept.info or {}).get("refined_from") == source:
            return replace(s, motion=ref)
    if has_stored_controls(load_motion(s.motion)):
        return s
    if (s.out / "config.yaml").exists():
        raise InputError(
            f"--out {s.out}: its run was not trained on a refinement of --motion {s.motion} "
            "(no matching reference.npz); pass the run's own motion"
        )
    if not may_refine:
        raise InputError(
            f"--motion {s.motion}: the action base {task.action_base!r} needs a refined motion; "
            "refine it first (humimic refine) for a data-parallel run"
        )
    motion = load_reference(s.motion, s.robot, 1.0 / task.step_dt)
    check_writable(ref)  # Before a minute of refining; atomic_write makes the folder.
    created = not s.out.exists()
    try:
        refined = _refine(motion, quiet=quiet, name=s.motion.name)
        refined = replace(refined, info={**(refined.info or {}), "refined_from": source})
        save_motion(refined, ref)
    except BaseException:
        if created:
            shutil.rmtree(s.out, ignore_errors=True)
        raise
    return replace(s, motion=ref)


def _check_refined_library(s: TrainSettings, base: str) -> None:
    """A library trains on a stored base only with every clip refined already.

    Raises:
        InputError: Naming the library, the first unrefined clip and the command that
            refines them all.
    """
    from humimic.motion import load_motion
    from humimic.tracking.actions import has_stored_controls
    from humimic.tracking.task import library_files

    files = library_files(s.motion)
    bare = [f for f in files if not has_stored_controls(load_motion(f))]
    if bare:
        more = f" and {len(bare) - 1} more" if len(bare) > 1 else ""
        raise InputError(
            f"--motion {s.motion}: the action base {base!r} needs refined clips, and "
            f"{bare[0].name}{more} of its {len(files)} are not: refine the library first "
            f"(humimic refine {s.motion} --out REFINED/, in parallel) and train on REFINED/, "
            "or train around --task.action-base reference"
        )


def _refine(motion: Any, *, quiet: bool, name: str) -> Any:
    """``humimic refine`` with its defaults (no robustness replays), with a progress bar."""
    from tqdm import tqdm

    from humimic.retarget.dynamics import refine

    with tqdm(total=motion.num_frames - 1, desc=f"refining {name}", unit="frame",
              disable=quiet, leave=False) as bar:  # fmt: skip
        refined, report = refine(motion, robustness=0, progress=bar.update)
    d = report["dynamics_replay"]
    if not quiet:
        state = f"fell at {d['seconds_until_fall']:.2f} s" if d["fell"] else "stays up"
        print(f"refined {name}: its open-loop replay {state}, MPJPE {d['mpjpe_mm']:.0f} mm "
              f"({report['cpu_seconds_per_motion_second']:.0f} CPU s per second of motion)")  # fmt: skip
    return refined


__all__ = ["REFERENCE_FILE", "prepare_reference"]
