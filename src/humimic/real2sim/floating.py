"""The floating base's state at a log's samples (:func:`estimate_base`): from motion capture
where the log has it, otherwise from the IMU and the stance foot."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.robotlog import RobotLog
from humimic.sim.joints import JointMap
from humimic.sim.models import REST_DEPTH, floor_colliders, lowest_point
from humimic.transforms import quat_conj, quat_mul, quat_slerp, quat_to_matrix

STANCE = (
    "IMU orientation and gyro; height and velocity from the lowest collider at rest "
    "(as deep in the floor as the model's feet sink standing)"
)
MOCAP = STANCE + "; horizontal position from motion capture (/base_pose)"
_SLACK = 0.05
"""How far [s] a sample may lie outside a stream's span and still be read (its end value)."""


@dataclass(frozen=True, kw_only=True)
class BaseEstimate:
    """The free joint's coordinates at some of a log's samples.

    Attributes:
        qpos: Position (world) and orientation (w x y z, world from root body). Shape: (n, 7).
        qvel: Linear velocity (world) and angular velocity (root body frame), as MuJoCo's free
            joint holds them. Shape: (n, 6).
        source: Where they come from: :data:`MOCAP` or :data:`STANCE`.
        world: Whether the horizontal position is the world's (motion capture) or zero.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    source: str
    world: bool


def free_joint(model: mujoco.MjModel) -> int | None:
    """The model's free joint (its floating base), or ``None`` for a fixed base.

    Raises:
        InputError: More than one free joint (a robot has one base).
    """
    free = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if free.size > 1:
        raise InputError(f"the model has {free.size} free joints; a robot log has one base")
    return int(free[0]) if free.size else None


def _span(where: str, topic: str, t_src: np.ndarray, t: np.ndarray) -> None:
    if t_src.size < 2:
        raise InputError(f"{where}: topic {topic} has {t_src.size} message; need at least 2")
    outside = (t < t_src[0] - _SLACK) | (t > t_src[-1] + _SLACK)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise InputError(
            f"{where}: topic {topic} covers {t_src[0]:.3f}-{t_src[-1]:.3f} s, but a state "
            f"sample at {t[i]:.3f} s needs it"
        )


def _interp(t_src: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of each column of ``x`` (N, k) at ``t``. Shape: (n, k)."""
    return np.stack([np.interp(t, t_src, x[:, k]) for k in range(x.shape[1])], axis=1)


def _interp_quat(t_src: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation between the neighbouring samples. Shape: (n, 4)."""
    i = np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, t_src.size - 2)
    u = np.clip((t - t_src[i]) / (t_src[i + 1] - t_src[i]), 0.0, 1.0)
    return quat_slerp(q[i], q[i + 1], u)


def rest_depth(model: mujoco.MjModel) -> float:
    """How deep [m] the model's feet sink into the floor when it stands: its numeric
    :data:`~humimic.sim.models.REST_DEPTH` (set by
    :func:`~humimic.sim.models.floating_prediction_spec`), else 0."""
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, REST_DEPTH)
    return float(model.numeric_data[model.numeric_adr[i]]) if i >= 0 else 0.0


def estimate_base(
    model: mujoco.MjModel, log: RobotLog, t: np.ndarray, q: np.ndarray, qd: np.ndarray
) -> BaseEstimate:
    """The floating base's coordinates at times ``t`` of a log.

    Orientation and angular velocity come from the IMU (its site's fixed rotation in the root
    body undone). Height and linear velocity come from the contact: the robot's lowest
    collider is taken to touch the floor at rest, which sets the base height and the linear
    velocity that keeps that point still given the joint velocities and the gyro. The
    horizontal position is motion capture's where the log has ``/base_pose``, else zero (a
    flat floor does not care). Motion capture is not used for the rest: on a clean simulated
    log with 1 mm of mocap noise, its height and differentiated velocity (0.2 m/s of noise at
    200 Hz) started the predictions 10 times further off (21.8 against 2.1 mrad of k-step
    joint error) than the contact does.

    Args:
        model: A floating-base model with the log's joints (and the IMU's site).
        log: The log, with ``/imu``.
        t: Times [s]. Shape: (n,).
        q, qd: The log's joint positions and velocities at ``t``, model order. Shape: (n, J).

    Raises:
        InputError: No IMU, an IMU site the model lacks or that is not on the root body, or
            a stream that does not cover ``t`` (naming the log and the topic).
    """
    fj = free_joint(model)
    if fj is None:
        raise InputError("estimate_base needs a floating-base model")
    where = log.where
    imu = log.imu
    if imu is None:
        raise InputError(
            f"{where}: a floating-base log needs topic /imu (orientation and angular "
            "velocity of the base) for its predictions"
        )
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, imu.site)
    if sid < 0:
        raise InputError(
            f"{where}: metadata robot.imu_site {imu.site!r} is not a site of the robot"
        )
    root = int(model.jnt_bodyid[fj])
    if int(model.site_bodyid[sid]) != root:
        raise InputError(
            f"{where}: metadata robot.imu_site {imu.site!r} is not on the root body "
            f"{model.body(root).name!r}; only an IMU on the floating base is supported so far"
        )
    q_bs = model.site_quat[sid] / np.linalg.norm(model.site_quat[sid])  # Body from site.
    _span(where, "/imu", imu.t, t)
    omega_b = _interp(imu.t, imu.gyro_b, t) @ quat_to_matrix(q_bs).T
    n = t.size
    qpos, qvel = np.zeros((n, 7)), np.zeros((n, 6))
    qvel[:, 3:] = omega_b
    quat_ws = _interp_quat(imu.t, imu.quat_w, t)
    qpos[:, 3:] = quat_mul(quat_ws, quat_conj(np.broadcast_to(q_bs, quat_ws.shape)))
    # Stance: the lowest collider rests on the floor, as deep as the model's feet sink when
    # it stands (its contacts are soft).
    f, colliders = floor_colliders(model)
    depth = rest_depth(model)
    jm = JointMap.of(model)
    qa, da = int(model.jnt_qposadr[fj]), int(model.jnt_dofadr[fj])
    data = mujoco.MjData(model)
    jacp = np.zeros((3, model.nv))
    for k in range(n):
        data.qpos[:] = model.qpos0
        data.qpos[qa : qa + 7] = 0.0, 0.0, 0.0, *qpos[k, 3:]
        data.qpos[jm.qadr] = q[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        best, point, body = lowest_point(model, data, f, colliders)
        qpos[k, 2] = -best - depth
        data.qvel[:] = 0.0
        data.qvel[da + 3 : da + 6] = omega_b[k]
        data.qvel[jm.dadr] = qd[k]
        mujoco.mj_jac(model, data, jacp, None, point, body)
        qvel[k, :3] = -(jacp @ data.qvel)
    if log.mocap is None:
        return BaseEstimate(qpos=qpos, qvel=qvel, source=STANCE, world=False)
    mc = log.mocap
    _span(where, "/base_pose", mc.t, t)
    qpos[:, :2] = _interp(mc.t, mc.pos_w[:, :2], t)
    return BaseEstimate(qpos=qpos, qvel=qvel, source=MOCAP, world=True)
