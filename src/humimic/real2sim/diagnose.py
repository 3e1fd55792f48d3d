"""Diagnose a robot log: which effects does the simulator lack, where, and how large are they.

:func:`diagnose_log` runs a cross-validated output-error search over the effect vocabulary
(:data:`SEARCHED`) and returns a :class:`Diagnosis`; docs/real2sim.md describes it for users.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.floating import BaseEstimate
from humimic.real2sim.residual import Predictor
from humimic.real2sim.robotlog import RobotLog
from humimic.robots.registry import RobotConfig
from humimic.sim.effects import EFFECTS, Correction, apply_effect, floor_colliders, soft_geoms
from humimic.sim.joints import JointMap

FIT_END = 0.7
"""The first 70% of a log is used to fit; the rest is held out."""

MIN_REDUCTION = 0.4
"""An effect must remove at least this share of its joints' error on unseen data (B)."""

CLAIM = 0.5
"""Confidence at or above which an effect is claimed."""

SEARCHED = ("coulomb_friction", "viscous_damping", "armature", "gain_mismatch", "delay", "lag",
            "torque_limit", "encoder_offset", "payload_mass", "contact_softness",
            "contact_friction", "backlash")  # fmt: skip
NOT_SEARCHED: tuple[str, ...] = ()

OFFSET_PROBE = 0.05
"""Encoder offset [rad] used to test whether offsets show in a log at all."""

MIN_FIT_SAMPLES = 50
"""Fewest state samples in the fit part of a log (the residual network and the signature
plots need some too)."""

PARTIAL = 3.0
"""A claimed effect whose joints keep more than this multiple of their noise floor (with every
claimed effect in the model) explains only part of their error, and the report says so. It is
a statement, not a confidence: on a gantry log of leg drives at 70 % of kp with kd kept, the
shared gain (0.70, the right kp; the vocabulary's gain scales kd too) kept 9 times the floor,
and a knee cable's spring claimed as Coulomb friction on a floor log 12 times; both removed
the same share of their joints' error on B (0.72 and 0.76), so nothing here tells an
incomplete effect from a proxy, and lowering the confidence by the remainder dropped the right
gain and tripled the held-out error (3.4 -> 10.2 mrad)."""

SCREEN = 0.1
"""A candidate scored on B must remove at least this share of its joints' error on A."""
_SCREEN_KEEP = 4

_SECANT_STEPS = 6
_SECANT_TOL = 1e-4
"""A pair's secant search stops when its next step is shorter than this share of its interval
(1e-3 left a 0.8 kg payload at 0.785 kg and the held-out error at 0.45 against 0.31 mrad)."""


@dataclass(frozen=True, kw_only=True)
class Finding:
    """An effect on one joint or body.

    Attributes:
        effect: Vocabulary name.
        target: Joint name, or body name for a body effect (``payload_mass``,
            ``contact_softness``, ``contact_friction``), or the name of a group that shares one value
            (``limb_of_J``: the joints of the limb that starts at joint J; ``limbs_of_J+K``;
            ``all_joints``; ``all_soles``: every body with a sole), whose joints or bodies
            are ``targets``.
        joints: The joints whose error it was scored on.
        value: Identified parameter: the amount added to the nominal model (friction N m,
            damping N m s/rad, armature kg m^2, payload kg), the delay or filter time constant
            [s], the torque limit [N m], the encoder offset [rad], or the applied / commanded
            gain ratio.
        confidence: In [0, 1]; >= 0.5 is a claim.
        error_reduction: Share of its joints' k-step error removed on unseen fit data (B).
        targets: The joints (bodies) of a group effect (empty for one joint or body).
        stands_out: The RMS position error its joints keep (on B) with every claimed effect in
            the model, in multiples of their noise floors (:func:`noise_floor`): above
            :data:`PARTIAL`, it explains only part of their error (``None``: not scored with
            the final correction).
    """

    effect: str
    target: str
    joints: tuple[str, ...]
    value: float
    confidence: float
    error_reduction: float
    targets: tuple[str, ...] = ()
    stands_out: float | None = None

    @property
    def partial(self) -> bool:
        """Its joints still stand out with it in the model: something else acts there."""
        return self.stands_out is not None and self.stands_out > PARTIAL

    @property
    def acts_on(self) -> tuple[str, ...]:
        """The joints (or the body) the effect acts on: its group's, or its target."""
        return self.targets or (self.target,)

    @property
    def on_body(self) -> bool:
        return EFFECTS[self.effect].target == "body"


