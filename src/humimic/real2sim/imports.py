"""Robot logs from other recorders, turned into humimic's MCAP contract (``humimic sysid
import``): Unitree low-state arrays (NPZ or CSV) and ROS 2 bags (docs/real2sim.md, "Real logs
in").

The entry points (:func:`import_log`, :func:`import_target`) and every public name of the
import, re-exported: the shared map, target and checks live in
:mod:`~humimic.real2sim.imports_common`, the readers in :mod:`~humimic.real2sim.imports_unitree`
and :mod:`~humimic.real2sim.imports_ros2`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from humimic.errors import InputError
from humimic.real2sim.imports_common import MAX_SPAN, ImportMap, Target, read_import_map
from humimic.real2sim.imports_ros2 import RosTopics, import_ros2
from humimic.real2sim.imports_unitree import MAX_LOG_ARRAY_BYTES, UNITREE_KEYS, import_unitree
from humimic.real2sim.robotlog import QUAT_TOL, RobotLog

if TYPE_CHECKING:
    from humimic.robots.registry import RobotConfig

__all__ = [
    "MAX_LOG_ARRAY_BYTES",
    "MAX_SPAN",
    "UNITREE_KEYS",
    "ImportMap",
    "RosTopics",
    "Target",
    "import_log",
    "import_ros2",
    "import_target",
    "import_unitree",
    "read_import_map",
]


def import_target(
    robot: RobotConfig, base: str, base_pose: np.ndarray | None, imu_site: str = ""
) -> Target:
    """The joints (model order) and IMU site a log of ``robot`` is imported for.

    Raises:
        InputError: A fixed base without ``base_pose``, or no IMU site on the root body.
    """
    from humimic.real2sim.simulate import imu_site_of
    from humimic.sim.joints import JointMap
    from humimic.sim.models import floating_prediction_spec, prediction_spec

    if base == "fixed":
        if base_pose is None:
            raise InputError("--base fixed needs --base-pose X Y Z QW QX QY QZ (the root body "
                             "in the gantry)")  # fmt: skip
        pose = np.asarray(base_pose, dtype=np.float64)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise InputError("--base-pose: expected 7 finite numbers X Y Z QW QX QY QZ")
        norm = float(np.linalg.norm(pose[3:]))
        if not abs(norm - 1.0) <= QUAT_TOL:
            raise InputError(f"--base-pose: the quaternion QW QX QY QZ has length {norm:.3g}, "
                             "expected unit length")  # fmt: skip
        pose[3:] /= norm
        model = prediction_spec(robot, pose).compile()
        names = tuple(model.joint(j).name for j in range(model.njnt))
        return Target(robot=robot.name, joint_names=names, imu_site="", base=base, base_pose=pose)
    if base_pose is not None:
        raise InputError("--base-pose is for a gantry log (--base fixed); a floating base's "
                         "pose comes from the IMU and motion capture")  # fmt: skip
    model = floating_prediction_spec(robot).compile()
    root = int(model.body(robot.root_body).id)
    return Target(robot=robot.name, joint_names=JointMap.of(model).names,
                  imu_site=imu_site_of(model, root, imu_site), base=base,
                  base_pose=np.zeros(7))  # fmt: skip


def import_log(
    path: str | os.PathLike[str], target: Target, imap: ImportMap, topics: RosTopics
) -> RobotLog:
    """A recorder's log as a robot log, by its kind: a ``.npz`` or ``.csv`` of Unitree
    low-state arrays, or a ROS 2 bag (a folder, or its ``.db3`` / ``.mcap`` file).

    Raises:
        InputError: An unknown kind of file, or a malformed one (naming the file and field).
    """
    p = Path(path)
    if p.suffix in (".npz", ".csv"):
        return import_unitree(p, target, imap)
    if p.is_dir() or p.suffix in (".db3", ".mcap"):
        return import_ros2(p, target, imap, topics)
    raise InputError(f"{p}: expected a .npz or .csv of Unitree low-state arrays, or a ROS 2 bag "
                     "(a folder with metadata.yaml, or its .db3 / .mcap file)")  # fmt: skip
