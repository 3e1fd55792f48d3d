"""iLQR over the PD targets of a MuJoCo model: the local polish of a sampled plan."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

StageFn = Callable[
    [mujoco.MjData, int, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
]
"""``stage(data, t, u)`` with ``data`` at the state after control step ``t`` under control
``u``: residuals ``r`` (m,) whose squared norm is the state's cost, their Jacobian in the tangent state (m, 2 nv + na, or its first
2 nv columns), and the gradient (nu,) and Hessian (nu, nu) of the step's cost in its
control."""


@dataclass(frozen=True, kw_only=True)
class IlqrResult:
    """The polished plan.

    Attributes:
        controls: One control per control step. Shape: (H, nu).
        cost: Its exact cost (the caller's ``cost``).
        initial_cost: The exact cost of the plan it started from.
        steps: The step size each iteration took (0 where no step lowered the cost).
    """

    controls: np.ndarray
    cost: float
    initial_cost: float
    steps: tuple[float, ...]


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


def ilqr(
    model: mujoco.MjModel,
    state: np.ndarray,
    warmstart: np.ndarray,
    controls: np.ndarray,
    *,
    decimation: int,
    stage: StageFn,
    cost: Callable[[np.ndarray], float],
    lower: np.ndarray,
    upper: np.ndarray,
    iterations: int,
    eps: float = 1e-6,
    mu: float = 2e-2,
) -> IlqrResult:
    """Polish ``controls`` from ``state`` by ``iterations`` of iLQR.

    Sampling (:mod:`humimic.retarget.dynamics.sampler`) finds a plan in the right basin but
    leaves it noisy: its hundreds of knot values are each set by a few hundred random draws.
    Starting from that plan, iterative LQR (Li and Todorov, "Iterative Linear Quadratic
    Regulator Design for Nonlinear Biological Movement Systems", 2004; the regularization and
    line search of Tassa, Erez and Todorov, "Synthesis and Stabilization of Complex Behaviors
    through Online Trajectory Optimization", 2012) moves every value along the cost's local
    Gauss-Newton model at once:

    * the plan holds one control per control step over ``decimation`` physics steps; the
      control step's Jacobians ``A = dx'/dx``, ``B = dx'/du`` compose MuJoCo's
      finite-difference transition derivatives (``mjd_transitionFD``) of its physics steps,
      in the tangent space of the state (``2 nv``: position differences as
      ``mj_differentiatePos`` gives them, then velocities; :func:`control_step_jacobians`);
    * the caller's ``stage`` gives, for the state after each control step, residuals ``r``
      and their Jacobian ``J`` (the cost ``|r|^2``: gradient ``2 J^T r``, Gauss-Newton
      Hessian ``2 J^T J``), and the gradient and Hessian of the step's cost in its control;
    * the backward pass is the Riccati recursion (:func:`riccati`) with Levenberg-Marquardt
      regularization ``mu`` on ``Q_uu`` (raised tenfold when ``Q_uu`` is not positive
      definite or no step helps, lowered threefold after a step helps);
    * the forward pass applies ``u + alpha k + K dx`` with the feedback gains ``K`` (clipped
      to the bounds), for step sizes ``alpha`` 1, 1/2, 1/4, 1/10, and keeps the first whose
      exact cost (the caller's ``cost``, a full simulation) is lower. The feedback acts only
      while the plan is made: what it produced is recorded per control step, so the result
      is an open-loop plan that reproduces the same motion.

    Args:
        model: The model; its controls are the plan's.
        state: The start (``mjSTATE_FULLPHYSICS``).
        warmstart: The constraint solver's warm start at the start (``qacc_warmstart``).
        controls: The plan to start from, one control per control step. Shape: (H, nu).
        decimation: Physics steps per control step.
        stage: See :data:`StageFn`; ``t`` runs over 0..H-1, the last state is ``t = H - 1``.
        cost: The exact cost of a plan (Shape: (H, nu)) from the same start; the result's
            cost never exceeds the start's.
        lower, upper: Bounds of every control. Shape: (nu,).
        iterations: Most iterations; fewer if the regularization grows past 1e4.
        eps: Finite-difference step of the transition derivatives.
        mu: Initial regularization.

    Returns:
        The polished plan and its exact cost.
    """
    spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    H, nu = controls.shape
    nv, nx = model.nv, 2 * model.nv + model.na
    data = mujoco.MjData(model)

    def start() -> mujoco.MjData:
        mujoco.mj_setState(model, data, state, spec)
        data.qacc_warmstart[:] = warmstart
        return data

    u = np.clip(controls, lower, upper)
    c = c0 = float(cost(u))
    steps: list[float] = []
    dq = np.zeros(nv)
    xq, xv = np.zeros((H + 1, model.nq)), np.zeros((H + 1, nv))
    xa = np.zeros((H + 1, model.na))
    A, B = np.zeros((H, nx, nx)), np.zeros((H, nx, nu))
    lx, lxx = np.zeros((H + 1, nx)), np.zeros((H + 1, nx, nx))
    lu, luu = np.zeros((H, nu)), np.zeros((H, nu, nu))
    stale = True  # The linearization is not the current plan's (a rejected step keeps it).
    for _ in range(iterations):
        if stale:
            d = start()
            xq[0], xv[0], xa[0] = d.qpos, d.qvel, d.act
            for t in range(H):
                A[t], B[t] = control_step_jacobians(model, d, u[t], decimation, eps)
                xq[t + 1], xv[t + 1], xa[t + 1] = d.qpos, d.qvel, d.act
                r, J, lu[t], luu[t] = stage(d, t, u[t])
                lx[t + 1, : J.shape[1]] = 2.0 * J.T @ r
                lxx[t + 1, : J.shape[1], : J.shape[1]] = 2.0 * J.T @ J
            stale = False
        gains = None
        while gains is None and mu <= 1e4:
            gains = riccati(lx, lxx, lu, luu, A, B, mu)
            if gains is None:
                mu *= 10.0
        if gains is None:
            break
        k, K = gains
        # Line search on the exact cost, with the feedback closing the loop on the way.
        taken = 0.0
        for alpha in (1.0, 0.5, 0.25, 0.1):
            d, un = start(), np.zeros_like(u)
            for t in range(H):
                mujoco.mj_differentiatePos(model, dq, 1.0, xq[t], d.qpos)
                dx = np.concatenate([dq, d.qvel - xv[t], d.act - xa[t]])
                un[t] = np.clip(u[t] + alpha * k[t] + K[t] @ dx, lower, upper)
                d.ctrl[:] = un[t]
                for _ in range(decimation):
                    mujoco.mj_step(model, d)
            cn = float(cost(un))
            if cn < c:
                u, c, taken, stale = un, cn, alpha, True
                break
        steps.append(taken)
        if taken:
            mu = max(mu / 3.0, 2e-4)
        else:
            mu *= 10.0
            if mu > 1e4:
                break
    return IlqrResult(controls=u, cost=c, initial_cost=c0, steps=tuple(steps))


__all__ = ["IlqrResult", "control_step_jacobians", "ilqr", "riccati"]
