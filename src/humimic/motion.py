"""The robot motion file: a versioned ``.npz`` of named arrays (no pickle). :class:`Motion`
is its content, :func:`motion_from_qpos` computes one, :func:`save_motion` and
:func:`load_motion` write and read it; every motion read or written passes
:func:`validate_motion` (defined in :mod:`humimic.motion_checks`).
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.errors import InputError, MotionDataError
from humimic.io import atomic_write, check_input_file
from humimic.motion_checks import FPS_RANGE as FPS_RANGE
from humimic.motion_checks import MAX_ABS_VALUE as MAX_ABS_VALUE
from humimic.motion_checks import validate_motion
from humimic.npyio import read_npz_members
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

MAX_MOTION_BYTES = 4 << 30
"""Most bytes of arrays (uncompressed) a motion file may declare; checked before reading."""
_ROOT_COPY_TOLERANCE = 1e-5
"""Largest difference of ``root_pos_w`` / ``root_quat_w`` from body 0's pose (float32
writers)."""


@dataclass(frozen=True, kw_only=True)
class Motion:
    """A robot motion. Shapes: T frames, J actuated joints, B bodies (world excluded).

    The file's keys are those read by mjlab/BeyondMimic trackers: ``fps, joint_pos,
    joint_vel, body_pos_w, body_quat_w, body_lin_vel_w, body_ang_vel_w``; plus
    ``joint_names``, ``body_names``, ``schema_version``, ``robot``,
    ``root_pos_w``/``root_quat_w`` (= body 0), and ``qpos`` (MuJoCo generalized positions, for
    exact replay). Quaternions are wxyz.

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
        source: The file it was read from, for messages (empty for a computed motion; not
            saved).
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
    source: str = ""

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
    """Compute every field of a :class:`Motion` from generalized positions by MuJoCo FK.

    Body kinematics come from MuJoCo forward kinematics of ``qpos``; velocities are central
    finite differences (one-sided at the ends).
    """
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


# ------------------------------------------------------------------------------ files


def sniff(path: Path) -> str:
    """What a file holds, from its first bytes: ``"npz"`` (a zip archive), ``"mcap"``,
    ``"npy"``, ``"empty"``, ``"text"`` or ``"unknown"``."""
    with path.open("rb") as f:
        head = f.read(512)
    if not head:
        return "empty"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if head.startswith(b"\x89MCAP"):
        return "mcap"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return "unknown"
    return "text" if all(c.isprintable() or c.isspace() for c in text) else "unknown"


def _not_a_motion(p: Path, kind: str) -> MotionDataError:
    """The message for a file that is not an ``.npz`` archive: what it is instead."""
    if kind == "mcap":
        if p.suffix.lower() == ".mcap":
            hint = f"convert it with `humimic convert {p} {p.with_suffix('.npz')}`"
        else:
            hint = f"rename it to {p.with_suffix('.mcap').name}, or convert it with humimic convert"
        return MotionDataError(f"{p}: is an MCAP file, not an .npz motion archive; {hint}")
    what = {
        "npy": "a single .npy array",
        "empty": "an empty file",
        "text": "a text file",
        "unknown": "binary data of no known format",
    }[kind]
    return MotionDataError(
        f"{p}: {what}, not an .npz motion archive (a zip of .npy arrays, as humimic "
        "retarget writes)"
    )


