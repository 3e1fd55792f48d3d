"""Motions and rollouts read whatever their file format (``.npz`` or ``.mcap``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from humimic.errors import InputError
from humimic.motion import Motion, load_motion


def read_any_motion(path: Path) -> Motion:
    """A motion from ``.npz`` (:func:`humimic.motion.load_motion`) or ``.mcap``.

    Raises:
        InputError: Another suffix (names the file), or what the reader raises.
    """
    from humimic.formats.mcap import read_motion_mcap

    if path.suffix == ".npz":
        return load_motion(path)
    if path.suffix == ".mcap":
        return read_motion_mcap(path)
    raise InputError(f"{path}: a motion must be .npz or .mcap")


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
