"""Motions and rollouts read whatever their file format (``.npz`` or ``.mcap``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from humimic.errors import InputError
from humimic.motion import Motion, load_motion


def read_any_motion(path: Path, *, robot: str | None = None, fps: float | None = None) -> Motion:
    """A motion from ``.npz`` (:func:`humimic.motion.load_motion`), ``.mcap`` or ``.csv``
    (:mod:`humimic.formats.csv_motion`; ``robot`` and ``fps`` for one without its sidecar).

    Raises:
        InputError: Another suffix (names the file), or what the reader raises.
    """
    from humimic.formats.mcap import read_motion_mcap

    if path.suffix == ".npz":
        return load_motion(path)
    if path.suffix == ".mcap":
        return read_motion_mcap(path)
    if path.suffix == ".csv":
        return _csv_motion(path, robot, fps)
    raise InputError(f"{path}: a motion must be .npz, .mcap or .csv")


def _csv_motion(path: Path, robot: str | None, fps: float | None) -> Motion:
    """A CSV motion on its robot's model: its joint columns must be the robot's joints (and
    the sidecar's joint order the robot's)."""
    from humimic.formats.csv_motion import read_motion_csv
    from humimic.motion import motion_from_qpos
    from humimic.robots import get_robot, nominal_model

    qpos, info = read_motion_csv(path, robot=robot, fps=fps)
    model = nominal_model(get_robot(info["robot"], str(path)))
    names = tuple(model.joint(j).name for j in range(1, model.njnt))
    if qpos.shape[1] != model.nq:
        raise InputError(f"{path}: {qpos.shape[1] - 7} joint columns; robot {info['robot']} "
                         f"has {len(names)} joints")  # fmt: skip
    if info["joint_names"] is not None and tuple(info["joint_names"]) != names:
        raise InputError(f"{path}: its joint order is not robot {info['robot']}'s (see "
                         f"{path.name}.yaml)")  # fmt: skip
    return motion_from_qpos(model, qpos, info["fps"], info["robot"],
                            info={"source": str(path)})  # fmt: skip


def load_rollout(rollout: Path | None, motion_path: Path, motion: Motion) -> np.ndarray | None:
    """A rollout's joint positions at a motion's frames: the ``rollout`` log's (an MCAP with
    ``/qpos``, or ``/base_pose`` and ``/joint_states``), else the motion MCAP's own ``/qpos``
    if it has one, else none.

    Args:
        rollout: A rollout or robot log, or None.
        motion_path: The motion's file (``.npz`` or ``.mcap``).
        motion: The motion read from it.

    Returns:
        Shape: (motion.num_frames, nq), or None.
    """
    from humimic.formats.mcap import qpos_from_log, read_mcap, sample_at

    if rollout is not None:
        log = read_mcap(rollout)
    elif motion_path.suffix == ".mcap":
        log = read_mcap(motion_path, topics=["/qpos"])
        if not log.messages.get("/qpos"):
            return None
    else:
        return None
    times, qpos = qpos_from_log(log, motion.joint_names)
    ref_t = np.round(np.arange(motion.num_frames) * 1e9 / motion.fps).astype(np.int64)
    return sample_at(times - times[0], qpos, ref_t)


__all__ = ["load_rollout", "read_any_motion"]