@dataclass(frozen=True, kw_only=True)
class Statement:
    """An effect the log cannot decide, and why."""

    effect: str
    joints: tuple[str, ...]
    reason: str


@dataclass(kw_only=True)
class Diagnosis:
    """The outcome: findings in the order they were found, rejected candidates after.

    Attributes:
        findings: Claimed effects first (in the order found), then rejected candidates.
        correction: The nominal prediction model with the claimed effects added.
        not_identifiable: Effects the log's excitation cannot reveal.
    """

    findings: list[Finding] = field(default_factory=list)
    correction: Correction | None = None
    not_identifiable: list[Statement] = field(default_factory=list)

    @property
    def claimed(self) -> list[Finding]:
        return [f for f in self.findings if f.confidence >= CLAIM]


@dataclass(frozen=True, kw_only=True)
class _Pair:
    """A candidate: one effect on one joint (or body), fitted on some joints' residual."""

    effect: str
    index: int  # Joint index, or body id for a body effect.
    joints: np.ndarray  # Joint indices its residual is fitted and scored on.
    lo: float
    hi: float
    none: float  # The value that adds nothing.
    probe: float  # A first, typical value.
    group: tuple[int, ...] = ()  # Joints (bodies) one shared value acts on; empty: ``index``.
    label: str = ""  # The group's name in a finding.

    def apply(self, c: Correction, value: float) -> None:
        """Add the effect at ``value`` to ``c`` in place (on every joint of its group)."""
        for i in self.group or (self.index,):
            apply_effect(c, self.effect, i, value)


def _chain(model: mujoco.MjModel, body: int) -> np.ndarray:
    """The log's joints between the fixed base and a body (those a load on it acts on)."""
    where = {int(j): i for i, j in enumerate(JointMap.of(model).jid)}
    out = []
    while body > 0:
        j0, n = model.body_jntadr[body], model.body_jntnum[body]
        out += [where[j] for j in range(j0, j0 + n) if j in where]
        body = int(model.body_parentid[body])
    return np.array(sorted(out), dtype=int)


def _limb_end(model: mujoco.MjModel, body: int) -> int:
    """The last body of the limb below ``body`` (the first child at every branch)."""
    while True:
        children = np.flatnonzero(model.body_parentid == body)
        children = children[children != body]
        if children.size == 0:
            return body
        body = int(children[0])


def _peak_torque(log: RobotLog) -> np.ndarray:
    """Largest commanded PD torque per joint over the log (from the logged state)."""
    idx = log.command_index(log.t)
    tau = log.kp[idx] * (log.cmd_q[idx] - log.q) + log.kd[idx] * (log.cmd_qd[idx] - log.qd)
    return np.abs(tau + log.cmd_tau[idx]).max(axis=0)


PAYLOAD_MAX = 15.0
"""Largest payload searched [kg]: a backpack or a tool on a link (5 before 2026-12-03,
which a 6 kg backpack passed)."""

_SINGLE: dict[str, tuple[float, float, float, float]] = {
    "coulomb_friction": (0.0, 20.0, 0.0, 1.0),
    "viscous_damping": (0.0, 10.0, 0.0, 0.5),
    "armature": (0.0, 0.5, 0.0, 0.02),
    "gain_mismatch": (0.3, 3.0, 1.0, 0.85),
    "delay": (0.0, 0.05, 0.0, 0.01),
    "lag": (0.0, 0.1, 0.0, 0.01),
}
"""Search interval, "no effect" value and first probe of each joint effect."""


