"""The vocabulary of physical effects a robot model can lack (names are part of the report format).

Each effect is one class that adds itself to a model spec (:meth:`Effect.on_spec`, to build a
robot that has it) and to a compiled model (:meth:`Effect.on_model`, to score a value without
recompiling), so an injected effect and an identified one mean the same thing.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.sim.joints import PLAY_SUFFIX, JointMap


@dataclass(kw_only=True)
class Correction:
    """A compiled fixed-base model and the effects that act around it.

    The model's own parameters hold friction, damping, armature, force limits, filter time
    constants and masses; three effects act outside it: a transport delay of the commands, an
    encoder offset (the drive and the log see ``q + offset``) and a gain scale (applied /
    commanded kp, kd).

    Attributes:
        model: Compiled fixed-base model; its joints are the log's joints, in order.
        delay: Transport delay of the commands per actuator [s]. Shape: (nu,).
        offset: Encoder offset per joint [rad]. Shape: (J,).
        gain_scale: Applied / commanded gains per actuator. Shape: (nu,).
    """

    model: mujoco.MjModel
    delay: np.ndarray
    offset: np.ndarray
    gain_scale: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel) -> Correction:
        """The model as it is. Transport delays the model carries natively (actuator
        ``delay``, as in a written model.xml) move to the correction, on a copy of the model:
        predictions start from logged states, which hold no control history."""
        delay = np.asarray(model.actuator_delay, dtype=np.float64).copy()
        if delay.any():
            model = copy.copy(model)
            model.actuator_delay[:] = 0.0
        return cls(model=model, delay=delay, offset=np.zeros(len(JointMap.of(model).names)),
                   gain_scale=np.ones(model.nu))  # fmt: skip

    def copy(self) -> Correction:
        return Correction(model=copy.copy(self.model), delay=self.delay.copy(),
                          offset=self.offset.copy(), gain_scale=self.gain_scale.copy())  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class Effect:
    """One physical effect.

    Attributes:
        name: Report name.
        unit: Unit of its parameter.
        target: What it applies to: ``joint``, or ``body`` (payload).
        expresses: The MuJoCo parameters that express it.
        signature: Its diagnostic signature in the residual.
        sign: Which values are physical: ``signed`` (any finite value), ``nonnegative``
            (0 adds nothing) or ``positive``.
        meaning: What the value is, for messages that refuse one of the wrong sign.
        maximum: Largest accepted value (``None``: no bound).
    """

    name: str
    unit: str
    target: str
    expresses: str
    signature: str
    sign: Literal["signed", "nonnegative", "positive"] = "nonnegative"
    meaning: str = ""
    maximum: float | None = None
    adds_joints: ClassVar[bool] = False
    """Whether the effect adds joints to the model (a model with a fixed joint layout, the
    tracking simulation's, cannot take it)."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        """Add the effect with ``value`` to ``target`` (a joint, or a body) of a spec."""
        raise NotImplementedError

    def on_model(self, c: Correction, index: int, value: float) -> None:
        """Add the effect with ``value`` to a compiled model in place (``index``: a joint of
        the log, or a body id for a body effect)."""
        raise NotImplementedError


def _joint(spec: mujoco.MjSpec, name: str) -> mujoco.MjsJoint:
    j = spec.joint(name)
    if j is None:
        raise InputError(f"no joint {name!r} in the robot")
    return j


def _actuator(spec: mujoco.MjSpec, joint: str) -> mujoco.MjsActuator:
    for a in spec.actuators:
        if a.target == joint:
            return a
    raise InputError(f"joint {joint!r} has no actuator")


def _dof(c: Correction, index: int) -> int:
    """The dof of log joint ``index`` (its motor side)."""
    return int(c.model.jnt_dofadr[int(JointMap.of(c.model).jid[index])])


def _act(c: Correction, index: int) -> int:
    """The actuator that drives log joint ``index``."""
    return int(np.flatnonzero(JointMap.of(c.model).act_log == index)[0])


def _set_const(m: mujoco.MjModel) -> None:
    mujoco.mj_setConst(m, mujoco.MjData(m))  # Constraint scaling depends on the inertia.


class CoulombFriction(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        j = _joint(spec, target)
        j.frictionloss = j.frictionloss + value

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.model.dof_frictionloss[_dof(c, index)] += value


class ViscousDamping(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        j = _joint(spec, target)
        d = np.array(j.damping, dtype=np.float64)  # MuJoCo 4: [linear, ...] coefficients.
        d[0] += value
        j.damping = d

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.model.dof_damping[_dof(c, index)] += value


class Armature(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        j = _joint(spec, target)
        j.armature = j.armature + value

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.model.dof_armature[_dof(c, index)] += value
        _set_const(c.model)


class Delay(Effect):
    """A transport delay: in a spec, the actuator's history buffer; on a compiled model, the
    correction's command delay (a history buffer changes the model's structure)."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        a = _actuator(spec, target)
        a.delay = value
        a.nsample = max(a.nsample, 2, int(np.ceil(value / spec.option.timestep)) + 2)

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.delay[_act(c, index)] = value


class Lag(Effect):
    """A first-order filter between command and torque; on a compiled model the actuator must
    already be a ``filterexact`` one (see :func:`~humimic.sim.models.prediction_spec`)."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        a = _actuator(spec, target)
        a.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
        prm = np.zeros(10)
        prm[0] = value
        a.dynprm = prm
        a.actdim = 1
        a.actearly = True  # The filtered command drives the joint in the same step.

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.model.actuator_dynprm[_act(c, index), 0] = value


class TorqueLimit(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        a = _actuator(spec, target)
        a.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.forcerange = np.array([-value, value])

    def on_model(self, c: Correction, index: int, value: float) -> None:
        act = _act(c, index)
        c.model.actuator_forcelimited[act] = 1
        c.model.actuator_forcerange[act] = (-value, value)


class GainMismatch(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        a = _actuator(spec, target)
        a.gainprm = np.asarray(a.gainprm) * value
        a.biasprm = np.asarray(a.biasprm) * value

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.gain_scale[_act(c, index)] *= value


class EncoderOffset(Effect):
    """The encoder reads ``value`` more than the true angle: in a spec, a joint whose reference
    (the coordinate of the body's modelled pose) is ``value``, its range moved with it; on a
    compiled model, the correction's offset of what the drive and the log see."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        j = _joint(spec, target)
        j.ref = j.ref + value
        j.range = np.asarray(j.range) + value

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.offset[index] = value


class PayloadMass(Effect):
    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        b = spec.body(target)
        if b is None:
            raise InputError(f"no body {target!r} in the robot")
        b.mass = b.mass + value

    def on_model(self, c: Correction, index: int, value: float) -> None:
        c.model.body_mass[index] += value
        _set_const(c.model)


def _planes(m: mujoco.MjModel) -> np.ndarray:
    return np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)


def floor_colliders(m: mujoco.MjModel, body: int) -> np.ndarray:
    """The geoms of ``body`` that touch the floor (they collide with the model's first plane)
    and whose contact parameters decide the floor's contact (a higher MuJoCo priority than
    the plane's, as the G1's feet have; else the two would be mixed). Empty when the body has
    none or the model no plane."""
    planes = _planes(m)
    if planes.size == 0:
        return np.zeros(0, dtype=np.int64)
    f = int(planes[0])
    g = np.flatnonzero(m.geom_bodyid == body)
    touch = (m.geom_contype[g] & m.geom_conaffinity[f]) | (
        m.geom_contype[f] & m.geom_conaffinity[g]
    )
    g = g[touch != 0]
    decides = np.all(m.geom_priority[g] > m.geom_priority[f])
    return g if g.size and decides else g[:0]


def soft_geoms(m: mujoco.MjModel, body: int) -> np.ndarray:
    """:func:`floor_colliders` with a contact time constant (a positive ``solref[0]``, not
    MuJoCo's direct stiffness-damping form). Empty when ``body`` has none."""
    g = floor_colliders(m, body)
    return g if np.all(m.geom_solref[g, 0] > 0) else g[:0]


def _spec_geoms(
    spec: mujoco.MjSpec, target: str, select: Callable[[mujoco.MjModel, int], np.ndarray]
) -> list[mujoco.MjsGeom]:
    """The spec geoms of body ``target`` that ``select`` picks on its compiled model.

    Raises:
        InputError: No such body, or it has no such geom.
    """
    b = spec.body(target)
    if b is None:
        raise InputError(f"no body {target!r} in the robot")
    m = spec.copy().compile()
    ids = select(m, m.body(target).id)
    if ids.size == 0:
        raise InputError(
            f"body {target!r} has no geom that decides its contact with the floor (one "
            "colliding with the model's plane, at a higher geom priority than the plane's)"
        )
    names = {m.geom(int(g)).name for g in ids}
    geoms = [g for g in b.geoms if g.name in names] if all(names) else None
    if geoms is None or len(geoms) != ids.size:  # Unnamed geoms: by their order in the body.
        order = np.flatnonzero(m.geom_bodyid == m.body(target).id).tolist()
        geoms = [b.geoms[order.index(int(g))] for g in ids]
    return geoms


class ContactSoftness(Effect):
    """The time constant of the contact between a body's floor colliders and the floor
    (MuJoCo's solref[0], the damping ratio kept): a softer sole, or a softer floor under it,
    lets the foot sink and rock further under load. ``value`` replaces the model's. On a
    spec the body's colliding geoms get it; a body whose colliders do not decide the floor's
    contact (:func:`soft_geoms`) is refused."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        for g in _spec_geoms(spec, target, soft_geoms):
            g.solref = np.array([value, g.solref[1]])

    def on_model(self, c: Correction, index: int, value: float) -> None:
        ids = soft_geoms(c.model, index)
        if ids.size == 0:
            raise InputError(f"body {c.model.body(index).name!r} decides no floor contact")
        c.model.geom_solref[ids, 0] = value


class ContactFriction(Effect):
    """The sliding friction coefficient of a body's contact with the floor (MuJoCo's
    ``friction[0]`` of its floor colliders, which decide the contact: :func:`floor_colliders`):
    a polished or wet floor, or worn soles, let a loaded foot slide. ``value`` replaces the
    model's; torsional and rolling friction are kept."""

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        for g in _spec_geoms(spec, target, floor_colliders):
            g.friction = np.array([value, g.friction[1], g.friction[2]])

    def on_model(self, c: Correction, index: int, value: float) -> None:
        ids = floor_colliders(c.model, index)
        if ids.size == 0:
            raise InputError(f"body {c.model.body(index).name!r} decides no floor contact")
        c.model.geom_friction[ids, 0] = value


class Backlash(Effect):
    """Play of ``value`` rad in the transmission: a second hinge on the same axis (the link
    side), free within +-value/2 and stopped stiffly at the ends; the drive turns the first
    (the motor side, with the rotor's armature) and the log reports the link, the sum of both.
    On a compiled model the play joint must exist (a model built with it); its range is set."""

    adds_joints = True

    def on_spec(self, spec: mujoco.MjSpec, target: str, value: float) -> None:
        j = _joint(spec, target)
        play = j.parent.add_joint(name=target + PLAY_SUFFIX, type=mujoco.mjtJoint.mjJNT_HINGE)
        play.axis, play.pos = j.axis, j.pos
        play.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        play.range = np.array([-value / 2, value / 2])
        play.armature = 1e-4  # The gear train's own inertia between the two sides.
        play.solref_limit = np.array([0.002, 1.0])  # A stiff stop (two physics steps).

    def on_model(self, c: Correction, index: int, value: float) -> None:
        m = c.model
        play = m.joint(JointMap.of(m).names[index] + PLAY_SUFFIX).id
        m.jnt_range[play] = (-value / 2, value / 2)


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        CoulombFriction(name="coulomb_friction", unit="N m", target="joint",
               expresses="joint frictionloss", signature="residual torque ~ sign(qdot)",
               meaning="friction added to the joint: it only resists motion"),
        ViscousDamping(name="viscous_damping", unit="N m s/rad", target="joint",
               expresses="joint damping", signature="residual torque ~ qdot",
               meaning="damping added to the joint: negative damping would feed energy in"),
        Armature(name="armature", unit="kg m^2", target="joint",
               expresses="joint armature", signature="residual torque ~ qddot",
               meaning="rotor inertia added to the joint"),
        Delay(name="delay", unit="s", target="joint",
               expresses="actuator delay (history buffer)",
               signature="cross-correlation peak of command and response at a non-zero lag",
               meaning="transport delay of the commands: they cannot act before they are sent",
               maximum=1.0),
        Lag(name="lag", unit="s", target="joint",
               expresses="actuator dyntype filterexact, dynprm[0] = time constant",
               signature="first-order low-pass between command and torque",
               meaning="time constant of the drive's filter"),
        TorqueLimit(name="torque_limit", unit="N m", target="joint",
               expresses="actuator forcerange", signature="residual only when |tau| is near a bound",
               sign="positive", meaning="the bound on |torque|"),
        GainMismatch(name="gain_mismatch", unit="ratio", target="joint",
               expresses="actuator gainprm/biasprm scale",
               signature="residual torque ~ position error (kp) and velocity (kd)",
               sign="positive",
               meaning="applied / commanded PD gains: 0 is no drive, below 0 positive feedback"),
        EncoderOffset(name="encoder_offset", unit="rad", target="joint",
               expresses="constant offset of the measured joint position",
               signature="constant residual in position, gravity-dependent torque residual",
               sign="signed", meaning="the encoder reads this much more than the true angle"),
        PayloadMass(name="payload_mass", unit="kg", target="body",
               expresses="body mass (and inertia)", signature="residual ~ gravity torque of the body",
               meaning="mass added to the body"),
        ContactSoftness(name="contact_softness", unit="s", target="body",
               expresses="solref[0] of the body's floor colliders",
               signature="residual on the stance leg's joints, growing with its load",
               sign="positive",
               meaning="the time constant of the body's contact with the floor (MuJoCo's "
                       "solref[0], 0.02 by default): larger is softer"),
        ContactFriction(name="contact_friction", unit="ratio", target="body",
               expresses="friction[0] of the body's geoms that decide its floor contact",
               signature="the stance foot slides: residual on the base and the stance leg "
                         "when the foot's tangential load nears value x its normal load",
               meaning="the sliding friction coefficient of the body's contact with the "
                       "floor: 0 is frictionless"),
        Backlash(name="backlash", unit="rad", target="joint",
               expresses="a second hinge on the joint's axis (the link side), limited to the play",
               signature="dead zone after velocity reversals",
               sign="positive", meaning="the total play of the transmission"),
    )
}  # fmt: skip
"""The vocabulary. Encoder offsets are signed (an encoder can read high or low); gain
mismatches are positive ratios; every other parameter is an amount, a time or a bound that
cannot be negative (a delay is also at most :attr:`Effect.maximum`)."""


@dataclass(frozen=True, kw_only=True)
class Injection:
    """An effect with its value on some joints (or one body).

    Attributes:
        source: Where it was given (``--inject 'TEXT'``, or a file and field), for messages;
            empty when made in code.
    """

    effect: str
    targets: tuple[str, ...]
    value: float
    source: str = field(default="", compare=False)

    @property
    def where(self) -> str:
        """The injection, as messages name it."""
        return self.source or f"{self.effect} on {', '.join(self.targets)}"


MAX_EFFECT_VALUE = 1e6
"""Largest size of any effect's parameter in its unit: beyond every physical value (a
``payload_mass`` of 1e308 kg overflowed MuJoCo's inertia)."""


def value_problem(effect: str, value: float) -> str | None:
    """Why ``value`` is not a physical value of ``effect`` (``None``: it is).

    Args:
        effect: A name of :data:`EFFECTS`.
        value: Its parameter, in the effect's unit.
    """
    e = EFFECTS[effect]
    if not np.isfinite(value):
        return f"{effect} must be a finite number of {e.unit}, got {value}"
    if abs(value) > MAX_EFFECT_VALUE:
        return (f"{effect} must be at most {MAX_EFFECT_VALUE:g} {e.unit} in size "
                f"({e.meaning}), got {value:g}")  # fmt: skip
    if e.sign == "nonnegative" and value < 0:
        return f"{effect} must be >= 0 {e.unit} ({e.meaning}), got {value:g}"
    if e.sign == "positive" and value <= 0:
        return f"{effect} must be > 0 {e.unit} ({e.meaning}), got {value:g}"
    if e.maximum is not None and value > e.maximum:
        return f"{effect} must be at most {e.maximum:g} {e.unit} ({e.meaning}), got {value:g}"
    return None


def parse_injection(text: str, where: str = "--inject") -> Injection:
    """Parse ``EFFECT:TARGET[,TARGET...]=VALUE`` (e.g. ``coulomb_friction:left_knee_joint=2``).

    Args:
        text: The injection.
        where: What gave it, for messages (the CLI flag, or a file and field).

    Raises:
        InputError: Naming ``where``, the text and the part that is wrong (including a value
            of the wrong sign for the effect, see :data:`EFFECTS`).
    """
    try:
        head, value_text = text.split("=", 1)
        name, targets_text = head.split(":", 1)
    except ValueError:
        raise InputError(
            f"{where} {text!r}: expected EFFECT:JOINT[,JOINT...]=VALUE, "
            "e.g. coulomb_friction:left_knee_joint=2.0"
        ) from None
    if name not in EFFECTS:
        raise InputError(f"{where} {text!r}: unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    try:
        value = float(value_text)
    except ValueError:
        raise InputError(f"{where} {text!r}: value {value_text!r} is not a number") from None
    problem = value_problem(name, value)
    if problem is not None:
        raise InputError(f"{where} {text!r}: {problem}")
    targets = tuple(t for t in targets_text.split(",") if t)
    if not targets:
        raise InputError(
            f"{where} {text!r}: name at least one joint (or a body for payload_mass, "
            "contact_softness or contact_friction)"
        )
    return Injection(effect=name, targets=targets, value=value, source=f"{where} {text!r}")


def apply_to_spec(spec: mujoco.MjSpec, injections: list[Injection]) -> None:
    """Add effects to a model spec (in place).

    Raises:
        InputError: An unknown effect, a value of the wrong sign, a joint or body that is not
            in the model.
    """
    for inj in injections:
        effect = EFFECTS.get(inj.effect)
        if effect is None:
            raise InputError(f"unknown effect {inj.effect!r}; known: {', '.join(EFFECTS)}")
        problem = value_problem(inj.effect, float(inj.value))
        if problem is not None:
            raise InputError(f"{inj.where}: {problem}")
        for target in inj.targets:
            try:
                effect.on_spec(spec, target, inj.value)
            except InputError as e:
                raise InputError(f"{inj.where}: {e}") from None


def apply_effect(c: Correction, effect: str, index: int, value: float) -> None:
    """Add one effect of the vocabulary to a compiled model in place (see
    :meth:`Effect.on_model`). Backlash needs a model with the joint's play joint."""
    EFFECTS[effect].on_model(c, index, value)
