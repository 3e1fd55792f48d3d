"""The vocabulary of physical effects a simulator can lack (names are part of the report format).

Each effect says which MuJoCo parameters express it and how to add it to a model spec. The
diagnosis (a later slice of issue 4) scores these effects against a log's residual; the log
simulator uses the same code to inject them, so an injected effect and an identified one mean
the same thing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.joints import PLAY_SUFFIX


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


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(name="coulomb_friction", unit="N m", target="joint",
               expresses="joint frictionloss", signature="residual torque ~ sign(qdot)",
               meaning="friction added to the joint: it only resists motion"),
        Effect(name="viscous_damping", unit="N m s/rad", target="joint",
               expresses="joint damping", signature="residual torque ~ qdot",
               meaning="damping added to the joint: negative damping would feed energy in"),
        Effect(name="armature", unit="kg m^2", target="joint",
               expresses="joint armature", signature="residual torque ~ qddot",
               meaning="rotor inertia added to the joint"),
        Effect(name="delay", unit="s", target="joint",
               expresses="actuator delay (history buffer)",
               signature="cross-correlation peak of command and response at a non-zero lag",
               meaning="transport delay of the commands: they cannot act before they are sent",
               maximum=1.0),
        Effect(name="lag", unit="s", target="joint",
               expresses="actuator dyntype filterexact, dynprm[0] = time constant",
               signature="first-order low-pass between command and torque",
               meaning="time constant of the drive's filter"),
        Effect(name="torque_limit", unit="N m", target="joint",
               expresses="actuator forcerange", signature="residual only when |tau| is near a bound",
               sign="positive", meaning="the bound on |torque|"),
        Effect(name="gain_mismatch", unit="ratio", target="joint",
               expresses="actuator gainprm/biasprm scale",
               signature="residual torque ~ position error (kp) and velocity (kd)",
               sign="positive",
               meaning="applied / commanded PD gains: 0 is no drive, below 0 positive feedback"),
        Effect(name="encoder_offset", unit="rad", target="joint",
               expresses="constant offset of the measured joint position",
               signature="constant residual in position, gravity-dependent torque residual",
               sign="signed", meaning="the encoder reads this much more than the true angle"),
        Effect(name="payload_mass", unit="kg", target="body",
               expresses="body mass (and inertia)", signature="residual ~ gravity torque of the body",
               meaning="mass added to the body"),
        Effect(name="backlash", unit="rad", target="joint",
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


def value_problem(effect: str, value: float) -> str | None:
    """Why ``value`` is not a physical value of ``effect`` (``None``: it is).

    Args:
        effect: A name of :data:`EFFECTS`.
        value: Its parameter, in the effect's unit.
    """
    e = EFFECTS[effect]
    if not np.isfinite(value):
        return f"{effect} must be a finite number of {e.unit}, got {value}"
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
        raise InputError(f"{where} {text!r}: name at least one joint (or a body for payload_mass)")
    return Injection(effect=name, targets=targets, value=value, source=f"{where} {text!r}")


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


def _friction(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    _joint(spec, joint).frictionloss = _joint(spec, joint).frictionloss + v


def _damping(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    j = _joint(spec, joint)
    d = np.array(j.damping, dtype=np.float64)  # MuJoCo 4: [linear, ...] coefficients.
    d[0] += v
    j.damping = d


def _armature(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    _joint(spec, joint).armature = _joint(spec, joint).armature + v


def _delay(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    a = _actuator(spec, joint)
    a.delay = v
    a.nsample = max(a.nsample, 2, int(np.ceil(v / spec.option.timestep)) + 2)


def _lag(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    a = _actuator(spec, joint)
    a.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
    prm = np.zeros(10)
    prm[0] = v
    a.dynprm = prm
    a.actdim = 1
    a.actearly = True  # The filtered command drives the joint in the same step.


def _torque_limit(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    a = _actuator(spec, joint)
    a.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    a.forcerange = np.array([-v, v])


def _gain(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    a = _actuator(spec, joint)
    a.gainprm = np.asarray(a.gainprm) * v
    a.biasprm = np.asarray(a.biasprm) * v


def _encoder_offset(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    """The encoder reads ``v`` more than the true angle: in MuJoCo, a joint whose reference
    (the coordinate of the body's modelled pose) is ``v``; its range moves with it."""
    j = _joint(spec, joint)
    j.ref = j.ref + v
    j.range = np.asarray(j.range) + v


def _backlash(spec: mujoco.MjSpec, joint: str, v: float) -> None:
    """Play of ``v`` rad in the transmission: a second hinge on the same axis (the link side),
    free within +-v/2 and stopped stiffly at the ends; the drive turns the first (the motor
    side, with the rotor's armature) and the log reports the link, the sum of both."""
    j = _joint(spec, joint)
    play = j.parent.add_joint(name=joint + PLAY_SUFFIX, type=mujoco.mjtJoint.mjJNT_HINGE)
    play.axis, play.pos = j.axis, j.pos
    play.limited = mujoco.mjtLimited.mjLIMITED_TRUE
    play.range = np.array([-v / 2, v / 2])
    play.armature = 1e-4  # The gear train's own inertia between the two sides.
    play.solref_limit = np.array([0.002, 1.0])  # A stiff stop (two physics steps).


def _payload(spec: mujoco.MjSpec, body: str, v: float) -> None:
    b = spec.body(body)
    if b is None:
        raise InputError(f"no body {body!r} in the robot")
    b.mass = b.mass + v


APPLY: dict[str, Callable[[mujoco.MjSpec, str, float], None]] = {
    "coulomb_friction": _friction,
    "viscous_damping": _damping,
    "armature": _armature,
    "delay": _delay,
    "lag": _lag,
    "torque_limit": _torque_limit,
    "gain_mismatch": _gain,
    "payload_mass": _payload,
    "encoder_offset": _encoder_offset,
    "backlash": _backlash,
}
"""How each effect is added to a model."""


def apply_to_spec(spec: mujoco.MjSpec, injections: list[Injection]) -> None:
    """Add effects to a model spec (in place).

    Raises:
        InputError: An unknown effect, a value of the wrong sign, a joint or body that is not
            in the model.
    """
    for inj in injections:
        fn = APPLY.get(inj.effect)
        if fn is None:
            raise InputError(f"effect {inj.effect!r} cannot be injected yet")
        problem = value_problem(inj.effect, float(inj.value))
        if problem is not None:
            raise InputError(f"{inj.where}: {problem}")
        for target in inj.targets:
            try:
                fn(spec, target, inj.value)
            except InputError as e:
                raise InputError(f"{inj.where}: {e}") from None
