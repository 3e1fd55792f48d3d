"""Diagnose a robot log: which joint-level effect does the simulator lack, and how large is it.

Output-error search (issue 4, second slice). The log is cut in three: A (first 35%) and B
(35-70%) to fit, H (last 30%) held out. Each round:

1. The joints whose k-step prediction error on A stands out (more than twice the median joint)
   are the candidates.
2. For each candidate joint and each effect this slice handles (``coulomb_friction``,
   ``viscous_damping``, ``armature``, ``gain_mismatch``, ``delay``: all expressible by changing
   the compiled model in place; delay needs the control history that
   :func:`~humimic.real2sim.simulate.fixed_base_spec` compiles in), the effect's value is fitted on A (bounded scalar search of that
   joint's k-step error) and scored on B: the share of the joint's error it removes there.
3. The best candidate is kept if it removes at least :data:`MIN_REDUCTION` of the error on B;
   its confidence grows with that share and with its margin over the runner-up effect on the
   same joint (two effects that explain a joint equally well share the credit). It is added to
   the model and the next round starts.

The corrected model is scored on H. Lag, torque limits, encoder offsets, payloads and backlash
are not searched yet; an effect outside the search can be absorbed by one inside it that mimics
it, which is why effects are claimed only on their cross-validated error reduction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.optimize import minimize_scalar

from humimic.real2sim.residual import kstep_error
from humimic.real2sim.robotlog import RobotLog

FIT_END = 0.7
"""The first 70% of a log is used to fit; the rest is held out."""

MIN_REDUCTION = 0.4
"""An effect must remove at least this share of its joint's error on unseen data (B)."""

CLAIM = 0.5
"""Confidence at or above which an effect is claimed."""

SEARCHED = ("coulomb_friction", "viscous_damping", "armature", "gain_mismatch", "delay")


@dataclass(frozen=True, kw_only=True)
class Finding:
    """An effect on one joint.

    Attributes:
        effect: Vocabulary name. joint: Joint name.
        value: Identified parameter: the amount added to the nominal model (friction N m,
            damping N m s/rad, armature kg m^2) or, for ``gain_mismatch``, the gain ratio.
        confidence: In [0, 1]; >= 0.5 is a claim.
        error_reduction: Share of the joint's k-step error removed on unseen fit data (B).
    """

    effect: str
    joint: str
    value: float
    confidence: float
    error_reduction: float


@dataclass(frozen=True, kw_only=True)
class Diagnosis:
    """The outcome: findings in the order they were found, rejected candidates after."""

    findings: list[Finding] = field(default_factory=list)
    gain_scale: np.ndarray | None = None
    """Applied / commanded gains per actuator in the corrected model."""

    @property
    def claimed(self) -> list[Finding]:
        return [f for f in self.findings if f.confidence >= CLAIM]


@dataclass
class _Knob:
    """Changes one effect on one joint of a compiled model (or of the gain scales) in place,
    and undoes it."""

    model: mujoco.MjModel
    gains: np.ndarray
    effect: str
    joint: int
    actuator: int
    saved: tuple[np.ndarray, ...] = ()

    def __post_init__(self) -> None:
        m = self.model
        self.saved = (
            m.dof_frictionloss.copy(), m.dof_damping.copy(), m.dof_armature.copy(),
            self.gains.copy(), m.actuator_delay.copy(),
        )  # fmt: skip

    def set(self, value: float) -> None:
        m, j = self.model, self.joint
        self.restore()
        if self.effect == "coulomb_friction":
            m.dof_frictionloss[j] += value
        elif self.effect == "viscous_damping":
            m.dof_damping[j] += value
        elif self.effect == "armature":
            m.dof_armature[j] += value
        elif self.effect == "gain_mismatch":
            self.gains[self.actuator] *= value
        elif self.effect == "delay":
            m.actuator_delay[self.actuator] = value

    def restore(self) -> None:
        m = self.model
        fl, dp, ar, g, dl = self.saved
        m.dof_frictionloss[:], m.dof_damping[:], m.dof_armature[:] = fl, dp, ar
        self.gains[:] = g
        m.actuator_delay[:] = dl


