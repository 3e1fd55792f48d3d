"""Fitting and scoring the diagnosis's candidates on a log's k-step windows: batched secant
and grid searches (:func:`fit_candidates`), joint refits (:func:`refit_together`), the noise floors, and the
predictors of the log's fit part (A and B windows).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.candidates import Candidate
from humimic.real2sim.correction import Correction
from humimic.real2sim.floating import BaseEstimate
from humimic.real2sim.residual import Predictor
from humimic.real2sim.robotlog import RobotLog
from humimic.robots.registry import RobotConfig
from humimic.sim.joints import JointMap

FIT_END = 0.7
"""The first 70% of a log is used to fit; the rest is held out."""

OFFSET_PROBE = 0.05
"""Encoder offset [rad] used to test whether offsets show in a log at all."""

MIN_FIT_SAMPLES = 50
"""Fewest state samples in the fit part of a log (the residual network and the signature
plots need some too)."""

_SECANT_STEPS = 6
_SECANT_TOL = 1e-4
"""A pair's secant search stops when its next step is shorter than this share of its interval
(1e-3 left a 0.8 kg payload at 0.785 kg and the held-out error at 0.45 against 0.31 mrad)."""


def fit_candidates(
    predictor: Scorer,
    bases: list[Correction],
    pairs: list[Candidate],
    first: list[float] | None = None,
    removed: list[float] | None = None,
) -> list[float]:
    """Fit every pair's parameter on the predictor's span: batched secant search on the
    residual of the pair's joints, each pair on its own base correction, starting from "no
    effect" and ``first`` (default: each pair's probe). Returns the best value per pair;
    ``removed`` (if given) receives the share of each pair's error its value removes there.

    A torque limit acts only above it, so its error is flat down to the largest torque and
    kinked there: it gets a grid and a golden-section search instead."""
    grid = [i for i, p in enumerate(pairs) if p.effect in _GRID_EFFECTS]
    if grid:
        return _fit_mixed(predictor, bases, pairs, grid, first, removed)

    def run(values: list[float], which: list[int]) -> list[np.ndarray]:
        cs = []
        for i in which:
            c = bases[i].copy()
            pairs[i].apply(c, values[i])
            cs.append(c)
        res = predictor.run(cs)
        return [res[k][..., pairs[i].joints, :].ravel() for k, i in enumerate(which)]

    unique = {id(b): b for b in bases}
    r_none = dict(zip(unique, predictor.run(list(unique.values())), strict=True))
    prev = [
        (p.none, r_none[id(b)][..., p.joints, :].ravel()) for b, p in zip(bases, pairs, strict=True)
    ]
    x = [p.probe for p in pairs] if first is None else list(first)
    best = [(float(r @ r), v) for v, r in prev]
    none_sse = [r for _, r in prev]
    active = list(range(len(pairs)))
    for _ in range(_SECANT_STEPS):
        if not active:
            break
        rs = run(x, active)
        still = []
        for r, i in zip(rs, active, strict=True):
            p, v = pairs[i], x[i]
            sse = float(r @ r)
            if sse < best[i][0]:
                best[i] = (sse, v)
            v0, r0 = prev[i]
            prev[i] = (v, r)
            jac = (r - r0) / (v - v0) if v != v0 else np.zeros_like(r)
            jj = float(jac @ jac)
            if jj * (p.hi - p.lo) ** 2 < 1e-9 * (sse + 1e-30):
                step = v + (v - p.none)  # No sensitivity yet: go further from "no effect".
            else:
                step = v - float(jac @ r) / jj
            step = float(np.clip(step, p.lo, p.hi))
            if step == v:  # Stuck on a bound: try half-way back to the best so far.
                step = 0.5 * (v + best[i][1])
            x[i] = step
            # Converged (the next step would move less than _SECANT_TOL of the interval):
            # the pair leaves the batch, and later rollouts are for the others only.
            if abs(step - v) > _SECANT_TOL * (p.hi - p.lo):
                still.append(i)
        active = still
    if removed is not None:
        removed[:] = [1.0 - e / max(float(r @ r), 1e-30)
                      for (e, _), r in zip(best, none_sse, strict=True)]  # fmt: skip
    return [v for _, v in best]


def _fit_mixed(
    predictor: Scorer,
    bases: list[Correction],
    pairs: list[Candidate],
    grid: list[int],
    first: list[float] | None,
    removed: list[float] | None,
) -> list[float]:
    """:func:`fit_candidates` of pairs some of which (``grid``) are fitted by :func:`_grid_fit`, the
    rest by the secant search."""
    smooth = [i for i in range(len(pairs)) if i not in grid]
    out = [0.0] * len(pairs)
    shares = [0.0] * len(pairs)
    part: list[float] = []
    for k, (i, v) in enumerate(zip(grid, _grid_fit(predictor, [bases[i] for i in grid],
                               [pairs[i] for i in grid], removed=part), strict=True)):  # fmt: skip
        out[i], shares[i] = v, part[k]
    if smooth:
        firsts = None if first is None else [first[i] for i in smooth]
        part = []
        for k, (i, v) in enumerate(zip(smooth, fit_candidates(predictor, [bases[i] for i in smooth],
                                   [pairs[i] for i in smooth], firsts, part), strict=True)):  # fmt: skip
            out[i], shares[i] = v, part[k]
    if removed is not None:
        removed[:] = shares
    return out


class Scorer:
    """Residuals of corrections on a predictor's windows, in units of the noise floor: joint
    positions and, when the log has them, drive torques (its effort), each divided by its
    floor (the median joint's error with the nominal model: most joints lack nothing).
    Shape of :meth:`run`: (C, W, S, J, channels)."""

    def __init__(self, predictor: Predictor, effort: bool) -> None:
        self.predictor = predictor
        self.effort = effort
        self.sigma = np.ones(2 if effort else 1)

    @property
    def samples(self) -> int:
        return self.predictor.samples

    def calibrate(self, nominal: Correction) -> np.ndarray:
        """Set the floors from the nominal model; returns its per-joint position RMSE."""
        raw = self._raw([nominal])[0]
        per_joint = np.sqrt(np.mean(raw**2, axis=(0, 1)))  # (J, ch)
        self.sigma = np.maximum(np.median(per_joint, axis=0), 1e-12)
        return per_joint[:, 0]

    def _raw(self, cs: list[Correction]) -> np.ndarray:
        res = self.predictor.run(cs, effort=self.effort)
        return res if self.effort else res[..., None]

    def run(self, cs: list[Correction]) -> np.ndarray:
        return self._raw(cs) / self.sigma

    def per_joint(self, c: Correction) -> np.ndarray:
        """Normalized RMS error per joint over both channels."""
        return np.sqrt(np.mean(self.run([c])[0] ** 2, axis=(0, 1, 3)))


BASE_PROBES = (("linear velocity", 0.02), ("angular velocity", 0.02), ("height", 0.003))
"""The floating-base estimate's errors a noise floor allows for: the most, per window start,
a log's base estimate is taken to be off by (m/s, rad/s, m). A chosen bound, not measured on
a real robot; the fit on a clean simulated standing G1 log (40 s) came to about 6 mm/s,
12 mrad/s and 1 mm."""


def noise_floor(predictor: Predictor, c: Correction, residual: np.ndarray) -> np.ndarray:
    """Each joint's noise floor [rad]: the k-step error it has when the model lacks nothing.

    ``residual`` is the position residual of ``c`` on ``predictor``'s windows (what its
    :meth:`~humimic.real2sim.residual.Predictor.run` gives, shape (W, S, J)), which callers
    have already. With a fixed base, the floor is the median joint's RMS error: most joints
    lack nothing, and the start states' noise reaches every joint
    alike. On the floor, each window starts from an estimated base state, and an error there
    moves some joints' predictions far more than others (on a standing G1, the ankles and the
    waist roll several times the median joint): the floor of joint j is
    ``sqrt(m^2 + sum_k b_k^2 s_kj^2)``, where ``m`` is the median joint's error (the least
    any joint is given), ``s_kj`` how far joint j's prediction moves (RMS) when the base state
    at every window start is off along axis ``k`` by its :data:`BASE_PROBES` size (x, y, z
    of the linear and of the angular velocity, and the height: seven axes), and ``b_k`` are
    fitted to the joints' RMS errors (non-negative least squares on the squares, relative;
    joints more than twice their fit are left out and the fit repeated: an effect on a few
    joints does not raise the floor). ``b_k`` is at most 1: a base estimate worse than the
    probes is not taken for noise, so an effect whose signature resembles a base error is not
    absorbed into the floor beyond that. (A free constant in place of ``m`` was pinned by
    the quietest joints, the wrists, on a noise-free log, and called 19 joints unexplained.)
    """
    from scipy.optimize import lsq_linear

    res0 = np.asarray(residual, dtype=float)
    e = np.sqrt(np.mean(res0**2, axis=(0, 1)))
    median = max(float(np.median(e)), 1e-12)
    if predictor.base is None:
        return np.full(e.shape, median)
    base = predictor.base
    # One run per axis of each probe, every window's base moved alike along it: a base
    # estimate's error need not be the same along every axis (forward and sideways velocity
    # move different joints), so each axis has its own column.
    axes = {"linear velocity": [(1, i) for i in range(3)],
            "angular velocity": [(1, i) for i in range(3, 6)], "height": [(0, 2)]}  # fmt: skip
    columns = []
    for name, sigma in BASE_PROBES:
        for which, i in axes[name]:
            qpos, qvel = base.qpos.copy(), base.qvel.copy()
            (qpos, qvel)[which][:, i] += sigma
            moved = predictor.with_base(qpos, qvel).run([c])[0]
            columns.append(np.mean((moved - res0) ** 2, axis=(0, 1)))
    a = np.stack(columns, axis=1)  # (J, axes): squared sensitivities.
    y = np.maximum(e, 1e-3 * median) ** 2
    keep = np.ones(e.size, dtype=bool)
    fit = np.full(e.shape, median**2)
    for _ in range(5):
        w = 1.0 / y[keep]
        x = lsq_linear(a[keep] * w[:, None], (y[keep] - median**2) * w, bounds=(0.0, 1.0)).x
        fit = median**2 + a @ x
        now = y <= 4.0 * fit
        if (now == keep).all() or now.sum() < a.shape[1]:
            break
        keep = now
    return np.sqrt(fit)


def offset_reach(predictor: Predictor, base: Correction) -> np.ndarray:
    """RMS change of every joint's prediction when one encoder reads :data:`OFFSET_PROBE`
    off. Shape: (J offset, J affected).

    A hanging robot's drives track the encoder, so an offset moves the limb only through
    gravity: where every change is below the noise, the log cannot reveal that offset.
    """
    J = len(JointMap.of(base.model).names)
    cs = []
    for j in range(J):
        c = base.copy()
        c.offset[j] = OFFSET_PROBE
        cs.append(c)
    res = predictor.run([base, *cs])
    return np.sqrt(np.mean((res[1:] - res[0][None]) ** 2, axis=(1, 2)))


_GRID_EFFECTS = ("torque_limit", "backlash", "contact_friction")
"""Effects that act only past a threshold (a torque above the limit, a reversal wider than
the play, a tangential load past friction x the normal one): their error is flat on one side."""


def _grid_fit(
    predictor: Scorer,
    bases: list[Correction],
    pairs: list[Candidate],
    n: int = 8,
    golden: int = 9,
    removed: list[float] | None = None,
) -> list[float]:
    """Batched grid search over each pair's interval, then golden-section search between the
    best grid point's neighbours; geometric where the interval spans decades (backlash),
    linear otherwise. Every pair advances one evaluation per batch.

    A pair whose grid is best at its "no effect" end, or ties with it there (a torque limit
    above every torque changes nothing), shows no effect the grid can resolve: it stays at
    that end, and the golden-section search is for the others."""
    geometric = np.array([p.lo > 0 and p.hi / p.lo > 20 for p in pairs])

    def value(x: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Parameter values from search coordinates (P,) or (P, k) of pairs ``which``."""
        g = geometric[which].reshape(-1, *([1] * (x.ndim - 1)))
        return np.where(g, np.exp(x), x)

    def sse(xs: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Error of each pair's joints at its value in ``xs`` (P, k). Shape: (P, k)."""
        k = xs.shape[1]
        cs = []
        for i, vs in zip(which, value(xs, which), strict=True):
            for v in vs:
                c = bases[i].copy()
                pairs[i].apply(c, float(v))
                cs.append(c)
        res = predictor.run(cs)
        return np.array([[float(np.sum(res[r * k + j][..., pairs[i].joints, :] ** 2))
                          for j in range(k)] for r, i in enumerate(which)])  # fmt: skip

    every = np.arange(len(pairs))
    lo = np.array([np.log(p.lo) if g else p.lo for p, g in zip(pairs, geometric, strict=True)])
    hi = np.array([np.log(p.hi) if g else p.hi for p, g in zip(pairs, geometric, strict=True)])
    grid = np.linspace(lo, hi, n, axis=1)  # (P, n)
    err = sse(grid, every)
    none_end = np.array([0 if abs(p.none - p.lo) <= abs(p.none - p.hi) else n - 1 for p in pairs])
    out = value(grid[every, none_end], every)
    at_none, best = err[every, none_end], err.min(axis=1)
    live = np.flatnonzero(at_none > best)
    if live.size == 0:
        if removed is not None:
            removed[:] = [0.0] * len(pairs)
        return [float(v) for v in out]
    grid, err = grid[live], err[live]
    rows = np.arange(live.size)
    tried_x, tried_e = [grid], [err]  # Every value evaluated, per live pair.
    k = np.argmin(err, axis=1)
    a = grid[rows, np.maximum(k - 1, 0)]
    b = grid[rows, np.minimum(k + 1, n - 1)]
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    x12 = np.stack([b - ratio * (b - a), a + ratio * (b - a)], axis=1)
    e12 = sse(x12, live)
    tried_x.append(x12)
    tried_e.append(e12)
    (x1, x2), (e1, e2) = x12.T, e12.T
    for _ in range(golden):
        left = e1 <= e2  # The minimum lies in [a, x2]: x1 becomes the new x2.
        a, b = np.where(left, a, x1), np.where(left, x2, b)
        x_new = np.where(left, b - ratio * (b - a), a + ratio * (b - a))
        e_new = sse(x_new[:, None], live)[:, 0]
        tried_x.append(x_new[:, None])
        tried_e.append(e_new[:, None])
        x1, e1, x2, e2 = (np.where(left, x_new, x2), np.where(left, e_new, e2),
                          np.where(left, x1, x_new), np.where(left, e1, e_new))  # fmt: skip
    xs, es = np.concatenate(tried_x, axis=1), np.concatenate(tried_e, axis=1)
    out[live] = value(xs[rows, np.argmin(es, axis=1)], live)
    best[live] = es.min(axis=1)
    if removed is not None:
        removed[:] = [float(1.0 - b / max(e, 1e-30)) for b, e in zip(best, at_none, strict=True)]
    return [float(v) for v in out]


def refit_together(
    predictor: Scorer, start: Correction, kept: list[tuple[Candidate, float]], iters: int = 5
) -> list[float]:
    """Refit the kept effects together (Gauss-Newton on the residual of all their joints,
    finite-difference Jacobian): effects on the same joint share its error, and the first one
    found took more than its part."""
    values = np.array([v for _, v in kept])
    if len(kept) < 2:
        return list(values)
    joints = np.unique(np.concatenate([p.joints for p, _ in kept]))
    lo = np.array([p.lo for p, _ in kept])
    hi = np.array([p.hi for p, _ in kept])
    none = np.array([p.none for p, _ in kept])

    def correction(v: np.ndarray) -> Correction:
        c = start.copy()
        for (p, _), x in zip(kept, v, strict=True):
            p.apply(c, float(x))
        return c

    step = np.maximum(0.1 * np.abs(values - none), 0.01 * (hi - lo))
    for _ in range(iters):
        probes = [values.copy()]
        for i in range(len(kept)):
            v = values.copy()
            v[i] = v[i] + step[i] if v[i] + step[i] <= hi[i] else v[i] - step[i]
            probes.append(v)
        res = predictor.run([correction(v) for v in probes])
        r0 = res[0][..., joints, :].ravel()
        jac = np.stack([(res[1 + i][..., joints, :].ravel() - r0) / (probes[1 + i][i] - values[i])
                        for i in range(len(kept))], axis=1)  # fmt: skip
        jtj = jac.T @ jac
        if not np.trace(jtj) > 0:  # No effect moves these predictions: nothing to refit.
            break
        delta = np.linalg.solve(jtj + 1e-6 * np.trace(jtj) * np.eye(len(kept)), -jac.T @ r0)
        trial = np.clip(values + delta, lo, hi)
        r1 = predictor.run([correction(trial)])[0][..., joints, :].ravel()
        if r1 @ r1 < r0 @ r0:
            values = trial
            step = np.maximum(0.1 * np.abs(delta), 0.002 * (hi - lo))
        else:
            break
    return list(values)


def polish_kept(
    predictor: Scorer, start: Correction, kept: list[tuple[Candidate, float]]
) -> list[float]:
    """Refit the kept effects: alone from where they are, or together (:func:`refit_together`)."""
    if len(kept) > 1:
        return refit_together(predictor, start, kept)
    ((p, v),) = kept
    return fit_candidates(predictor, [start], [p], first=[v])


def backlash_models(
    robot: RobotConfig, base_pose: np.ndarray
) -> Callable[[tuple[str, ...]], mujoco.MjModel]:
    """Builds the prediction model with a play joint on each given joint."""
    from humimic.sim.effects import Injection, apply_to_spec
    from humimic.sim.models import prediction_spec

    built: dict[tuple[str, ...], mujoco.MjModel] = {}
    nominal: list[mujoco.MjSpec] = []

    def build(joints: tuple[str, ...]) -> mujoco.MjModel:
        if joints not in built:
            if not nominal:
                nominal.append(prediction_spec(robot, base_pose))
            spec = nominal[0].copy()
            apply_to_spec(spec, [Injection(effect="backlash", targets=joints, value=0.02)])
            built[joints] = spec.compile()
        return copy.copy(built[joints])

    return build


def fit_predictors(
    model: mujoco.MjModel, log: RobotLog, horizon: float, base_track: BaseEstimate | None = None
) -> tuple[Predictor, Predictor, Predictor]:
    """The fit-part predictors of a diagnosis: A for the secant fits (every other window of
    A), A and B for scoring (A and B interleave: alternate windows of the fit span, so that
    both see every kind of motion the log has). The floating base (if any) is estimated
    once for the three, or ``base_track`` is used (see
    :class:`~humimic.real2sim.residual.Predictor`).

    Raises:
        InputError: The log is too short for the horizon (naming the log file and
            ``--horizon``), or its fit part has fewer than :data:`MIN_FIT_SAMPLES` states.
    """
    fit = (0.0, FIT_END)
    fit_a = Predictor(model, log, horizon=horizon, span=fit, every=4, phase=0,
                      base_track=base_track)  # fmt: skip
    score_a = Predictor(model, log, horizon=horizon, span=fit, every=2, phase=0,
                        base_track=fit_a.track)  # fmt: skip
    score_b = Predictor(model, log, horizon=horizon, span=fit, every=2, phase=1,
                        base_track=fit_a.track)  # fmt: skip
    n = int(np.searchsorted(log.t, log.t[0] + FIT_END * log.duration))
    if n < MIN_FIT_SAMPLES:
        raise InputError(
            f"{log.where}: {n} state samples in the fit part (first {FIT_END:.0%}) of the log; "
            f"the diagnosis needs at least {MIN_FIT_SAMPLES}"
        )
    return fit_a, score_a, score_b