def save_motion(motion: Motion, path: str | os.PathLike[str]) -> Path:
    """Write a motion atomically as ``.npz`` (compressed, no pickled objects).

    Raises:
        InputError: The path does not end in ``.npz``.
        MotionDataError: The motion fails :func:`validate_motion` (nothing is written).
    """
    p = Path(path)
    if p.suffix != ".npz":
        raise InputError(f"{p}: motion files must end in .npz")
    validate_motion(motion, f"{p}: not written: the motion")
    arrays: dict[str, np.ndarray] = {
        "schema_version": np.array(SCHEMA_VERSION),
        "fps": np.array(motion.fps),
        "robot": np.array(motion.robot),
        "joint_names": np.array(motion.joint_names, dtype=str),
        "body_names": np.array(motion.body_names, dtype=str),
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
    """Read and validate a motion file (:func:`validate_motion`).

    The archive is read by :func:`humimic.npyio.read_npz_members` (sizes checked before
    anything is allocated, never a pickle).

    Raises:
        InputError: No such file.
        MotionDataError: Not an ``.npz`` archive (says what it is: an MCAP file, an ``.npy``
            array, ...), a wrong suffix, a corrupt or truncated archive, pickled or oversized
            arrays, or a motion that fails :func:`validate_motion`; names the file and key.
    """
    p = Path(path)
    check_input_file(p, "a motion file")
    try:
        kind = sniff(p)
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror}") from None
    if kind != "npz":
        raise _not_a_motion(p, kind)
    if p.suffix.lower() != ".npz":
        raise MotionDataError(
            f"{p}: motion files end in .npz (this one is a zip archive: rename it if it holds "
            "a motion)"
        )
    data = read_npz_members(
        p, max_bytes=MAX_MOTION_BYTES, kinds="biufU", error=MotionDataError, required=_REQUIRED
    )
    version = _scalar(p, data, "schema_version", "iu", "integer")
    if int(version) != SCHEMA_VERSION:
        raise MotionDataError(
            f"{p}: schema_version {int(version)}, this humimic reads {SCHEMA_VERSION}"
        )
    fps = float(_scalar(p, data, "fps", "iuf", "number"))
    robot = str(_scalar(p, data, "robot", "U", "string"))
    motion = Motion(
        robot=robot,
        fps=fps,
        joint_names=_names(p, data, "joint_names"),
        body_names=_names(p, data, "body_names"),
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
        source=str(p),
    )
    validate_motion(motion, p)
    _check_root_copies(p, data, motion)
    return motion


def _check_root_copies(p: Path, data: dict[str, np.ndarray], motion: Motion) -> None:
    """``root_pos_w`` and ``root_quat_w``, where a file has them, are copies of body 0's
    pose for the trackers that read them (mjlab's): they must be that pose, or a tracker
    would read another motion than humimic does."""
    for key, body in (("root_pos_w", motion.body_pos_w[:, 0]),
                      ("root_quat_w", motion.body_quat_w[:, 0])):  # fmt: skip
        if key not in data:
            continue
        v = data[key]
        if v.shape != body.shape or v.dtype.kind not in "iuf":
            raise MotionDataError(
                f"{p}: {key} has shape {v.shape} and dtype {v.dtype}, expected {body.shape} "
                "numbers (a copy of body 0's pose)"
            )
        off = np.abs(v - body).max(axis=-1)
        if not np.all(off <= _ROOT_COPY_TOLERANCE):  # NaN fails too.
            t = int(np.argmax(~(off <= _ROOT_COPY_TOLERANCE)))
            name = "body_pos_w" if key == "root_pos_w" else "body_quat_w"
            raise MotionDataError(
                f"{p}: {key} frame {t} is {np.round(v[t], 6).tolist()}, but it must be a copy "
                f"of {name}[:, 0] ({np.round(body[t], 6).tolist()})"
            )


def _scalar(p: Path, data: dict[str, np.ndarray], key: str, kinds: str, what: str) -> np.ndarray:
    v = data[key]
    if v.ndim != 0 or v.dtype.kind not in kinds:
        raise MotionDataError(
            f"{p}: {key}: expected one {what}, got an array of shape {v.shape} and dtype {v.dtype}"
        )
    return v


def _names(p: Path, data: dict[str, np.ndarray], key: str) -> tuple[str, ...]:
    v = data[key]
    if v.ndim != 1 or (v.size and v.dtype.kind != "U"):
        raise MotionDataError(
            f"{p}: {key}: expected a list of names, got shape {v.shape} and dtype {v.dtype}"
        )
    return tuple(str(s) for s in v)


def _info(p: Path, data: dict[str, np.ndarray]) -> dict[str, Any] | None:
    if "info_json" not in data:
        return None
    text = _scalar(p, data, "info_json", "U", "string")
    try:
        info = json.loads(str(text))
    except (json.JSONDecodeError, RecursionError) as e:
        raise MotionDataError(f"{p}: info_json is not valid JSON ({e})") from None
    if not isinstance(info, dict):
        raise MotionDataError(f"{p}: info_json must hold a JSON object")
    return info