def _pairs(
    model: mujoco.MjModel, joints: list[int], peak: np.ndarray, reach: np.ndarray
) -> list[_Pair]:
    """Candidate pairs for the standing-out joints. ``reach[i, j]``: an offset of joint i's
    encoder shows in joint j's predictions."""
    out: list[_Pair] = []
    bodies: set[int] = set()
    offsets: set[int] = set()
    soles = [b for b in range(model.nbody) if soft_geoms(model, b).size]
    slides = [b for b in range(model.nbody) if floor_colliders(model, b).size]
    for j in joints:
        one = np.array([j])
        spec = dict(_SINGLE)
        if peak[j] > 0:  # A drive that never pushes has no torque limit to find.
            # Two decades below the peak: a drive that saturates lags its command, which
            # inflates the commanded torque the peak is computed from (a 3.5 N m knee limit
            # lay below 5 % of its peak on a 12 s log).
            spec["torque_limit"] = (0.01 * peak[j], peak[j], peak[j], 0.8 * peak[j])
        for effect, (lo, hi, none, probe) in spec.items():
            out.append(_Pair(effect=effect, index=j, joints=one, lo=lo, hi=hi, none=none,
                             probe=probe))  # fmt: skip
        # An encoder offset anywhere that shows at this joint (through gravity, often on
        # another joint of the limb than its own).
        for i in np.flatnonzero(reach[:, j]):
            if int(i) not in offsets:
                offsets.add(int(i))
                out.append(_Pair(effect="encoder_offset", index=int(i),
                                 joints=np.flatnonzero(reach[i]), lo=-0.2, hi=0.2, none=0.0,
                                 probe=0.02))  # fmt: skip
        body = int(model.jnt_bodyid[JointMap.of(model).jid[j]])
        for b in (body, _limb_end(model, body)):
            if b not in bodies:
                bodies.add(b)
                out.append(_Pair(effect="payload_mass", index=b, joints=_chain(model, b),
                                 lo=0.0, hi=PAYLOAD_MAX, none=0.0, probe=0.5))  # fmt: skip
                if b in soles:  # A sole (floating-base logs have a floor).
                    out.append(_sole_pair(model, (b,), "contact_softness"))
                if b in slides:
                    out.append(_sole_pair(model, (b,), "contact_friction"))
    # The floor carries the whole robot: a softer or slipperier floor (every sole alike) is a
    # candidate whatever joint stands out (a sliding foot shows in the waist's and the arms'
    # predictions as much as in the legs').
    if len(soles) > 1:
        out.append(_sole_pair(model, tuple(soles), "contact_softness"))
    if len(slides) > 1:
        out.append(_sole_pair(model, tuple(slides), "contact_friction"))
    return out


def _sole_pair(model: mujoco.MjModel, soles: tuple[int, ...], effect: str) -> _Pair:
    """The ``contact_softness`` or ``contact_friction`` candidate of one sole, or of several
    sharing one value (the floor's; the group's label is ``all_soles``), scored on the joints
    that carry them."""
    first = soles[0]
    if effect == "contact_softness":
        now = float(model.geom_solref[soft_geoms(model, first)[0], 0])
        lo, hi = max(2 * float(model.opt.timestep), SOFTNESS_RANGE[0]), SOFTNESS_RANGE[1]
        probe = min(2 * now, hi)
    else:
        now = float(model.geom_friction[floor_colliders(model, first)[0], 0])
        lo, hi = FRICTION_LOW, max(now, FRICTION_LOW * 1.5)
        probe = 0.5 * now
    joints = np.unique(np.concatenate([_chain(model, b) for b in soles]))
    group = soles if len(soles) > 1 else ()
    return _Pair(effect=effect, index=first, joints=joints, lo=lo, hi=hi, none=now,
                 probe=probe, group=group, label="all_soles" if group else "")  # fmt: skip


SOFTNESS_RANGE = (0.005, 0.2)
"""Contact time constants searched [s] (MuJoCo's default is 0.02; no lower than two physics
steps, which MuJoCo enforces)."""

FRICTION_LOW = 0.02
"""The lowest sliding friction searched (wet ice); the highest is the model's own. A floor
that grips more than the model's shows only where the model's foot slides, and a model's
friction is rarely set low enough for that; a slipperier one shows wherever a loaded foot
slides in the log and not in the model."""

