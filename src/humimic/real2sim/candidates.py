"""The candidates of the diagnosis: each an effect of the vocabulary on a joint, a body or a
group of them (:class:`Candidate`), with its search interval, and the joints whose error it is
fitted and scored on.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.real2sim.correction import Correction, apply_effect
from humimic.real2sim.robotlog import RobotLog
from humimic.sim.contacts import floor_colliders, soft_geoms
from humimic.sim.joints import JointMap


@dataclass(frozen=True, kw_only=True)
class Candidate:
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


def peak_torque(log: RobotLog) -> np.ndarray:
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


def joint_candidates(
    model: mujoco.MjModel, joints: list[int], peak: np.ndarray, reach: np.ndarray
) -> list[Candidate]:
    """Candidate pairs for the standing-out joints. ``reach[i, j]``: an offset of joint i's
    encoder shows in joint j's predictions."""
    out: list[Candidate] = []
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
            out.append(Candidate(effect=effect, index=j, joints=one, lo=lo, hi=hi, none=none,
                             probe=probe))  # fmt: skip
        # An encoder offset anywhere that shows at this joint (through gravity, often on
        # another joint of the limb than its own).
        for i in np.flatnonzero(reach[:, j]):
            if int(i) not in offsets:
                offsets.add(int(i))
                out.append(Candidate(effect="encoder_offset", index=int(i),
                                 joints=np.flatnonzero(reach[i]), lo=-0.2, hi=0.2, none=0.0,
                                 probe=0.02))  # fmt: skip
        body = int(model.jnt_bodyid[JointMap.of(model).jid[j]])
        for b in (body, _limb_end(model, body)):
            if b not in bodies:
                bodies.add(b)
                out.append(Candidate(effect="payload_mass", index=b, joints=_chain(model, b),
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


def _sole_pair(model: mujoco.MjModel, soles: tuple[int, ...], effect: str) -> Candidate:
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
    return Candidate(effect=effect, index=first, joints=joints, lo=lo, hi=hi, none=now,
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


def group_candidates(
    model: mujoco.MjModel, joints: list[int], names: tuple[str, ...]
) -> list[Candidate]:
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
            out.append(Candidate(effect=effect, index=group[0], joints=np.array(group), lo=lo,
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


def scored_channels(p: Candidate, n: int) -> list[int]:
    """The residual channels (0: positions, 1: torques) pair ``p`` is scored on."""
    return [0] if p.effect in POSITION_SCORED else list(range(n))


NONE_SHARE = 0.01
"""An effect whose value lies within this share of its search interval from "no effect" has
no size and is not claimed."""


def is_sized(p: Candidate, value: float) -> bool:
    """Whether ``value`` is an effect at all (see :data:`NONE_SHARE`)."""
    return abs(value - p.none) > NONE_SHARE * (p.hi - p.lo)


def at_bound(p: Candidate, value: float) -> bool:
    """Whether ``value`` sits on the far end of its search interval (within
    :data:`NONE_SHARE` of it): the data want more of the effect than any plausible robot has,
    so it stands in for something else (an effect outside the vocabulary, or a base state the
    log cannot pin down), and it is not claimed. On floating-base logs a hip's armature
    pinned at its bound of 0.5 kg m^2 was claimed (confidence 0.53-0.67) beside a torso
    payload and in place of an ankle's friction; on the backpack's gantry log the torso
    payload at its bound of 15 kg stood in for a 6 kg backpack with its CoM 8 cm behind."""
    span = NONE_SHARE * (p.hi - p.lo)
    return any(abs(value - b) <= span and abs(b - p.none) > span for b in (p.lo, p.hi))
