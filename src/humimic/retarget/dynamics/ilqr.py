"""iLQR over the PD targets of a MuJoCo model: the local polish of a sampled plan."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.sim import rollout
from humimic.sim.lqr import control_step_jacobians, riccati

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
                rollout.step(model, d, decimation, ctrl=un[t])
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