GROUPED = ("delay", "gain_mismatch")
"""Effects also searched as one value shared by a group of joints (a latency of the whole
robot's bus, or of one limb's; drives of one kind weaker on both sides): one hypothesis for
many joints, which the error reduction prefers when the joints share it, instead of the same
effect claimed joint by joint."""


def _mirror(name: str, names: tuple[str, ...]) -> int | None:
    """The joint on the other side (``left`` and ``right`` swapped in the name), if any."""
    import re

    swap = {"left": "right", "right": "left", "Left": "Right", "Right": "Left", "LEFT": "RIGHT",
            "RIGHT": "LEFT", "l_": "r_", "r_": "l_", "L_": "R_", "R_": "L_"}  # fmt: skip
    other = re.sub(r"left|right|Left|Right|LEFT|RIGHT|^[lLrR]_", lambda m: swap[m.group(0)], name)
    return names.index(other) if other != name and other in names else None


def _group_pairs(model: mujoco.MjModel, joints: list[int], names: tuple[str, ...]) -> list[_Pair]:
    """Group candidates for the standing-out joints: each one's limb (the joints of the
    chain from the base that starts at the limb's first joint), the limbs of all of them
    together, each one with its mirror joint (:func:`_mirror`), and every joint; groups of one
    joint are the single candidates already."""
    jmap = JointMap.of(model)
    chains = [_chain(model, int(model.jnt_bodyid[jmap.jid[j]])) for j in range(len(names))]
    root = np.array([c[0] if c.size else j for j, c in enumerate(chains)])
    limb_of = {int(j): tuple(int(i) for i in np.flatnonzero(root == root[j])) for j in joints}
    groups: dict[tuple[int, ...], str] = {}
    for j in joints:
        groups.setdefault(limb_of[j], f"limb_of_{names[root[j]]}")
    starts = sorted({int(root[j]) for j in joints})
    if len(starts) > 1:
        both = tuple(sorted({i for j in joints for i in limb_of[j]}))
        groups.setdefault(both, "limbs_of_" + "+".join(names[i] for i in starts))
    for j in joints:  # The same joint on both sides (both knees' drives).
        k = _mirror(names[j], names)
        if k is not None:
            groups.setdefault(tuple(sorted((j, k))), f"both_{names[min(j, k)]}")
    groups.setdefault(tuple(range(len(names))), "all_joints")
    out = []
    for group, label in groups.items():
        if len(group) < 2:
            continue
        for effect in GROUPED:
            lo, hi, none, probe = _SINGLE[effect]
            out.append(_Pair(effect=effect, index=group[0], joints=np.array(group), lo=lo,
                             hi=hi, none=none, probe=probe, group=group, label=label))  # fmt: skip
    return out


POSITION_SCORED = ("contact_friction",)
"""Effects scored on joint positions only, not on drive torques. A foot that slides in
a window slides from the state the window starts in, and whether it sticks or slips there
hangs on the foot's velocity, which the base estimate gives to a few mm/s: the torques,
set by velocities, are then off by spikes where the slip starts and stops, while the
positions integrate over them. Measured on a noise-free 8 s standing log on a floor of
friction 0.1: the true friction brought the held-out position error from 2.31 to 1.11 mrad
and the torque error from 0.119 up to 0.145 N m (``benchmarks/sysid_floor_checks.py --only
slip_truth``)."""


def _channels(p: _Pair, n: int) -> list[int]:
    """The residual channels (0: positions, 1: torques) pair ``p`` is scored on."""
    return [0] if p.effect in POSITION_SCORED else list(range(n))


NONE_SHARE = 0.01
"""An effect whose value lies within this share of its search interval from "no effect" has
no size and is not claimed."""


def _sized(p: _Pair, value: float) -> bool:
    """Whether ``value`` is an effect at all (see :data:`NONE_SHARE`)."""
    return abs(value - p.none) > NONE_SHARE * (p.hi - p.lo)


