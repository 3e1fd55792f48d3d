"""Diagnose a robot log: which effects does the simulator lack, where, and how large are they.

:func:`diagnose_log` runs a cross-validated output-error search over the effect vocabulary
(:data:`SEARCHED`) and returns a :class:`Diagnosis`; docs/real2sim.md describes it for users.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from humimic.real2sim.candidates import (
    Candidate,
    at_bound,
    group_candidates,
    is_sized,
    joint_candidates,
    peak_torque,
    scored_channels,
)
from humimic.real2sim.correction import Correction
from humimic.real2sim.fitting import (
    FIT_END,
    OFFSET_PROBE,
    Scorer,
    fit_candidates,
    fit_predictors,
    noise_floor,
    offset_reach,
    polish_kept,
    refit_together,
)
from humimic.real2sim.floating import BaseEstimate
from humimic.real2sim.result import CLAIM
from humimic.real2sim.robotlog import RobotLog
from humimic.sim.effects import EFFECTS

MIN_REDUCTION = 0.4
"""An effect must remove at least this share of its joints' error on unseen data (B)."""

SEARCHED = ("coulomb_friction", "viscous_damping", "armature", "gain_mismatch", "delay", "lag",
            "torque_limit", "encoder_offset", "payload_mass", "contact_softness",
            "contact_friction", "backlash")  # fmt: skip
NOT_SEARCHED: tuple[str, ...] = ()

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
            the model, in multiples of their noise floors (:func:`~humimic.real2sim.fitting.noise_floor`): above
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


