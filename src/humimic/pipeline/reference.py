"""The reference a training run needs: a kinematic motion refined first when the run's action
base is ``feedforward`` or ``feedback`` (:mod:`humimic.tracking.actions`)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

from humimic.configs import DynamicsConfig
from humimic.configs.runs import TrainSettings
from humimic.errors import InputError
from humimic.io import check_writable
from humimic.tracking.runs import LIBRARY_LIST, REFERENCE_FILE, REFERENCE_LIBRARY


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
        return _refine_library(s, task.action_base, 1.0 / task.step_dt, quiet=quiet,
                               may_refine=may_refine)  # fmt: skip
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


def _refine_library(
    s: TrainSettings, base: str, fps: float, *, quiet: bool, may_refine: bool
) -> TrainSettings:
    """A library on a stored base: its clips without stored controls refined (at the policy
    rate ``fps``) into ``RUN/reference/`` on worker processes, one per core, each only once
    for the same bytes (the folder's manifest, :func:`~humimic.pipeline.refining.refine_motions`);
    ``s`` with the library ``RUN/reference/library.yaml`` that lists the refined clips and
    the clips refined already. A clip that fails to refine is reported and left out.

    Raises:
        InputError: A clip of another robot or an unreadable one (before any refining), two
            clips of one name, every clip failing, refining where ``may_refine`` is false, or
            a resumed run whose library changed since it was refined.
    """
    from humimic.motion import load_motion
    from humimic.pipeline.refining import refine_motions
    from humimic.tracking.actions import has_stored_controls
    from humimic.tracking.task import library_files

    folder = s.out / REFERENCE_LIBRARY
    listing = folder / LIBRARY_LIST
    if s.motion.resolve() == listing.resolve():
        return s  # The run's own refined library (a resume that passes it).
    files = library_files(s.motion)
    bare = []
    for f in files:
        clip = load_motion(f)
        if clip.robot != s.robot:
            raise InputError(f"{f}: the motion is for robot {clip.robot!r}, not {s.robot!r}")
        if not has_stored_controls(clip):
            bare.append(f)
    if not bare:
        return s
    if not may_refine:
        raise InputError(
            f"--motion {s.motion}: the action base {base!r} needs refined clips, and "
            f"{bare[0].name} of its {len(files)} is not: refine the library first "
            f"(humimic refine DIR --out REFINED/) for a data-parallel run"
        )
    names = [f.stem for f in bare]
    twice = next((n for n in names if names.count(n) > 1), None)
    if twice is not None:
        raise InputError(f"--motion {s.motion}: two clips are named {twice!r}; rename one")
    if (s.out / "config.yaml").exists():
        _check_resumed_library(s, folder, bare)
    created = not s.out.exists()
    try:
        summary = refine_motions([(f, Path(f.stem)) for f in bare], folder, DynamicsConfig(),
                                 robustness=0, fps=fps, quiet=quiet)  # fmt: skip
    except BaseException:
        if created:
            shutil.rmtree(s.out, ignore_errors=True)
        raise
    failed = {r["key"]: r["error"] for r in summary.failed}
    failed |= {r["key"]: r["error"] for r in summary.skipped if r.get("status") == "failed"}
    kept = [f for f in files if f.stem not in failed or f not in bare]
    if not kept:
        if created:
            shutil.rmtree(s.out, ignore_errors=True)
        raise InputError(f"--motion {s.motion}: no clip of the library could be refined: "
                         f"{next(iter(failed.values()))}")  # fmt: skip
    if not quiet:
        print(f"refined {len(summary.done)} clips of {s.motion} in {summary.seconds:.0f} s "
              f"({len([r for r in summary.skipped if r.get('status') == 'done'])} refined "
              f"before); outcomes in {summary.manifest}")  # fmt: skip
    for name, error in failed.items():
        print(f"left out of the run: {name} (refining failed: {error})")
    _write_listing(s, listing, bare, kept)
    return replace(s, motion=listing)


def _check_resumed_library(s: TrainSettings, folder: Path, bare: list[Path]) -> None:
    """A resumed library run: its clips as refined before, or refused before refining.

    Raises:
        InputError: A clip to refine that the run's manifest does not hold as it is now.
    """
    from humimic.pipeline.dataset import MANIFEST_NAME, Manifest, file_sha256

    done = Manifest(folder / MANIFEST_NAME).last
    changed = [f for f in bare
               if (r := done.get(f.stem)) is None or r.get("sha256") != file_sha256(f)]  # fmt: skip
    if changed:
        raise InputError(
            f"--out {s.out}: its run was not trained on a refinement of {changed[0]} (new "
            "or changed since); pass the run's own motion or start a new run"
        )


def _write_listing(s: TrainSettings, listing: Path, bare: list[Path], kept: list[Path]) -> None:
    """The library a run trains on: its refined clips (beside the listing) and the clips that
    had stored controls (by absolute path), each with its weight in ``s.motion``."""
    import yaml

    from humimic.io import atomic_write_text
    from humimic.tracking.task import library_entries

    weight = dict(library_entries(s.motion))
    entries: list[Any] = []
    for f in kept:
        name = f"{f.stem}.npz" if f in bare else str(f.resolve())
        entries.append(name if weight[f] == 1.0 else {"file": name, "weight": weight[f]})
    atomic_write_text(listing, yaml.safe_dump(entries, sort_keys=False))


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
