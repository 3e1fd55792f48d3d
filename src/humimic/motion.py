"""The robot motion file: a versioned ``.npz`` of named arrays (no pickle).

Keys read by mjlab/BeyondMimic trackers: ``fps, joint_pos, joint_vel, body_pos_w, body_quat_w,
body_lin_vel_w, body_ang_vel_w``; plus ``joint_names``, ``body_names``, ``schema_version``,
``robot``, ``root_pos_w``/``root_quat_w`` (= body 0), and ``qpos`` (MuJoCo generalized
positions, for exact replay). Quaternions are wxyz. Body kinematics come from MuJoCo forward
kinematics of ``qpos``; velocities are central finite differences (one-sided at the ends).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.errors import InputError, MotionDataError
from humimic.io import atomic_write
from humimic.transforms import quat_conj, quat_mul, quat_to_rotvec

SCHEMA_VERSION = 1
_REQUIRED = (
    "schema_version",
    "fps",
    "robot",
    "joint_names",
    "body_names",
    "qpos",
    "joint_pos",
    "joint_vel",
    "body_pos_w",
    "body_quat_w",
    "body_lin_vel_w",
    "body_ang_vel_w",
)


@dataclass(frozen=True, kw_only=True)
class Motion:
    """A robot motion. Shapes: T frames, J actuated joints, B bodies (world excluded).

    Attributes:
        robot: Registry name of the robot.
        fps: Frames per second.
        joint_names: Shape: (J,).
        body_names: Shape: (B,); body 0 is the floating base.
        qpos: MuJoCo generalized positions. Shape: (T, 7 + J).
        joint_pos: Shape: (T, J). joint_vel: Shape: (T, J).
        body_pos_w: Shape: (T, B, 3). body_quat_w: Shape: (T, B, 4), wxyz.
        body_lin_vel_w: Shape: (T, B, 3). body_ang_vel_w: Shape: (T, B, 3), world frame.
        extras: Further per-frame named arrays (first axis T), e.g. ``human_contacts``.
        info: Free-form metadata (JSON-able), e.g. the source clip and how it was aligned.
        dynamics: The dynamic section of a dynamically feasible motion (``humimic refine``):
            ``initial_state`` (``mjSTATE_FULLPHYSICS`` of the training model at frame 0),
            ``ctrl`` (S, nu) the PD targets of every physics step, the states they produce,
            ``qpos`` (S, nq) and ``qvel`` (S, nv), and ``physics_dt`` (a scalar).
    """

    robot: str
    fps: float
    joint_names: tuple[str, ...]
    body_names: tuple[str, ...]
    qpos: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    body_pos_w: np.ndarray
    body_quat_w: np.ndarray
    body_lin_vel_w: np.ndarray
    body_ang_vel_w: np.ndarray
    extras: dict[str, np.ndarray] | None = None
    info: dict[str, Any] | None = None
    dynamics: dict[str, np.ndarray] | None = None

    @property
    def num_frames(self) -> int:
        return int(self.qpos.shape[0])


def _diff(x: np.ndarray, fps: float) -> np.ndarray:
    if x.shape[0] < 2:
        return np.zeros_like(x)
    return np.gradient(x, axis=0) * fps


def angular_velocity_w(quat_w: np.ndarray, fps: float) -> np.ndarray:
    """World-frame angular velocity from a wxyz quaternion trajectory (central differences).

    Args:
        quat_w: Shape: (T, ..., 4).
        fps: Frames per second.

    Returns:
        Shape: (T, ..., 3).
    """
    T = quat_w.shape[0]
    if T < 2:
        return np.zeros((*quat_w.shape[:-1], 3))
    out = np.zeros((*quat_w.shape[:-1], 3))
    # q_{t+1} = dq * q_t with dq a world-frame rotation.
    fwd = quat_to_rotvec(quat_mul(quat_w[1:], quat_conj(quat_w[:-1]))) * fps  # (T-1, ..., 3)
    out[0] = fwd[0]
    out[-1] = fwd[-1]
    if T > 2:
        out[1:-1] = 0.5 * (fwd[1:] + fwd[:-1])
    return out


def motion_from_qpos(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    fps: float,
    robot: str,
    extras: dict[str, np.ndarray] | None = None,
    info: dict[str, Any] | None = None,
) -> Motion:
    """Compute every field of a :class:`Motion` from generalized positions by MuJoCo FK."""
    T = qpos.shape[0]
    data = mujoco.MjData(model)
    robot_bodies = [b for b in range(1, model.nbody) if model.body_weldid[b] != 0]
    pos = np.zeros((T, len(robot_bodies), 3))
    quat = np.zeros((T, len(robot_bodies), 4))
    for t in range(T):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        pos[t] = data.xpos[robot_bodies]
        quat[t] = data.xquat[robot_bodies]
    # Keep quaternion signs continuous so that differences are small rotations.
    for t in range(1, T):
        flip = np.sum(quat[t] * quat[t - 1], axis=-1) < 0
        quat[t, flip] *= -1
    qvel = np.zeros((T, model.nv))
    if T > 1:
        fwd = np.zeros((T - 1, model.nv))
        for t in range(T - 1):
            mujoco.mj_differentiatePos(model, fwd[t], 1.0 / fps, qpos[t], qpos[t + 1])
        qvel[0], qvel[-1] = fwd[0], fwd[-1]
        qvel[1:-1] = 0.5 * (fwd[1:] + fwd[:-1])
    return Motion(
        robot=robot,
        fps=float(fps),
        joint_names=tuple(model.joint(j).name for j in range(1, model.njnt)),
        body_names=tuple(model.body(b).name for b in robot_bodies),
        qpos=qpos.copy(),
        joint_pos=qpos[:, 7:].copy(),
        joint_vel=qvel[:, 6:].copy(),
        body_pos_w=pos,
        body_quat_w=quat,
        body_lin_vel_w=_diff(pos, fps),
        body_ang_vel_w=angular_velocity_w(quat, fps),
        extras=extras,
        info=info,
    )


def save_motion(motion: Motion, path: str | os.PathLike[str]) -> Path:
    """Write a motion atomically as ``.npz`` (compressed, no pickled objects)."""
    p = Path(path)
    if p.suffix != ".npz":
        raise InputError(f"{p}: motion files must end in .npz")
    arrays: dict[str, np.ndarray] = {
        "schema_version": np.array(SCHEMA_VERSION),
        "fps": np.array(motion.fps),
        "robot": np.array(motion.robot),
        "joint_names": np.array(motion.joint_names),
        "body_names": np.array(motion.body_names),
        "qpos": motion.qpos,
        "joint_pos": motion.joint_pos,
        "joint_vel": motion.joint_vel,
        "body_pos_w": motion.body_pos_w,
        "body_quat_w": motion.body_quat_w,
        "body_lin_vel_w": motion.body_lin_vel_w,
        "body_ang_vel_w": motion.body_ang_vel_w,
        "root_pos_w": motion.body_pos_w[:, 0],
        "root_quat_w": motion.body_quat_w[:, 0],
    }
    for k, v in (motion.extras or {}).items():
        arrays[f"extra_{k}"] = np.asarray(v)
    if motion.info:
        arrays["info_json"] = np.array(json.dumps(motion.info))
    for k, v in (motion.dynamics or {}).items():
        arrays[f"dynamics_{k}"] = np.asarray(v)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]
    with atomic_write(p, "wb") as f:
        f.write(buf.getvalue())
    return p


def load_motion(path: str | os.PathLike[str]) -> Motion:
    """Read and validate a motion file; errors name the file and the key."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise MotionDataError(f"{p}: not a readable .npz motion file ({e})") from None
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise MotionDataError(f"{p}: missing key(s) {missing}")
    version = int(data["schema_version"])
    if version != SCHEMA_VERSION:
        raise MotionDataError(f"{p}: schema_version {version}, this humimic reads {SCHEMA_VERSION}")
    fps = float(data["fps"])
    if not np.isfinite(fps) or fps <= 0:
        raise MotionDataError(f"{p}: fps must be a positive number, got {fps}")
    for k in _REQUIRED[5:]:
        if data[k].ndim < 2:
            raise MotionDataError(
                f"{p}: {k} must be an array with a frame axis, got shape {data[k].shape}"
            )
    T = data["qpos"].shape[0]
    for k in _REQUIRED[5:]:
        if data[k].shape[0] != T:
            raise MotionDataError(f"{p}: {k} has {data[k].shape[0]} frames, qpos has {T}")
        if not np.all(np.isfinite(data[k])):
            raise MotionDataError(f"{p}: {k} contains NaN or inf")
    return Motion(
        robot=str(data["robot"]),
        fps=fps,
        joint_names=tuple(str(s) for s in data["joint_names"]),
        body_names=tuple(str(s) for s in data["body_names"]),
        qpos=data["qpos"],
        joint_pos=data["joint_pos"],
        joint_vel=data["joint_vel"],
        body_pos_w=data["body_pos_w"],
        body_quat_w=data["body_quat_w"],
        body_lin_vel_w=data["body_lin_vel_w"],
        body_ang_vel_w=data["body_ang_vel_w"],
        extras={k[len("extra_") :]: v for k, v in data.items() if k.startswith("extra_")},
        info=_info(p, data),
        dynamics={k[len("dynamics_") :]: v for k, v in data.items() if k.startswith("dynamics_")}
        or None,
    )


def _info(p: Path, data: dict[str, np.ndarray]) -> dict[str, Any] | None:
    if "info_json" not in data:
        return None
    try:
        info = json.loads(str(data["info_json"]))
    except json.JSONDecodeError as e:
        raise MotionDataError(f"{p}: info_json is not valid JSON ({e})") from None
    if not isinstance(info, dict):
        raise MotionDataError(f"{p}: info_json must hold a JSON object")
    return info