class _Search:
    """The state of :func:`diagnose_log`'s search between its rounds: the scorers, the
    effects kept so far (pairs and values, and their findings), the rejected candidates, and
    the corrections they make."""

    def __init__(
        self,
        correction: Correction | mujoco.MjModel,
        log: RobotLog,
        horizon: float,
        backlash_model: Callable[[tuple[str, ...]], mujoco.MjModel] | None,
        base_track: BaseEstimate | None,
    ) -> None:
        base = (
            correction if isinstance(correction, Correction) else Correction.of(correction)
        ).copy()
        self.names = log.joint_names
        self.backlash_model = backlash_model
        effort = log.effort is not None
        # Fits use joint positions only: a logged drive torque jumps with every command step, so
        # its error is discontinuous in a delay (a sample falls before or after the delayed step)
        # and would trap the search. Scoring on B uses both.
        pred_fit, pred_a, pred_b = fit_predictors(base.model, log, horizon, base_track)
        self.fit_a = Scorer(pred_fit, False)
        self.score_a = Scorer(pred_a, effort)
        self.score_b = Scorer(pred_b, effort)
        self.floor_q = float(np.median(self.score_a.calibrate(base)))  # Position floor [rad].
        self.score_b.sigma = self.score_a.sigma
        self.fit_a.sigma = self.score_a.sigma[:1]
        self.peak = peak_torque(log)
        self.reach = offset_reach(self.fit_a.predictor, base) > 2.0 * self.floor_q
        self.diagnosis = Diagnosis(correction=base)
        self._note_hidden_offsets()
        self.findings: list[Finding] = []
        self.rejected: list[Finding] = []
        self.kept: list[tuple[Candidate, float]] = []
        self.nominal = self.start = self.base = base
        self.plays: tuple[str, ...] = ()  # Joints whose claimed backlash the model carries.

    def _note_hidden_offsets(self) -> None:
        """Say which encoder offsets the log cannot show (:func:`~humimic.real2sim.fitting.offset_reach`)."""
        hidden = np.flatnonzero(~self.reach.any(axis=1))
        if not hidden.size:
            return
        self.diagnosis.not_identifiable.append(
            Statement(
                effect="encoder_offset",
                joints=tuple(self.names[j] for j in hidden),
                reason=(
                    f"an encoder offset of {OFFSET_PROBE} rad on any of these joints changes "
                    f"no joint's predicted position by more than twice the noise floor "
                    f"({self.floor_q * 1e3:.2f} mrad): the drives track the encoder, and this "
                    "log's gravity loads do not reveal where it reads zero. Calibrate these "
                    "offsets against a mechanical reference (or excite them under load)."
                ),
            )
        )

    def start_for(self, joints: tuple[str, ...]) -> Correction:
        """The nominal correction, on a model with play joints on ``joints``."""
        if not joints:
            return self.nominal
        assert self.backlash_model is not None
        c = Correction.of(self.backlash_model(joints))
        n = self.nominal
        c.delay[:], c.offset[:], c.gain_scale[:] = n.delay, n.offset, n.gain_scale
        return c

    def with_kept(self, c0: Correction) -> Correction:
        """``c0`` with the kept effects at their current values."""
        c = c0.copy()
        for q, v in self.kept:
            q.apply(c, v)
        return c

    def _set_kept_values(self, values: list[float]) -> None:
        self.kept = [(q, v) for (q, _), v in zip(self.kept, values, strict=True)]
        self.findings = [replace(f, value=v) for f, v in zip(self.findings, values, strict=True)]

    def round(self, candidates_per_round: int) -> bool:
        """One round: fit the candidates of the joints that stand out, score them on B, and
        claim the best or stop. Returns whether the search goes on."""
        if self.kept:  # The effects so far at their best together, before crediting a new one.
            self._set_kept_values(polish_kept(self.fit_a, self.start, self.kept))
            self.base = self.with_kept(self.start)
        model = self.base.model
        joints = self._candidate_joints(candidates_per_round)
        if not joints:
            return False
        pairs, bases = self._candidate_pairs(model, joints)
        shares: list[float] = []
        values = fit_candidates(self.fit_a, bases, pairs, removed=shares)
        pairs, bases, values = self._screen(pairs, bases, values, shares)
        revised, cs = self._corrections(pairs, bases, values)
        return self._choose(model, pairs, values, revised, cs)

    def _candidate_joints(self, n: int) -> list[int]:
        """The joints whose error on A stands out (twice the median; three times where an
        effect is kept already: what an imperfect fit leaves is more likely than a second
        effect there; a group's shared value is no reason to doubt a joint of it)."""
        err_a = self.score_a.per_joint(self.base)
        order = np.argsort(-err_a)
        busy = {int(j) for q, _ in self.kept if not q.group for j in q.joints}
        return [int(j) for j in order[:n] if err_a[j] > (3.0 if j in busy else 2.0)]

    def _candidate_pairs(
        self, model: mujoco.MjModel, joints: list[int]
    ) -> tuple[list[Candidate], list[Correction]]:
        """Every effect that can act on ``joints``, each with the correction it is fitted on
        (backlash: a model with one more hinge)."""
        names = self.names
        pairs = joint_candidates(model, joints, self.peak, self.reach) + group_candidates(
            model, joints, names
        )
        bases = [self.base] * len(pairs)
        if self.backlash_model is not None:  # Play in a joint: a model with one more hinge.
            for j in joints:
                if names[j] not in self.plays:
                    bases.append(self.with_kept(self.start_for((*self.plays, names[j]))))
                    pairs.append(Candidate(effect="backlash", index=j, joints=np.array([j]),
                                       lo=0.002, hi=0.2, none=0.0, probe=0.02))  # fmt: skip
        return pairs, bases

    def _screen(
        self,
        pairs: list[Candidate],
        bases: list[Correction],
        values: list[float],
        shares: list[float],
    ) -> tuple[list[Candidate], list[Correction], list[float]]:
        """The pairs scored on B: those that remove a part of their joints' error on A, and
        always the best few of them, the rivals the confidence weighs (a pair that removes less
        than :data:`SCREEN` of its joints' error where it was fitted does not remove
        :data:`MIN_REDUCTION` of it on B). Pairs on the joints of an effect kept already are
        all scored: on top of that effect they remove little until refitted with it."""
        top = set(np.argsort(-np.array(shares))[:_SCREEN_KEEP].tolist())
        taken = [int(j) for q, _ in self.kept if not q.group for j in q.joints]
        keep = [i for i, (p, r) in enumerate(zip(pairs, shares, strict=True))
                if r >= SCREEN or i in top or np.intersect1d(p.joints, taken).size]  # fmt: skip
        return [pairs[i] for i in keep], [bases[i] for i in keep], [values[i] for i in keep]

    def _corrections(
        self, pairs: list[Candidate], bases: list[Correction], values: list[float]
    ) -> tuple[list[list[float]], list[Correction]]:
        """Each pair's correction with the kept effects. A pair on joints that already carry
        an effect is refitted together with it (the effect found first took more than its
        share of their error): ``values`` is updated in place, and each pair's values of the
        kept effects are returned beside the corrections."""
        kept = self.kept
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
                others = self.start.copy()
                for k, (q, v) in enumerate(kept):
                    if k not in shared:
                        q.apply(others, v)
                group = [kept[k] for k in shared] + [(p, values[i])]
                fitted = refit_together(self.fit_a, others, group)
                for k, v in zip(shared, fitted[:-1], strict=True):
                    revised[i][k] = v
                values[i] = fitted[-1]
            c = self.start.copy()
            for (q, _), v in zip(kept, revised[i], strict=True):
                q.apply(c, v)
            p.apply(c, values[i])
            cs.append(c)
        return revised, cs

    def _choose(
        self,
        model: mujoco.MjModel,
        pairs: list[Candidate],
        values: list[float],
        revised: list[list[float]],
        cs: list[Correction],
    ) -> bool:
        """Score the pairs on B; claim the one that removes the most if it removes at least
        :data:`MIN_REDUCTION` of its joints' error with confidence :data:`CLAIM` (its best
        rivals are recorded as rejected). Returns whether one was claimed."""
        res_b = self.score_b.run([self.base, *cs])
        gains, reds = [], []
        for i, p in enumerate(pairs):
            ch = scored_channels(p, res_b.shape[-1])
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
            2 * self.score_b.samples * len(scored_channels(best, res_b.shape[-1]))
        )
        conf = float(np.clip(red / (2 * MIN_REDUCTION), 0.0, 1.0)
                     * (0.4 + 0.6 * (1.0 - np.exp(-evidence))))  # fmt: skip

        def finding(i: int, confidence: float) -> Finding:
            return self._finding(model, pairs[i], values[i], reds[i], confidence)

        for i in order_p[1:4]:  # The best rivals, for the record.
            rival_conf = min(conf, float(np.clip(reds[i] / (2 * MIN_REDUCTION), 0, 1)))
            rival_conf *= 0.49  # A rival is never claimed.
            self.rejected.append(finding(int(i), rival_conf))
        if red < MIN_REDUCTION or conf < CLAIM or gains[k] <= 0:
            self.rejected.append(finding(k, min(conf, CLAIM - 0.01)))
            return False
        self.base = cs[k]  # Keep it: the correction carries the effect.
        if best.effect == "backlash":
            self.plays = (*self.plays, self.names[best.index])
            self.start = self.start_for(self.plays)
        self._set_kept_values(revised[k])
        self.findings.append(finding(k, conf))
        self.kept.append((pairs[k], values[k]))
        return True

    def _finding(
        self, model: mujoco.MjModel, p: Candidate, value: float, red: float, confidence: float
    ) -> Finding:
        names = self.names
        on_body = EFFECTS[p.effect].target == "body"
        name = (lambda k: model.body(k).name) if on_body else (lambda k: names[k])
        return Finding(effect=p.effect, target=p.label or name(p.index),
                       joints=tuple(names[j] for j in p.joints), value=value,
                       confidence=confidence, error_reduction=red,
                       targets=tuple(name(k) for k in p.group))  # fmt: skip

    def confirm(self) -> None:
        """Claim an effect only if, with all the others, it leaves little of its joints' error:
        one that removes half of a joint's error and leaves the rest is a proxy for something
        else (an effect outside the vocabulary), not a finding. Once corrected, most joints
        lack nothing: a claimed effect's joints should come down to their noise floor."""
        if not self.findings:
            return
        self._set_kept_values(refit_together(self.fit_a, self.start, self.kept))
        self.base = self.with_kept(self.start)
        final = self.score_b.run([self.start, self.base])
        residual_after = final[1][..., 0] * self.score_b.sigma[0]  # Positions [rad].
        after = np.sqrt(np.mean(residual_after**2, axis=(0, 1)))
        floor_after = noise_floor(self.score_b.predictor, self.base, residual_after)
        claimed, unclaimed = [], []
        for f, (p, v) in zip(self.findings, self.kept, strict=True):
            ch = scored_channels(p, final.shape[-1])
            sse0 = float(np.sum(final[0][..., p.joints, :][..., ch] ** 2))
            sse1 = float(np.sum(final[1][..., p.joints, :][..., ch] ** 2))
            noise = float(final[0][..., p.joints, :][..., ch].size)  # One floor squared each.
            left = max(sse1 - noise, 0.0) / max(sse0 - noise, 1e-30)
            conf = f.confidence * float(np.clip(1.0 - 1.5 * left, 0.0, 1.0))
            stands = float(np.sqrt(np.mean((after[p.joints] / floor_after[p.joints]) ** 2)))
            if not is_sized(p, v) or at_bound(p, v):  # Nothing, or a proxy (see the two).
                conf = min(conf, CLAIM - 0.01)
            g = replace(f, confidence=conf, stands_out=stands)
            (claimed if conf >= CLAIM else unclaimed).append((g, p, v))
        if unclaimed:  # Rebuild the correction from the claimed effects only.
            plays = tuple(self.names[p.index] for _, p, _ in claimed if p.effect == "backlash")
            self.base = self.start_for(plays).copy()
            for _, p, v in claimed:
                p.apply(self.base, v)
        self.findings = [g for g, _, _ in claimed]
        self.rejected += [
            replace(g, confidence=min(g.confidence, CLAIM - 0.01)) for g, _, _ in unclaimed
        ]

    def result(self) -> Diagnosis:
        """The claimed findings, then each rejected candidate once (its best showing) and
        none that was claimed; the correction with the claimed effects."""
        rejected = sorted(self.rejected, key=lambda f: -f.confidence)
        seen = {(f.effect, f.target) for f in self.findings}
        unique = []
        for f in rejected:
            if (f.effect, f.target) not in seen:
                seen.add((f.effect, f.target))
                unique.append(f)
        self.diagnosis.findings = self.findings + unique
        self.diagnosis.correction = self.base
        return self.diagnosis


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
    between A (fit) and B (score) (:func:`~humimic.real2sim.fitting.fit_predictors`); the last 30% (H) is held out for
    the report. Each round:

    1. The joints whose k-step prediction error on A stands out (more than twice the median
       joint: most joints lack nothing, so the median is the noise floor) are the candidates.
    2. Each candidate joint is paired with every effect that can act on it: the joint effects
       of :data:`SEARCHED`, and ``payload_mass`` on the body the joint moves and on the end of
       its limb. Every pair's parameter is fitted on A by a bounded secant (Gauss-Newton)
       search on the residual of the joints the effect can reach (:func:`~humimic.real2sim.fitting._fit`); all pairs of
       a round are evaluated together, as one batched rollout per iteration.
    3. Each pair's fit is scored on B: the share of the error of its joints that it removes
       (``error_reduction``), and the error it removes from the whole robot. The pair removing
       the most is kept if it removes at least :data:`MIN_REDUCTION` of its joints' error; its
       confidence grows with that share and with the evidence against the best rival
       explanation of the same joints (the log-likelihood ratio of the two on B under the
       noise floor): two effects that explain a joint equally well are both left unclaimed. A
       claimed effect joins the correction and the next round starts.

    Encoder offsets are searched only on joints where an offset would show in the log
    (:func:`~humimic.real2sim.fitting.offset_reach`): a hanging robot tracks its (offset) encoder, so an offset moves the
    joint only through the change in gravity torque. Where a large offset changes the
    predictions less than the noise does, the diagnosis says the offset is not identifiable
    from this log (:attr:`Diagnosis.not_identifiable`), and does not guess.

    Backlash changes the model's structure (a second hinge per joint: the link side, free
    within the play), so its candidates run on their own model (given by ``backlash_model``),
    with the play joint starting each window at the end the drive pushes against. Torque limits
    and backlash are fitted by a grid and a golden-section search (their error is flat, then
    kinked: :func:`~humimic.real2sim.fitting._grid_fit`), the rest by secant search; effects that share joints are
    refitted together (Gauss-Newton, :func:`~humimic.real2sim.fitting._refit`).

    Args:
        correction: The nominal fixed-base prediction model (see
            :func:`~humimic.sim.models.prediction_spec`); it is not changed.
        log: The log (its joints in the model's order).
        horizon: k-step window [s].
        max_effects: Most effects claimed.
        candidates_per_round: Most joints examined per round.
        backlash_model: The prediction model with play joints on the given joints (see
            :func:`~humimic.real2sim.fitting.backlash_models`); without it backlash is not searched.
        base_track: A floating-base log's base estimate, when the caller has one already
            (:attr:`~humimic.real2sim.residual.Predictor.track`); default: estimated here.

    Raises:
        InputError: A log the diagnosis cannot use (see :func:`~humimic.real2sim.fitting.fit_predictors`), or a
            ``horizon`` that is not a positive number of seconds.
    """
    search = _Search(correction, log, horizon, backlash_model, base_track)
    for _ in range(max_effects):
        if not search.round(candidates_per_round):
            break
    search.confirm()
    return search.result()


__all__ = [
    "CLAIM",
    "FIT_END",
    "MIN_REDUCTION",
    "NOT_SEARCHED",
    "PARTIAL",
    "SEARCHED",
    "Diagnosis",
    "Finding",
    "Statement",
    "diagnose_log",
]
