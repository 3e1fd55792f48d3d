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
    problem = _Problem(
        model, state, warmstart, *controls.shape, decimation=decimation, stage=stage,
        lower=lower, upper=upper, eps=eps,
    )  # fmt: skip
    u = np.clip(controls, lower, upper)
    c = c0 = float(cost(u))
    steps: list[float] = []
    stale = True  # The linearization is not the current plan's (a rejected step keeps it).
    for _ in range(iterations):
        if stale:
            problem.linearize(u)
        gains, mu = problem.gains(mu)
        if gains is None:
            break
        u, c, taken = problem.line_search(u, c, *gains, cost=cost)
        stale = taken > 0.0
        steps.append(taken)
        mu = max(mu / 3.0, 2e-4) if taken else mu * 10.0
        if mu > 1e4:  # Only after a rejected step (gains came with mu <= 1e4).
            break
    return IlqrResult(controls=u, cost=c, initial_cost=c0, steps=tuple(steps))


class _Problem:
    """One :func:`ilqr` problem: the model, the start, the stage model and the bounds, and
    the linearization of the current plan along its trajectory (the states it visits, the
    control steps' Jacobians, and the cost's derivatives), refilled by :meth:`linearize`.

    All simulation runs on one ``MjData``, set to the start before each rollout.

    Args:
        model, state, warmstart, decimation, stage, lower, upper, eps: As :func:`ilqr`'s.
        H, nu: Control steps of the plan, and controls of each.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        state: np.ndarray,
        warmstart: np.ndarray,
        H: int,
        nu: int,
        *,
        decimation: int,
        stage: StageFn,
        lower: np.ndarray,
        upper: np.ndarray,
        eps: float,
    ) -> None:
        self.model, self.state, self.warmstart = model, state, warmstart
        self.decimation, self.stage, self.eps = decimation, stage, eps
        self.lower, self.upper = lower, upper
        self.spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        nv, nx = model.nv, 2 * model.nv + model.na
        self.data = mujoco.MjData(model)
        self.dq = np.zeros(nv)
        self.xq, self.xv = np.zeros((H + 1, model.nq)), np.zeros((H + 1, nv))
        self.xa = np.zeros((H + 1, model.na))
        self.A, self.B = np.zeros((H, nx, nx)), np.zeros((H, nx, nu))
        self.lx, self.lxx = np.zeros((H + 1, nx)), np.zeros((H + 1, nx, nx))
        self.lu, self.luu = np.zeros((H, nu)), np.zeros((H, nu, nu))

    def start(self) -> mujoco.MjData:
        """The ``MjData`` at the start state, with the start's solver warm start."""
        mujoco.mj_setState(self.model, self.data, self.state, self.spec)
        self.data.qacc_warmstart[:] = self.warmstart
        return self.data

    def linearize(self, u: np.ndarray) -> None:
        """Simulate plan ``u`` (Shape: (H, nu)) from the start, recording the states it
        visits, each control step's Jacobians, and the stage's Gauss-Newton model of the
        cost at each step's end."""
        model, xq, xv, xa = self.model, self.xq, self.xv, self.xa
        d = self.start()
        xq[0], xv[0], xa[0] = d.qpos, d.qvel, d.act
        for t in range(u.shape[0]):
            self.A[t], self.B[t] = control_step_jacobians(model, d, u[t], self.decimation, self.eps)
            xq[t + 1], xv[t + 1], xa[t + 1] = d.qpos, d.qvel, d.act
            r, J, self.lu[t], self.luu[t] = self.stage(d, t, u[t])
            self.lx[t + 1, : J.shape[1]] = 2.0 * J.T @ r
            self.lxx[t + 1, : J.shape[1], : J.shape[1]] = 2.0 * J.T @ J

    def gains(self, mu: float) -> tuple[tuple[np.ndarray, np.ndarray] | None, float]:
        """The Riccati pass's gains ``k, K`` on the current linearization, regularized by
        ``mu``, which grows tenfold while ``Q_uu`` is not positive definite.

        Returns:
            The gains (``None`` once ``mu`` passes 1e4 without them) and the ``mu`` they
            took.
        """
        gains = None
        while gains is None and mu <= 1e4:
            gains = riccati(self.lx, self.lxx, self.lu, self.luu, self.A, self.B, mu)
            if gains is None:
                mu *= 10.0
        return gains, mu

    def line_search(
        self,
        u: np.ndarray,
        c: float,
        k: np.ndarray,
        K: np.ndarray,
        *,
        cost: Callable[[np.ndarray], float],
    ) -> tuple[np.ndarray, float, float]:
        """The first of the step sizes 1, 1/2, 1/4, 1/10 whose plan, the feedback closing
        the loop on the linearized trajectory while it is made, lowers the exact ``cost``
        below ``c``.

        Returns:
            The new plan, its cost and the step size; or ``u``, ``c`` and 0 if none helps.
        """
        model, lower, upper, dq = self.model, self.lower, self.upper, self.dq
        for alpha in (1.0, 0.5, 0.25, 0.1):
            d, un = self.start(), np.zeros_like(u)
            for t in range(u.shape[0]):
                mujoco.mj_differentiatePos(model, dq, 1.0, self.xq[t], d.qpos)
                dx = np.concatenate([dq, d.qvel - self.xv[t], d.act - self.xa[t]])
                un[t] = np.clip(u[t] + alpha * k[t] + K[t] @ dx, lower, upper)
                rollout.step(model, d, self.decimation, ctrl=un[t])
            cn = float(cost(un))
            if cn < c:
                return un, cn, alpha
        return u, c, 0.0


__all__ = ["IlqrResult", "control_step_jacobians", "ilqr", "riccati"]