def _at_bound(p: _Pair, value: float) -> bool:
    """Whether ``value`` sits on the far end of its search interval (within
    :data:`NONE_SHARE` of it): the data want more of the effect than any plausible robot has,
    so it stands in for something else (an effect outside the vocabulary, or a base state the
    log cannot pin down), and it is not claimed. On floating-base logs a hip's armature
    pinned at its bound of 0.5 kg m^2 was claimed (confidence 0.53-0.67) beside a torso
    payload and in place of an ankle's friction; on the backpack's gantry log the torso
    payload at its bound of 15 kg stood in for a 6 kg backpack with its CoM 8 cm behind."""
    span = NONE_SHARE * (p.hi - p.lo)
    return any(abs(value - b) <= span and abs(b - p.none) > span for b in (p.lo, p.hi))


def _fit(
    predictor: _Scorer,
    bases: list[Correction],
    pairs: list[_Pair],
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
            for k, (i, v) in enumerate(zip(smooth, _fit(predictor, [bases[i] for i in smooth],
                                       [pairs[i] for i in smooth], firsts, part), strict=True)):  # fmt: skip
                out[i], shares[i] = v, part[k]
        if removed is not None:
            removed[:] = shares
        return out

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


class _Scorer:
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
    predictor: _Scorer,
    bases: list[Correction],
    pairs: list[_Pair],
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


def _refit(
    predictor: _Scorer, start: Correction, kept: list[tuple[_Pair, float]], iters: int = 5
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


def _polish(predictor: _Scorer, start: Correction, kept: list[tuple[_Pair, float]]) -> list[float]:
    """Refit the kept effects: alone from where they are, or together (:func:`_refit`)."""
    if len(kept) > 1:
        return _refit(predictor, start, kept)
    ((p, v),) = kept
    return _fit(predictor, [start], [p], first=[v])


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


def diagnose_log(
    correction: Correction | mujoco.MjModel,
    log: RobotLog,
    *,
    horizon: float = 0.5,
    max_effects: int = 4,
    candidates_per_round: int = 3,
    backlash_model: Callable[[tuple[str, ...]], mujoco.MjModel] | None = None,
    base_track: BaseEstimate | None = None,
) -> Diagnosis:
    """Find and size the effects the model lacks, by a cross-validated output-error search.

    The first :data:`FIT_END` (70%) of the log is for fitting, its k-step windows alternating
    between A (fit) and B (score) (:func:`fit_predictors`); the last 30% (H) is held out for
    the report. Each round:

    1. The joints whose k-step prediction error on A stands out (more than twice the median
       joint: most joints lack nothing, so the median is the noise floor) are the candidates.
    2. Each candidate joint is paired with every effect that can act on it: the joint effects
       of :data:`SEARCHED`, and ``payload_mass`` on the body the joint moves and on the end of
       its limb. Every pair's parameter is fitted on A by a bounded secant (Gauss-Newton)
       search on the residual of the joints the effect can reach (:func:`_fit`); all pairs of
       a round are evaluated together, as one batched rollout per iteration.
    3. Each pair's fit is scored on B: the share of the error of its joints that it removes
       (``error_reduction``), and the error it removes from the whole robot. The pair removing
       the most is kept if it removes at least :data:`MIN_REDUCTION` of its joints' error; its
       confidence grows with that share and with the evidence against the best rival
       explanation of the same joints (the log-likelihood ratio of the two on B under the
       noise floor): two effects that explain a joint equally well are both left unclaimed. A
       claimed effect joins the correction and the next round starts.

    Encoder offsets are searched only on joints where an offset would show in the log
    (:func:`offset_reach`): a hanging robot tracks its (offset) encoder, so an offset moves the
    joint only through the change in gravity torque. Where a large offset changes the
    predictions less than the noise does, the diagnosis says the offset is not identifiable
    from this log (:attr:`Diagnosis.not_identifiable`), and does not guess.

    Backlash changes the model's structure (a second hinge per joint: the link side, free
    within the play), so its candidates run on their own model (given by ``backlash_model``),
    with the play joint starting each window at the end the drive pushes against. Torque limits
    and backlash are fitted by a grid and a golden-section search (their error is flat, then
    kinked: :func:`_grid_fit`), the rest by secant search; effects that share joints are
    refitted together (Gauss-Newton, :func:`_refit`).

    Args:
        correction: The nominal fixed-base prediction model (see
            :func:`~humimic.sim.models.prediction_spec`); it is not changed.
        log: The log (its joints in the model's order).
        horizon: k-step window [s].
        max_effects: Most effects claimed.
        candidates_per_round: Most joints examined per round.
        backlash_model: The prediction model with play joints on the given joints (see
            :func:`backlash_models`); without it backlash is not searched.
        base_track: A floating-base log's base estimate, when the caller has one already
            (:attr:`~humimic.real2sim.residual.Predictor.track`); default: estimated here.

    Raises:
        InputError: A log the diagnosis cannot use (see :func:`fit_predictors`), or a
            ``horizon`` that is not a positive number of seconds.
    """
    base = (correction if isinstance(correction, Correction) else Correction.of(correction)).copy()
    model = base.model
    names = log.joint_names
    effort = log.effort is not None
    # Fits use joint positions only: a logged drive torque jumps with every command step, so
    # its error is discontinuous in a delay (a sample falls before or after the delayed step)
    # and would trap the search. Scoring on B uses both.
    pred_fit, pred_a, pred_b = fit_predictors(model, log, horizon, base_track)
    fit_a = _Scorer(pred_fit, False)
    score_a = _Scorer(pred_a, effort)
    score_b = _Scorer(pred_b, effort)
    floor_q = float(np.median(score_a.calibrate(base)))  # The position noise floor [rad].
    score_b.sigma = score_a.sigma
    fit_a.sigma = score_a.sigma[:1]
    peak = _peak_torque(log)

    reach = offset_reach(fit_a.predictor, base) > 2.0 * floor_q
    diagnosis = Diagnosis(correction=base)
    hidden = np.flatnonzero(~reach.any(axis=1))
    if hidden.size:
        diagnosis.not_identifiable.append(
            Statement(
                effect="encoder_offset",
                joints=tuple(names[j] for j in hidden),
                reason=(
                    f"an encoder offset of {OFFSET_PROBE} rad on any of these joints changes "
                    f"no joint's predicted position by more than twice the noise floor "
                    f"({floor_q * 1e3:.2f} mrad): the drives track the encoder, and this log's "
                    "gravity loads do not reveal where it reads zero. Calibrate these offsets "
                    "against a mechanical reference (or excite them under load)."
                ),
            )
        )

    findings: list[Finding] = []
    rejected: list[Finding] = []
    kept: list[tuple[_Pair, float]] = []
    nominal = base
    plays: tuple[str, ...] = ()  # Joints whose claimed backlash the model carries.

    def start_for(joints: tuple[str, ...]) -> Correction:
        """The nominal correction, on a model with play joints on ``joints``."""
        if not joints:
            return nominal
        assert backlash_model is not None
        c = Correction.of(backlash_model(joints))
        c.delay[:], c.offset[:], c.gain_scale[:] = nominal.delay, nominal.offset, nominal.gain_scale
        return c

    def with_kept(c0: Correction) -> Correction:
        """``c0`` with the kept effects at their current values."""
        c = c0.copy()
        for q, v in kept:
            q.apply(c, v)
        return c

    start = base
    for _ in range(max_effects):
        if kept:  # The effects so far at their best together, before crediting a new one.
            values_now = _polish(fit_a, start, kept)
            kept = [(q, v) for (q, _), v in zip(kept, values_now, strict=True)]
            findings = [replace(f, value=v) for f, v in zip(findings, values_now, strict=True)]
            base = with_kept(start)
            model = base.model
        err_a = score_a.per_joint(base)
        order = np.argsort(-err_a)
        # A joint that carries an effect already must stand out more: what an imperfect fit
        # leaves is more likely than a second effect there.
        # A group's shared value is no reason to doubt a joint of it.
        busy = {int(j) for q, _ in kept if not q.group for j in q.joints}
        joints = [int(j) for j in order[:candidates_per_round]
                  if err_a[j] > (3.0 if j in busy else 2.0)]  # fmt: skip
        if not joints:
            break
        pairs = _pairs(model, joints, peak, reach) + _group_pairs(model, joints, names)
        bases = [base] * len(pairs)
        if backlash_model is not None:  # Play in a joint: a model with one more hinge.
            for j in joints:
                if names[j] not in plays:
                    bases.append(with_kept(start_for((*plays, names[j]))))
                    pairs.append(_Pair(effect="backlash", index=j, joints=np.array([j]),
                                       lo=0.002, hi=0.2, none=0.0, probe=0.02))  # fmt: skip
        shares: list[float] = []
        values = _fit(fit_a, bases, pairs, removed=shares)
        # Only the pairs that remove a part of their joints' error on A are scored on B, and
        # always the best few of them, the rivals the confidence weighs: a pair that removes
        # less than SCREEN of its joints' error where it was fitted does not remove
        # MIN_REDUCTION of it on B. Pairs on the joints of an effect kept already are all
        # scored: on top of that effect they remove little until refitted with it (below).
        top = set(np.argsort(-np.array(shares))[:_SCREEN_KEEP].tolist())
        taken = [int(j) for q, _ in kept if not q.group for j in q.joints]
        keep = [i for i, (p, r) in enumerate(zip(pairs, shares, strict=True))
                if r >= SCREEN or i in top or np.intersect1d(p.joints, taken).size]  # fmt: skip
        pairs, bases = [pairs[i] for i in keep], [bases[i] for i in keep]
        values = [values[i] for i in keep]
        # A pair on joints that already carry an effect is refitted together with it: the
        # effect found first took more than its share of their error.
        revised = [[v for _, v in kept] for _ in pairs]
        cs = []
        for i, p in enumerate(pairs):
            if p.effect == "backlash":
                c = bases[i].copy()
                p.apply(c, values[i])
                cs.append(c)
                continue
            # (Not with a group: its one value spreads over many joints, and refitting it
            # with every candidate on any of them would cost a search per candidate.)
            shared = [k for k, (q, _) in enumerate(kept)
                      if not q.group and np.intersect1d(q.joints, p.joints).size]  # fmt: skip
            if shared:
                others = start.copy()
                for k, (q, v) in enumerate(kept):
                    if k not in shared:
                        q.apply(others, v)
                group = [kept[k] for k in shared] + [(p, values[i])]
                fitted = _refit(fit_a, others, group)
                for k, v in zip(shared, fitted[:-1], strict=True):
                    revised[i][k] = v
                values[i] = fitted[-1]
            c = start.copy()
            for (q, _), v in zip(kept, revised[i], strict=True):
                q.apply(c, v)
            p.apply(c, values[i])
            cs.append(c)
        res_b = score_b.run([base, *cs])
        gains, reds = [], []
        for i, p in enumerate(pairs):
            ch = _channels(p, res_b.shape[-1])
            sse0 = np.sum(res_b[0][..., ch] ** 2, axis=(0, 1, 3))  # Per joint, before.
            sse = np.sum(res_b[1 + i][..., ch] ** 2, axis=(0, 1, 3))
            gains.append(float(np.sum(sse0 - sse)))
            reds.append(1.0 - float(np.sum(sse[p.joints]) / max(np.sum(sse0[p.joints]), 1e-30)))
        order_p = np.argsort(-np.array(gains))
        k = int(order_p[0])
        best, red = pairs[k], reds[k]
        rival = max([gains[i] for i in order_p[1:]
                     if np.intersect1d(pairs[i].joints, best.joints).size], default=0.0)  # fmt: skip
        # How much better the best explains B than its best rival, as a log-likelihood ratio
        # under the noise floors, counting each window and channel once (samples inside a
        # window are not independent: a k-step error accumulates).
        evidence = (gains[k] - max(rival, 0.0)) / (
            2 * score_b.samples * len(_channels(best, res_b.shape[-1]))
        )
        conf = float(np.clip(red / (2 * MIN_REDUCTION), 0.0, 1.0)
                     * (0.4 + 0.6 * (1.0 - np.exp(-evidence))))  # fmt: skip

        def finding(
            i: int, confidence: float, pairs=pairs, values=values, reds=reds, model=model
        ) -> Finding:
            p = pairs[i]
            on_body = EFFECTS[p.effect].target == "body"
            name = (lambda k: model.body(k).name) if on_body else (lambda k: names[k])
            return Finding(effect=p.effect, target=p.label or name(p.index),
                           joints=tuple(names[j] for j in p.joints), value=values[i],
                           confidence=confidence, error_reduction=reds[i],
                           targets=tuple(name(k) for k in p.group))  # fmt: skip

        for i in order_p[1:4]:  # The best rivals, for the record.
            rival_conf = min(conf, float(np.clip(reds[i] / (2 * MIN_REDUCTION), 0, 1)))
            rival_conf *= 0.49  # A rival is never claimed.
            rejected.append(finding(int(i), rival_conf))
        if red < MIN_REDUCTION or conf < CLAIM or gains[k] <= 0:
            rejected.append(finding(k, min(conf, CLAIM - 0.01)))
            break
        base = cs[k]  # Keep it: the correction carries the effect.
        model = base.model
        if best.effect == "backlash":
            plays = (*plays, names[best.index])
            start = start_for(plays)
        kept = [(q, v) for (q, _), v in zip(kept, revised[k], strict=True)]
        findings = [replace(f, value=v) for f, v in zip(findings, revised[k], strict=True)]
        findings.append(finding(k, conf))
        kept.append((pairs[k], values[k]))
    # An effect is claimed only if, with all the others, it leaves little of its joints' error:
    # one that removes half of a joint's error and leaves the rest is a proxy for something
    # else (an effect outside the vocabulary), not a finding.
    if findings:
        values = _refit(fit_a, start, kept)
        kept = [(p, v) for (p, _), v in zip(kept, values, strict=True)]
        findings = [replace(f, value=v) for f, v in zip(findings, values, strict=True)]
        base = with_kept(start)
        final = score_b.run([start, base])
        # Once corrected, most joints lack nothing: a claimed effect's joints should come down
        # to their noise floor.
        residual_after = final[1][..., 0] * score_b.sigma[0]  # Positions [rad].
        after = np.sqrt(np.mean(residual_after**2, axis=(0, 1)))
        floor_after = noise_floor(score_b.predictor, base, residual_after)
        claimed, unclaimed = [], []
        for f, (p, v) in zip(findings, kept, strict=True):
            ch = _channels(p, final.shape[-1])
            sse0 = float(np.sum(final[0][..., p.joints, :][..., ch] ** 2))
            sse1 = float(np.sum(final[1][..., p.joints, :][..., ch] ** 2))
            noise = float(final[0][..., p.joints, :][..., ch].size)  # One floor squared each.
            left = max(sse1 - noise, 0.0) / max(sse0 - noise, 1e-30)
            conf = f.confidence * float(np.clip(1.0 - 1.5 * left, 0.0, 1.0))
            stands = float(np.sqrt(np.mean((after[p.joints] / floor_after[p.joints]) ** 2)))
            if not _sized(p, v) or _at_bound(p, v):  # Nothing, or a proxy (see the two).
                conf = min(conf, CLAIM - 0.01)
            g = replace(f, confidence=conf, stands_out=stands)
            (claimed if conf >= CLAIM else unclaimed).append((g, p, v))
        if unclaimed:  # Rebuild the correction from the claimed effects only.
            base = start_for(tuple(names[p.index] for _, p, _ in claimed if p.effect == "backlash"))
            base = base.copy()
            for _, p, v in claimed:
                p.apply(base, v)
        findings = [g for g, _, _ in claimed]
        rejected += [
            replace(g, confidence=min(g.confidence, CLAIM - 0.01)) for g, _, _ in unclaimed
        ]
    # Each rejected candidate once (its best showing), and none that was claimed.
    rejected.sort(key=lambda f: -f.confidence)
    seen = {(f.effect, f.target) for f in findings}
    unique = []
    for f in rejected:
        if (f.effect, f.target) not in seen:
            seen.add((f.effect, f.target))
            unique.append(f)
    diagnosis.findings = findings + unique
    diagnosis.correction = base
    return diagnosis
