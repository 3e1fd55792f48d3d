"""Robot-to-robot retargeting (``humimic retarget g1_walk.npz --robot h1``): a humimic motion of
one robot as a clip of humimic's canonical key points, each where its robot map puts it on the
robot's bodies, computed frame by frame on the robot's model. The ``canonical`` skeleton map
names each key point as itself, so any robot's map retargets it."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.errors import InputError
from humimic.motion import load_motion
from humimic.npyio import npz_keys

CANONICAL = "canonical"
"""The skeleton of a robot motion's key points (``robots/maps/skeletons/canonical.yaml``)."""


def is_motion_file(path: Path) -> bool:
    """Whether ``path`` is a humimic motion (an ``.npz`` with ``qpos`` and ``robot``), not an
    array of human joint positions."""
    if path.suffix.lower() != ".npz":
        return False
    keys = npz_keys(path)
    return {"qpos", "robot"} <= keys


def robot_motion_clip(path: Path) -> HumanClip:
    """The canonical key points of the robot motion in ``path`` as a clip.

    Raises:
        InputError: The motion cannot be read, names an unknown robot, is not that robot's,
            or its robot has no robot map.
    """
    from humimic.robots.maps import compose_map, robot_map_file, skeleton_maps
    from humimic.robots.model import motion_model

    motion = load_motion(path)
    model = motion_model(motion, str(path))
    robot_file = robot_map_file(motion.robot)
    if robot_file is None:
        raise InputError(f"{path}: robot {motion.robot!r} has no robot map to read it by")
    m = compose_map(skeleton_maps()[CANONICAL], robot_file)
    names = tuple(m.keypoints)
    parents = tuple(names.index(kp.parent) if kp.parent else -1 for kp in m.keypoints.values())
    bodies = np.array([model.body(kp.body).id for kp in m.keypoints.values()])
    offsets = np.array([kp.offset for kp in m.keypoints.values()], dtype=float)
    data = mujoco.MjData(model)
    pos = np.zeros((motion.num_frames, len(names), 3))
    for t, q in enumerate(motion.qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        rot = data.xmat[bodies].reshape(-1, 3, 3)
        pos[t] = data.xpos[bodies] + np.einsum("kij,kj->ki", rot, offsets)
    return HumanClip(names=names, parents=parents, positions_w=pos, fps=motion.fps,
                     source=str(path), skeleton=CANONICAL,
                     meta={"start_frame": "0", "robot": motion.robot})  # fmt: skip
