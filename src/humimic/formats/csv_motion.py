"""Robot motions as CSV, the layout BeyondMimic's and GMR's users feed their trackers.

One row per frame, no header: base position ``x y z`` [m], base orientation as a quaternion
``qx qy qz qw`` (scalar last), then the joint positions [rad] in the robot's joint order.
Beside the file, ``<name>.csv.yaml`` records what the CSV cannot: the robot, the frame rate,
the joint order and the columns. Humimic's own ``qpos`` has the quaternion scalar first
(MuJoCo's ``w x y z``); the conversion is here and nowhere else. Pure arrays and files: the
robot model is the caller's.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from humimic.errors import InputError
from humimic.io import atomic_write_text, read_yaml

META_SUFFIX = ".yaml"
"""The sidecar is the CSV's name with this appended (``walk.csv.yaml``)."""


def meta_path(path: Path) -> Path:
    """The sidecar of ``path``."""
    return path.with_name(path.name + META_SUFFIX)


def write_motion_csv(
    path: Path, qpos: np.ndarray, *, fps: float, robot: str, joint_names: tuple[str, ...]
) -> Path:
    """Write ``qpos`` (T, 7 + J; MuJoCo's quaternion order) as CSV with its sidecar.

    Returns:
        The sidecar's path.
    """
    q = np.asarray(qpos, dtype=float)
    if q.ndim != 2 or q.shape[1] != 7 + len(joint_names):
        raise InputError(f"{path}: qpos of shape {q.shape} for {len(joint_names)} joints")
    rows = np.concatenate([q[:, :3], q[:, 4:7], q[:, 3:4], q[:, 7:]], axis=1)
    text = "\n".join(",".join(f"{v:.9g}" for v in row) for row in rows) + "\n"
    meta = {
        "format": "humimic motion csv",
        "robot": robot,
        "fps": float(fps),
        "frames": int(q.shape[0]),
        "columns": [
            "base_x",
            "base_y",
            "base_z",
            "base_qx",
            "base_qy",
            "base_qz",
            "base_qw",
            *joint_names,
        ],
        "joint_names": list(joint_names),
    }
    import yaml

    atomic_write_text(path, text)
    side = meta_path(path)
    atomic_write_text(side, yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
    return side


def read_motion_csv(
    path: Path, *, robot: str | None = None, fps: float | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """A CSV motion as ``qpos`` (T, 7 + J; MuJoCo's quaternion order, normalized) and what is
    known of it: ``robot``, ``fps`` and ``joint_names`` (from the sidecar where there is one;
    ``robot`` and ``fps`` given here win over it, and are needed without it).

    Raises:
        InputError: Naming the file (and row or field): not numbers, ragged rows, fewer than 8
            columns, NaN or infinite values, a zero quaternion, no robot or frame rate, a
            sidecar that does not match the file.
    """
    side = meta_path(path)
    meta: dict[str, Any] = {}
    if side.is_file():
        data = read_yaml(side)
        if not isinstance(data, dict):
            raise InputError(f"{side}: not a humimic CSV sidecar (a mapping)")
        meta = data
    robot = robot or meta.get("robot")
    fps = fps if fps is not None else meta.get("fps")
    if not isinstance(robot, str) or not robot:
        raise InputError(f"{path}: which robot? give --robot (no {side.name} beside it says)")
    try:
        fps = float(fps) if fps is not None else None
    except (TypeError, ValueError):
        raise InputError(f"{side}: fps: not a number ({fps!r})") from None
    if fps is None or not math.isfinite(fps) or fps <= 0:
        raise InputError(f"{path}: the frame rate must be a positive number: give --fps")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read: {e}") from None
    rows = [line for line in text.splitlines() if line.strip()]
    if not rows:
        raise InputError(f"{path}: no rows")
    table: list[list[float]] = []
    for i, line in enumerate(rows, start=1):
        try:
            table.append([float(v) for v in line.split(",")])
        except ValueError:
            raise InputError(f"{path}: row {i}: not a comma-separated row of numbers") from None
        if len(table[-1]) != len(table[0]):
            raise InputError(f"{path}: row {i} has {len(table[-1])} columns, row 1 has "
                             f"{len(table[0])}")  # fmt: skip
    a = np.array(table)
    if a.shape[1] < 8:
        raise InputError(f"{path}: {a.shape[1]} columns; a motion has 7 base columns (x y z "
                         "qx qy qz qw) and a column per joint")  # fmt: skip
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        r, c = (int(v) for v in bad[0])
        raise InputError(f"{path}: row {r + 1}, column {c + 1}: {a[r, c]} (NaN or infinite)")
    names = meta.get("joint_names")
    if names is not None and len(names) != a.shape[1] - 7:
        raise InputError(f"{side}: joint_names has {len(names)} joints, {path.name} has "
                         f"{a.shape[1] - 7} joint columns")  # fmt: skip
    quat = np.concatenate([a[:, 6:7], a[:, 3:6]], axis=1)  # w x y z
    norm = np.linalg.norm(quat, axis=1)
    if np.any(norm < 1e-6):
        r = int(np.argmax(norm < 1e-6))
        raise InputError(f"{path}: row {r + 1}: the base quaternion is zero")
    qpos = np.concatenate([a[:, :3], quat / norm[:, None], a[:, 7:]], axis=1)
    info = {"robot": robot, "fps": fps,
            "joint_names": tuple(names) if names is not None else None}  # fmt: skip
    return qpos, info
