"""Linear-quadratic control of a MuJoCo model along a trajectory: the Jacobians of a control
step, the Riccati recursion, and the time-varying LQR gains that stabilize a stored plan."""

from __future__ import annotations

import hashlib
import pickle
from collections import OrderedDict
from dataclasses import dataclass

import mujoco
import numpy as np


def control_step_jacobians(
    model: mujoco.MjModel, data: mujoco.MjData, ctrl: np.ndarray, decimation: int, eps: float
) -> tuple[np.ndarray, np.ndarray]:
    """The Jacobians of one control step (``ctrl`` held over ``decimation`` physics steps)
    at ``data``'s state, which the call advances by that step.

    Returns:
        ``A`` Shape: (2 nv, 2 nv) and ``B`` Shape: (2 nv, nu), in the tangent state.
    """
    nx = 2 * model.nv + model.na
    a, b = np.zeros((nx, nx)), np.zeros((nx, model.nu))
    A, B = np.eye(nx), np.zeros((nx, model.nu))
    data.ctrl[:] = ctrl
    for _ in range(decimation):
        mujoco.mjd_transitionFD(model, data, eps, False, a, b, None, None)
        A, B = a @ A, a @ B + b
        mujoco.mj_step(model, data)
    return A, B


def riccati(
    lx: np.ndarray,
    lxx: np.ndarray,
    lu: np.ndarray,
    luu: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    mu: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The backward pass: feedforward steps ``k`` and feedback gains ``K`` of the local LQR
    problem, or None if a regularized ``Q_uu`` is not positive definite.

    Args:
        lx, lxx: Gradient and Hessian of the state cost at states 0..H. Shape: (H + 1, nx),
            (H + 1, nx, nx).
        lu, luu: Gradient and Hessian of the control cost of steps 0..H-1. Shape: (H, nu),
            (H, nu, nu).
        A, B: The control steps' Jacobians. Shape: (H, nx, nx), (H, nx, nu).
        mu: Regularization added to ``Q_uu``'s diagonal.

    Returns:
        ``k`` Shape: (H, nu), ``K`` Shape: (H, nu, nx).
    """
    H, nu = lu.shape
    vx, vxx = lx[H].copy(), lxx[H].copy()
    k, K = np.zeros((H, nu)), np.zeros((H, nu, lx.shape[1]))
    eye = mu * np.eye(nu)
    for t in range(H - 1, -1, -1):
        qx = lx[t] + A[t].T @ vx
        qu = lu[t] + B[t].T @ vx
        vxx_a, vxx_b = vxx @ A[t], vxx @ B[t]
        qxx = lxx[t] + A[t].T @ vxx_a
        quu = luu[t] + B[t].T @ vxx_b + eye
        qux = B[t].T @ vxx_a
        try:
            chol = np.linalg.cholesky(quu)
        except np.linalg.LinAlgError:
            return None
        sol = -np.linalg.solve(chol.T, np.linalg.solve(chol, np.column_stack([qu, qux])))
        k[t], K[t] = sol[:, 0], sol[:, 1:]
        vx = qx + K[t].T @ quu @ k[t] + K[t].T @ qu + qux.T @ k[t]
        vxx = qxx + K[t].T @ quu @ K[t] + K[t].T @ qux + qux.T @ K[t]
        vxx = 0.5 * (vxx + vxx.T)
    return k, K


@dataclass(frozen=True, kw_only=True)
class LqrWeights:
    """Diagonal costs of the time-varying LQR around a plan, per unit of the tangent state
    (``mj_differentiatePos`` positions, then velocities) and of the PD targets.

    The root position's cost (100 per m^2, as much as the orientation's per rad^2) holds the
    robot to the plan's place in the world: with 10, the expert alone drifted 96 mm (global
    MPJPE) under DR ``default`` on the CMU walk, with 100, 66 mm (BENCHMARKS.md, issue 25).

    Attributes:
        base_position: Root position [1/m^2].
        base_orientation: Root orientation [1/rad^2].
        joint_position: Joint positions [1/rad^2].
        base_velocity: Root linear and angular velocity [s^2/m^2, s^2/rad^2].
        joint_velocity: Joint velocities [s^2/rad^2].
        control: PD target deviation [1/rad^2].
    """

    base_position: float = 100.0
    base_orientation: float = 100.0
    joint_position: float = 3.0
    base_velocity: float = 1.0
    joint_velocity: float = 0.1
    control: float = 10.0

    def state_diagonal(self, nv: int) -> np.ndarray:
        """The state cost's diagonal for a floating base with ``nv - 6`` joints. Shape: (2 nv,)."""
        j = nv - 6
        return np.concatenate([
            [self.base_position] * 3, [self.base_orientation] * 3, [self.joint_position] * j,
            [self.base_velocity] * 6, [self.joint_velocity] * j,
        ])  # fmt: skip


