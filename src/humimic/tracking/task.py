"""The task a tracking command runs: the robot's task under a DR profile, physics file and
``--task.*`` settings (:func:`task_config`), and the reference motions at the policy rate
(:func:`load_reference` for a clip, :func:`load_references` for a clip or a library)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from humimic.configs.runs import TaskSettings
from humimic.errors import InputError
from humimic.motion import Motion, load_motion, motion_from_qpos
from humimic.sim.randomization import DR_PROFILES, DomainRandomization, load_dr_profile
from humimic.tracking.config import TrackingConfig, tracking_task


def resolve_dr(dr: str) -> DomainRandomization:
    """A DR profile by name, or from a YAML file."""
    if dr in DR_PROFILES:
        return DR_PROFILES[dr]()
    path = Path(dr)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(
            f"--dr {dr!r}: choose a profile ({', '.join(DR_PROFILES)}) or a .yaml file"
        )
    return load_dr_profile(path)


def apply_task_settings(task: TrackingConfig, settings: TaskSettings) -> TrackingConfig:
    """The task with the values ``settings`` sets (``--task.*``; unset ones keep the task's).

    Raises:
        InputError: ``--task.reward-weights`` names a term the task does not have, or
            ``--task.reward-stds`` one without a std.
    """
    names = ("episode_length_s", "action_base", "action_scale", "soft_limit_factor",
             "history_length")  # fmt: skip
    changes: dict[str, Any] = {n: getattr(settings, n) for n in names}
    changes = {n: v for n, v in changes.items() if v is not None}
    weights = settings.reward_weights
    unknown = sorted(set(weights) - set(task.rewards))
    if unknown:
        raise InputError(
            f"--task.reward-weights: the {task.robot} task has no reward term {unknown[0]!r}; "
            f"its terms: {', '.join(task.rewards)}"
        )
    stds = settings.reward_stds
    no_std = sorted(n for n in stds if "std" not in getattr(task.rewards.get(n), "params", {}))
    if no_std:
        with_std = [n for n, t in task.rewards.items() if "std" in t.params]
        raise InputError(
            f"--task.reward-stds: the {task.robot} task has no reward term {no_std[0]!r} with a "
            f"std; its terms with one: {', '.join(with_std)}"
        )
    if weights or stds:
        changes["rewards"] = {
            name: replace(
                term,
                weight=float(weights.get(name, term.weight)),
                params={**term.params, **({"std": float(stds[name])} if name in stds else {})},
            )
            for name, term in task.rewards.items()
        }
    if settings.feedback_root_cost is not None:
        changes["feedback"] = replace(task.feedback, base_position=settings.feedback_root_cost)
    if settings.feedback_delay is not None:
        changes["feedback_delay"] = int(settings.feedback_delay)
    if settings.dr_replay is not None:
        changes["adaptive"] = replace(task.adaptive, dr_replay=float(settings.dr_replay))
    return replace(task, **changes)


def task_config(
    robot: str,
    dr: str,
    seed: int,
    physics: str | None = None,
    settings: TaskSettings | None = None,
) -> TrackingConfig:
    """The registered tracking task of a robot (:func:`tracking_task`) with a DR profile, the
    values a run's ``settings`` set (:func:`apply_task_settings`) and, if given, a physics file
    (or a shipped one's name)."""
    from humimic.sim.physics import load_physics

    task = replace(tracking_task(robot, resolve_dr(dr)), seed=seed)
    if settings is not None:
        task = apply_task_settings(task, settings)
    return task if physics is None else replace(task, physics=load_physics(physics))


def _slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-6
    s = np.sin(np.where(small, 1.0, theta))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / s)
    w1 = np.where(small, u, np.sin(u * theta) / s)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def load_reference(path: Path, robot: str, fps: float) -> Motion:
    """The motion file at the policy rate (resampled by interpolating ``qpos`` if needed)."""
    from humimic.robots import get_robot, nominal_model

    motion = load_motion(path)
    if motion.robot != robot:
        raise InputError(f"{path}: the motion is for robot {motion.robot!r}, not {robot!r}")
    if motion.num_frames < 2:
        raise InputError(
            f"{path}: the motion has {motion.num_frames} frame; tracking needs 2 or more"
        )
    if abs(motion.fps - fps) < 1e-6:
        return motion
    T = motion.num_frames
    duration = (T - 1) / motion.fps
    n = max(2, math.floor(duration * fps + 1e-9) + 1)
    x = np.arange(n) / fps * motion.fps
    i0 = np.clip(np.floor(x).astype(int), 0, T - 2)
    u = (x - i0)[:, None]
    q0, q1 = motion.qpos[i0], motion.qpos[i0 + 1]
    qpos = (1 - u) * q0 + u * q1
    qpos[:, 3:7] = _slerp(q0[:, 3:7], q1[:, 3:7], u)
    model = nominal_model(get_robot(robot))
    info = dict(motion.info or {})
    info["resampled_from_fps"] = motion.fps
    return motion_from_qpos(model, qpos, fps, robot, info=info)


def is_library(path: Path) -> bool:
    """Whether ``--motion`` names a library of clips (a folder, or a ``.yaml`` list)."""
    return path.is_dir() or path.suffix.lower() in (".yaml", ".yml")


def library_files(path: Path) -> list[Path]:
    """The clip files ``--motion`` names: the file itself; a folder's ``.npz`` files (sorted
    by name, not its subfolders); or the files a ``.yaml`` list names (:func:`library_entries`).

    Raises:
        InputError: A missing path, an empty folder, a bad list (naming what is wrong).
    """
    return [f for f, _ in library_entries(path)]


def library_entries(path: Path) -> list[tuple[Path, float]]:
    """The clip files ``--motion`` names, each with its sampling weight: 1 for a file or a
    folder's clips; a ``.yaml`` list names files (paths relative to the list's folder), each
    an entry ``- a.npz`` (weight 1) or ``- {file: a.npz, weight: 2}``: every frame of a clip
    of weight 2 is twice as likely to start an episode as it would be.

    Raises:
        InputError: A missing path, an empty folder, a list that is not a list of entries,
            a weight that is not a positive number, a listed file that does not exist or is
            listed twice (naming it).
    """
    if not path.exists():
        raise InputError(f"--motion {path}: no such file or folder")
    if path.is_dir():
        files = sorted(p for p in path.glob("*.npz") if p.is_file())
        if not files:
            raise InputError(f"--motion {path}: the folder holds no .npz motion")
        return [(f, 1.0) for f in files]
    if not is_library(path):
        return [(path, 1.0)]
    from humimic.io import read_yaml

    data = read_yaml(path)
    if not isinstance(data, list) or not data:
        raise InputError(f"{path}: expected a list of motion files (.npz), one per line")
    entries = []
    for item in data:
        if isinstance(item, str):
            name, weight = item, 1.0
        elif (
            isinstance(item, dict)
            and isinstance(item.get("file"), str)
            and set(item) <= {"file", "weight"}
        ):
            name, weight = item["file"], item.get("weight", 1.0)
        else:
            raise InputError(f"{path}: {item!r}: an entry is a file name or "
                             "{file: NAME, weight: W}")  # fmt: skip
        if (
            isinstance(weight, bool)
            or not isinstance(weight, int | float)
            or not (math.isfinite(weight) and weight > 0)
        ):
            raise InputError(f"{path}: {name}: weight {weight!r} must be a positive number")
        entries.append((path.parent / name, float(weight)))
    missing = [f for f, _ in entries if not f.is_file()]
    if missing:
        raise InputError(f"{path}: lists {missing[0]}, which does not exist")
    if len({f.resolve() for f, _ in entries}) != len(entries):
        raise InputError(f"{path}: lists a file twice")
    return entries


def load_references(path: Path, robot: str, fps: float) -> list[Motion]:
    """Every clip ``--motion`` names (:func:`library_entries`), each at the policy rate
    (:func:`load_reference`); a clip of weight other than 1 carries it in
    ``info["library_weight"]`` (:class:`~humimic.tracking.command.MotionCommand` reads it)."""
    out = []
    for f, w in library_entries(path):
        m = load_reference(f, robot, fps)
        out.append(m if w == 1.0 else replace(m, info={**(m.info or {}), "library_weight": w}))
    return out


__all__ = [
    "apply_task_settings",
    "is_library",
    "library_entries",
    "library_files",
    "load_reference",
    "load_references",
    "resolve_dr",
    "task_config",
]
