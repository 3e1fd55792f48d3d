"""What a kinematic reference asks of the physics: the joint torques that move the robot
along it (inverse dynamics), and how ballistic its flight phases are."""

from __future__ import annotations

import copy

import mujoco
import numpy as np

from humimic.motion import Motion
from humimic.retarget.contacts import runs
from humimic.robots.registry import get_robot


def inverse_dynamics_torques(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    fps: float,
    joint_names: tuple[str, ...],
    foot_body_names: tuple[str, ...],
    *,
    planted_height: float = 0.03,
    moment_weight: float = 10.0,
) -> np.ndarray:
    """Joint torques that move the robot along ``qpos``: inverse dynamics of its finite-
    difference velocities and accelerations, the floating base's share carried by the feet
    on the ground.

    ``mj_inverse`` on the model without constraints gives each frame's generalized force.
    Its six base rows, which no motor produces, are explained by one wrench per planted foot
    (within ``planted_height`` of the foot's lowest in the clip) of least weighted norm
    (moments count ``moment_weight`` times as much as forces); the joint rows less those
    wrenches' share are the torques. In flight (no foot planted) the base rows stay
    unexplained: a reference whose flight is not ballistic has no exact torques.

    Args:
        model: The robot with a free base (dofs 0-5).
        qpos: The motion. Shape: (T, nq).
        fps: Its frame rate.
        joint_names: The joints whose torques are returned, in this order.
        foot_body_names: The bodies that carry the base's wrench when on the ground.

    Returns:
        Shape: (T, len(joint_names)).
    """
    mi = copy.copy(model)
    mi.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    data = mujoco.MjData(mi)
    T = qpos.shape[0]
    qv = np.zeros((T, mi.nv))
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(mi, qv[t], (b - a) / fps, qpos[a], qpos[b])
    qa = np.gradient(qv, 1.0 / fps, axis=0) if T > 1 else np.zeros_like(qv)
    feet = [mi.body(b).id for b in foot_body_names]
    fz = np.zeros((T, len(feet)))
    for t in range(T):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(mi, data)
        fz[t] = data.xpos[feet, 2]
    planted = fz < fz.min(axis=0) + planted_height
    dofs = [int(mi.joint(j).dofadr[0]) for j in joint_names]
    out = np.zeros((T, len(dofs)))
    jp, jr = np.zeros((3, mi.nv)), np.zeros((3, mi.nv))
    w_inv = np.r_[np.ones(3), np.full(3, 1.0 / moment_weight)]
    for t in range(T):
        data.qpos[:], data.qvel[:], data.qacc[:] = qpos[t], qv[t], qa[t]
        mujoco.mj_inverse(mi, data)
        f = data.qfrc_inverse.copy()
        jac = []
        for k, b in enumerate(feet):
            if planted[t, k]:
                mujoco.mj_jacBody(mi, data, jp, jr, b)
                jac.append(np.vstack([jp, jr]))
        if jac:
            J = np.vstack(jac)  # (6k, nv): the planted feet's wrenches in generalized forces
            A = J[:, :6].T  # (6, 6k)
            wi = np.tile(w_inv, len(jac))
            lam = np.linalg.lstsq((A * wi) @ A.T, f[:6], rcond=None)[0]
            f = f - J.T @ (wi * (A.T @ lam))  # A w = f[:6] with w = wi A^T lam
        out[t] = f[dofs]
    return out


FLIGHT_CLEARANCE = 0.05
"""Both feet this far [m] above their lowest in the clip: a flight frame."""


def com_and_feet(model: mujoco.MjModel, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """The robot's centre of mass and its feet's heights in every frame of a motion.

    Returns:
        ``com`` [m], Shape: (T, 3), and the foot bodies' heights [m], Shape: (T, feet).
    """
    data = mujoco.MjData(model)
    feet = [model.body(b).id for b in get_robot(motion.robot).feet.values()]
    T = motion.num_frames
    com, foot_z = np.zeros((T, 3)), np.zeros((T, len(feet)))
    for t in range(T):
        data.qpos[:] = motion.qpos[t]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        com[t], foot_z[t] = data.subtree_com[1], data.xpos[feet, 2]
    return com, foot_z


def reference_flight(motion: Motion, model: mujoco.MjModel) -> dict[str, float | int]:
    """How ballistic a reference's flight phases are: the frames where both feet are
    :data:`FLIGHT_CLEARANCE` above their lowest, and the mean vertical acceleration of the
    whole-body centre of mass there (of ``model``'s masses under the motion's qpos). A physical
    flight falls at gravity (-9.81 m/s^2 on Earth's model); a retargeted one often does not
    (the human's timing with the robot's scaled heights), and then no feasible motion follows
    its timing exactly. How far a feasible one must stay from it: ``ballistic_gap_mm``, the
    RMS distance between the centre of mass's height and the closest (least-squares) arc of
    free fall through each flight phase of 3 frames or more (the arcs' start height and
    vertical speed fitted per phase).

    Returns:
        ``flight_frames``, ``frames``, ``com_z_acc_in_flight`` [m/s^2] (NaN without flight),
        ``gravity_z`` [m/s^2], ``ballistic_gap_mm`` (NaN without a flight phase of 3
        frames).
    """
    com, foot_z = com_and_feet(model, motion)
    acc_z = (com[2:, 2] - 2 * com[1:-1, 2] + com[:-2, 2]) * motion.fps**2
    airborne = (foot_z > foot_z.min(axis=0) + FLIGHT_CLEARANCE).all(axis=1)
    flight = airborne[1:-1]
    gz = float(model.opt.gravity[2])
    gaps = []
    for a, b in runs(airborne):  # Each flight phase [a, b).
        if b - a < 3:
            continue
        t = np.arange(b - a) / motion.fps
        free = com[a:b, 2] - 0.5 * gz * t**2  # Linear in t for a free fall.
        basis = np.stack([np.ones_like(t), t], axis=1)
        gaps.append(free - basis @ np.linalg.lstsq(basis, free, rcond=None)[0])
    gap = np.concatenate(gaps) if gaps else np.zeros(0)
    return {
        "flight_frames": int(flight.sum()),
        "frames": motion.num_frames,
        "com_z_acc_in_flight": float(acc_z[flight].mean()) if flight.any() else float("nan"),
        "gravity_z": gz,
        "ballistic_gap_mm": 1000.0 * float(np.sqrt(np.mean(gap**2))) if gap.size else float("nan"),
    }


__all__ = [
    "FLIGHT_CLEARANCE",
    "inverse_dynamics_torques",
    "reference_flight",
]
