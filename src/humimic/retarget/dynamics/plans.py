"""The dynamics retargeter's plans: the knots its decision variables sit at, interpolated to
the control steps, and the motion it commits (:class:`DynamicsResult`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class DynamicsResult:
    """A dynamically feasible motion: initial state, controls, and the states they produce.

    Attributes:
        initial_state: ``mjSTATE_FULLPHYSICS`` state at frame 0. Shape: (``mj_stateSize``,).
        ctrl: PD targets of every physics step. Shape: (S, nu).
        qpos: Generalized positions after each physics step. Shape: (S, nq).
        qvel: Generalized velocities after each physics step. Shape: (S, nv).
        physics_dt: Physics step [s].
        decimation: Physics steps per frame of the reference.
        seconds: Wall-clock time of the optimization [s].
        cpu_seconds: Process CPU time of the optimization, all threads [s].
        rollouts: Physics steps simulated by the sampler, all samples and iterations.
        iterations: Sampling iterations of each window. Shape: (windows,).
        window_costs: Each window's cost after sampling (its best sample's) and of the plan
            committed from it (after the iLQR polish). Shape: (windows, 2).
    """

    initial_state: np.ndarray
    ctrl: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    physics_dt: float
    decimation: int
    seconds: float
    cpu_seconds: float
    rollouts: int
    iterations: np.ndarray
    window_costs: np.ndarray

    def frame_qpos(self) -> np.ndarray:
        """The state at each reference frame: the start, then every ``decimation``-th step.
        Shape: (T, nq)."""
        start = self.initial_state[1 : 1 + self.qpos.shape[1]]
        return np.concatenate([start[None], self.qpos[self.decimation - 1 :: self.decimation]])


def knot_weights(num_steps: int, step_dt: float, knot_dt: float) -> np.ndarray:
    """Linear interpolation of knots at ``0, knot_dt, 2 knot_dt, ...`` to control steps at
    ``0, step_dt, ...``: row j holds the weights of the knots at ``j * step_dt``.

    Returns:
        Shape: (num_steps, K) with ``K = ceil((num_steps - 1) step_dt / knot_dt) + 1``; rows
        sum to 1.
    """
    t = np.arange(num_steps) * step_dt / knot_dt
    k = math.ceil(t[-1] - 1e-9) + 1 if num_steps > 1 else 1
    w = np.zeros((num_steps, max(k, 2)))
    lo = np.minimum(np.floor(t + 1e-9).astype(int), w.shape[1] - 2)
    frac = t - lo
    w[np.arange(num_steps), lo] = 1.0 - frac
    w[np.arange(num_steps), lo + 1] += frac
    return w


__all__ = ["DynamicsResult", "knot_weights"]