def delayed_system(A: np.ndarray, B: np.ndarray, delay: int) -> tuple[np.ndarray, np.ndarray]:
    """The linear system of commands that reach the plant ``delay`` control steps after they
    are issued, as an undelayed one: the state ``z_t = [dx_t, du_{t-d}, ..., du_{t-1}]``
    appends the commands in flight (oldest first), ``dx_{t+1} = A_t dx_t + B_t du_{t-d}``, and
    the command issued at ``t`` enters the end of the queue.

    Args:
        A, B: The plant's step Jacobians. Shape: (H, nx, nx), (H, nx, nu).
        delay: Control steps ``d`` >= 0 (0 returns ``A`` and ``B``).

    Returns:
        ``A_z`` Shape: (H, nx + d nu, nx + d nu) and ``B_z`` Shape: (H, nx + d nu, nu).
    """
    if delay == 0:
        return A, B
    H, nx, nu = B.shape
    nz = nx + delay * nu
    Az, Bz = np.zeros((H, nz, nz)), np.zeros((H, nz, nu))
    Az[:, :nx, :nx], Az[:, :nx, nx : nx + nu] = A, B
    for i in range(delay - 1):  # The queue moves up by one command per step.
        r, c = nx + i * nu, nx + (i + 1) * nu
        Az[:, r : r + nu, c : c + nu] = np.eye(nu)
    Bz[:, nz - nu :] = np.eye(nu)
    return Az, Bz


def tvlqr_gains(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    qvel: np.ndarray,
    ctrl: np.ndarray,
    decimation: int,
    weights: LqrWeights | None = None,
    eps: float = 1e-6,
    delay: int = 0,
) -> np.ndarray:
    """Time-varying LQR gains around a plan of a floating-base model: the feedback
    ``u_t = ctrl_t + K_t (x - x_t)`` (``x - x_t`` in the tangent state, as
    ``mj_differentiatePos(x_t, x)`` and the velocity difference) that minimizes the
    quadratic cost of :class:`LqrWeights` along the plan's linearization.

    With ``delay`` d > 0 the gains are for a plant whose commands act d control steps after
    they are issued (:func:`delayed_system`): the command issued at ``t`` is
    ``ctrl_{t+d} + K_t [x - x_t, du_{t-d}, ..., du_{t-1}]``, where ``du_s`` is the command
    issued at ``s`` minus ``ctrl_{s+d}``, the plan's control for the step it will act on. The
    cost is on the plant's state and on each issued command's deviation.

    Args:
        model: The model (its physics step is the plan's).
        qpos: The plan's states at its control steps. Shape: (H + 1, nq). qvel: Shape:
            (H + 1, nv).
        ctrl: The plan's controls, one per control step. Shape: (H, nu).
        decimation: Physics steps per control step.
        weights: The costs (default: :class:`LqrWeights`).
        eps: Finite-difference step of the Jacobians.
        delay: Control steps between issuing a command and its acting on the plant.

    Returns:
        ``K`` Shape: (H, nu, 2 nv + delay nu).
    """
    if delay < 0 or int(delay) != delay:
        raise ValueError(f"delay must be a whole number of control steps >= 0, got {delay}")
    w = weights or LqrWeights()
    # The gains of one plan on one model are the same wherever they are asked for (training,
    # then evaluation under each physics: the base's controller is the nominal robot's), and
    # take seconds: they are remembered by the model's whole content and the plan's.
    key = hashlib.sha1(pickle.dumps(model))
    for a in (qpos, qvel, ctrl):
        key.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        key.update(repr(np.shape(a)).encode())
    key.update(repr((decimation, w, eps, int(delay))).encode())
    digest = key.hexdigest()
    if digest in _GAINS:
        _GAINS.move_to_end(digest)
        return _GAINS[digest].copy()
    K = _tvlqr_gains(model, qpos, qvel, ctrl, decimation, w, eps, int(delay))
    _GAINS[digest] = K.copy()
    while len(_GAINS) > _GAINS_KEPT:
        _GAINS.popitem(last=False)
    return K


_GAINS: OrderedDict[str, np.ndarray] = OrderedDict()
_GAINS_KEPT = 8


def _tvlqr_gains(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    qvel: np.ndarray,
    ctrl: np.ndarray,
    decimation: int,
    w: LqrWeights,
    eps: float,
    delay: int,
) -> np.ndarray:
    H, nv, nu = ctrl.shape[0], model.nv, model.nu
    nx = 2 * nv
    data = mujoco.MjData(model)
    A, B = np.zeros((H, nx, nx)), np.zeros((H, nx, nu))
    for t in range(H):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos[t], qvel[t]
        mujoco.mj_forward(model, data)
        A[t], B[t] = control_step_jacobians(model, data, ctrl[t], decimation, eps)
    A, B = delayed_system(A, B, int(delay))
    nz = A.shape[1]
    q = np.zeros((nz, nz))
    q[:nx, :nx] = np.diag(w.state_diagonal(nv))  # No cost on the queue itself.
    lxx, lx = np.broadcast_to(q, (H + 1, nz, nz)).copy(), np.zeros((H + 1, nz))
    luu, lu = np.broadcast_to(w.control * np.eye(nu), (H, nu, nu)).copy(), np.zeros((H, nu))
    out = riccati(lx, lxx, lu, luu, A, B, 0.0)
    if out is None:  # Positive costs keep Q_uu positive definite: only NaN gets here.
        raise FloatingPointError("the plan's linearization is not finite")
    return out[1]


__all__ = ["LqrWeights", "control_step_jacobians", "delayed_system", "riccati", "tvlqr_gains"]
