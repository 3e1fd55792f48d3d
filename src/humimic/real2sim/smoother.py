"""A point's position and velocity over a whole log from its accelerometer and its measured
positions and velocities (:func:`smooth_track`: a Kalman filter and a Rauch-Tung-Striebel
smoother), for the floating base's estimate (:func:`~humimic.real2sim.floating.estimate_base`)."""

from __future__ import annotations

import numpy as np

SIGMA_ACC = 0.5
"""The accelerometer's noise [m/s^2] (white, per sample) the smoother assumes, sampling and
orientation error included."""
SIGMA_FREE = 10.0
"""Without an accelerometer: the base's acceleration [m/s^2] as white noise per sample."""
SIGMA_BIAS = 0.3
"""The accelerometer's bias [m/s^2] before the log (world axes, slowly turning)."""
BIAS_WALK = 0.02
"""How fast the bias may wander [m/s^2 per sqrt(s)]."""
_GATE = 4.0
"""A stance velocity this many standard deviations from the prediction is not read (a slip)."""


def smooth_track(
    t: np.ndarray,
    acc: np.ndarray | None,
    pos: np.ndarray,
    sigma_pos: np.ndarray,
    vel: np.ndarray,
    sigma_vel: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A point's position and velocity at every sample, from all samples (a Kalman filter and a
    Rauch-Tung-Striebel smoother, each axis on its own; Rauch, Tung and Striebel 1965).

    The state per axis is position, velocity and the accelerometer's bias; the accelerometer
    drives the prediction (trapezoidal between samples) or, without one, the acceleration is
    white noise (:data:`SIGMA_FREE`). Position measurements with an infinite ``sigma_pos`` are
    not read; a velocity measurement more than :data:`_GATE` standard deviations from the
    prediction is not read either.

    Args:
        t: Sample times [s], increasing, one unbroken stretch. Shape: (N,).
        acc: The point's acceleration in the world [m/s^2] (gravity removed), or ``None``.
            Shape: (N, 3).
        pos: Measured positions [m]. Shape: (N, 3). sigma_pos: Their noise [m] (``inf``: not
            measured). Shape: (N, 3).
        vel: Measured velocities [m/s]. Shape: (N, 3). sigma_vel: Their noise [m/s].

    Returns:
        Position and velocity. Shape: (N, 3) each.
    """
    n = t.size
    has_acc = acc is not None
    u = acc if acc is not None else np.zeros((n, 3))
    sig_a = np.full(3, SIGMA_ACC if has_acc else SIGMA_FREE)
    x = np.zeros((3, 3))  # Axis, (position, velocity, bias).
    first = np.isfinite(sigma_pos[0])
    x[:, 0] = np.where(first, pos[0], 0.0)
    x[:, 1] = vel[0]
    big = 1e4
    P = np.zeros((3, 3, 3))
    P[:, 0, 0] = np.where(first, sigma_pos[0] ** 2, big)
    P[:, 1, 1] = max(sigma_vel, 1.0) ** 2
    P[:, 2, 2] = (SIGMA_BIAS if has_acc else 1e-6) ** 2
    xp, Pp = np.zeros((n, 3, 3)), np.zeros((n, 3, 3, 3))  # Predicted (before reading k).
    xf, Pf = np.zeros((n, 3, 3)), np.zeros((n, 3, 3, 3))  # Filtered.
    Fs = np.zeros((n, 3, 3))
    for k in range(n):
        if k > 0:
            dt = float(t[k] - t[k - 1])
            a = 0.5 * (u[k - 1] + u[k])
            F = np.array([[1.0, dt, -0.5 * dt * dt], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]])
            if not has_acc:
                F[:, 2] = 0.0
            F[2, 2] = 1.0
            Fs[k] = F
            x = x @ F.T
            x[:, 0] += 0.5 * dt * dt * a
            x[:, 1] += dt * a
            g = np.array([0.5 * dt * dt, dt, 0.0])
            Q = sig_a[:, None, None] ** 2 * np.outer(g, g)
            Q[:, 2, 2] = (BIAS_WALK**2 * dt) if has_acc else 0.0
            P = F @ P @ F.T + Q
        xp[k], Pp[k] = x, P
        for j, z, r in ((0, pos[k], sigma_pos[k] ** 2), (1, vel[k], np.full(3, sigma_vel**2))):
            s = P[:, j, j] + r
            innov = z - x[:, j]
            use = np.isfinite(r)
            if j == 1:
                use &= innov**2 <= _GATE**2 * s
            gain = np.where(use[:, None], P[:, :, j] / np.where(use, s, 1.0)[:, None], 0.0)
            x = x + gain * np.where(use, innov, 0.0)[:, None]
            P = P - gain[:, :, None] * P[:, j, None, :]
        xf[k], Pf[k] = x, P
    xs = xf.copy()
    eye = 1e-12 * np.eye(3)
    for k in range(n - 2, -1, -1):
        F = Fs[k + 1]
        C = np.linalg.solve(Pp[k + 1] + eye, (Pf[k] @ F.T).transpose(0, 2, 1)).transpose(0, 2, 1)
        xs[k] = xf[k] + np.einsum("aij,aj->ai", C, xs[k + 1] - xp[k + 1])
    return xs[:, :, 0], xs[:, :, 1]