BOUNDS: dict[str, Callable[[mujoco.MjModel, int], tuple[float, float]]] = {
    "coulomb_friction": lambda m, j: (0.0, 20.0),
    "viscous_damping": lambda m, j: (0.0, 10.0),
    "armature": lambda m, j: (0.0, 0.5),
    "gain_mismatch": lambda m, j: (0.3, 3.0),
    "delay": lambda m, j: (0.0, 0.05),
}
"""Search intervals per effect (friction N m, damping N m s/rad, armature kg m^2, gain ratio)."""


def diagnose_log(
    model: mujoco.MjModel,
    log: RobotLog,
    *,
    horizon: float = 0.5,
    max_effects: int = 3,
    candidates_per_round: int = 3,
) -> Diagnosis:
    """Find and size the joint-level effects the model lacks. ``model`` is changed in place to
    carry the claimed effects (the corrected model); gain mismatches are returned as
    ``Diagnosis.gain_scale`` (the logged gains are applied at prediction time)."""
    names = log.joint_names
    act_of = {int(model.actuator_trnid[a, 0]): a for a in range(model.nu)}
    a_span, b_span = (0.0, FIT_END / 2), (FIT_END / 2, FIT_END)
    gains = np.ones(model.nu)  # Applied / commanded gain per actuator.

    def errors(span: tuple[float, float]) -> np.ndarray:
        return kstep_error(
            model, log, horizon=horizon, span=span, stride=horizon, gain_scale=gains
        ).per_joint

    def joint_error(span: tuple[float, float], j: int, stride: float) -> float:
        del stride
        return float(errors(span)[j])

    findings: list[Finding] = []
    rejected: list[Finding] = []
    for _ in range(max_effects):
        base_a = errors(a_span)
        typical = float(np.median(base_a))
        order = np.argsort(-base_a)
        joints = [int(j) for j in order[:candidates_per_round] if base_a[j] > 2 * typical]
        if not joints:
            break
        scored: list[tuple[float, Finding, _Knob]] = []
        for j in joints:
            before_b = joint_error(b_span, j, horizon)
            per_joint: list[tuple[float, Finding, _Knob]] = []
            for effect in SEARCHED:
                if effect in ("gain_mismatch", "delay") and j not in act_of:
                    continue
                if effect == "delay" and model.actuator_history[act_of[j], 0] < 2:
                    continue  # No control history compiled in: cannot be searched.
                knob = _Knob(model, gains, effect, j, act_of.get(j, -1))
                lo, hi = BOUNDS[effect](model, j)

                def cost(v: float, knob: _Knob = knob, j: int = j) -> float:
                    knob.set(v)
                    return joint_error(a_span, j, horizon)

                res = minimize_scalar(cost, bounds=(lo, hi), method="bounded",
                                      options={"xatol": 1e-3 * (hi - lo), "maxiter": 14})  # fmt: skip
                knob.set(float(res.x))
                after_b = joint_error(b_span, j, horizon)
                knob.restore()
                reduction = 1.0 - after_b / max(before_b, 1e-12)
                per_joint.append(
                    (reduction, Finding(effect=effect, joint=names[j], value=float(res.x),
                                        confidence=0.0, error_reduction=reduction), knob)
                )  # fmt: skip
            per_joint.sort(key=lambda x: -x[0])
            best_red, best, knob = per_joint[0]
            runner = per_joint[1][0] if len(per_joint) > 1 else 0.0
            margin = (best_red - max(runner, 0.0)) / max(best_red, 1e-12)
            conf = float(np.clip(best_red / (2 * MIN_REDUCTION), 0.0, 1.0) * np.clip(
                0.5 + margin, 0.0, 1.0))  # fmt: skip
            best = Finding(effect=best.effect, joint=best.joint, value=best.value,
                           confidence=conf, error_reduction=best_red)  # fmt: skip
            scored.append((best_red, best, knob))
            rejected += [
                Finding(effect=f.effect, joint=f.joint, value=f.value,
                        confidence=float(min(conf, np.clip(r / (2 * MIN_REDUCTION), 0, 1)) * 0.5),
                        error_reduction=r)
                for r, f, _ in per_joint[1:]
            ]  # fmt: skip
        scored.sort(key=lambda x: -x[0])
        red, best, knob = scored[0]
        if red < MIN_REDUCTION or best.confidence < CLAIM:
            rejected.append(best)
            break
        knob.set(best.value)  # Keep it: the corrected model carries the effect.
        findings.append(best)
    rejected.sort(key=lambda f: -f.confidence)
    return Diagnosis(findings=findings + rejected, gain_scale=gains)
