"""The vocabulary of physical effects a simulator can lack (names are part of the report format).

Each effect says which MuJoCo parameters express it and how to add it to a model spec. The
diagnosis (a later slice of issue 4) scores these effects against a log's residual; the log
simulator uses the same code to inject them, so an injected effect and an identified one mean
the same thing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

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
    """

    name: str
    unit: str
    target: str
    expresses: str
    signature: str


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(name="coulomb_friction", unit="N m", target="joint",
               expresses="joint frictionloss", signature="residual torque ~ sign(qdot)"),
        Effect(name="viscous_damping", unit="N m s/rad", target="joint",
               expresses="joint damping", signature="residual torque ~ qdot"),
        Effect(name="armature", unit="kg m^2", target="joint",
               expresses="joint armature", signature="residual torque ~ qddot"),
        Effect(name="delay", unit="s", target="joint",
               expresses="actuator delay (history buffer)",
               signature="cross-correlation peak of command and response at a non-zero lag"),
        Effect(name="lag", unit="s", target="joint",
               expresses="actuator dyntype filterexact, dynprm[0] = time constant",
               signature="first-order low-pass between command and torque"),
        Effect(name="torque_limit", unit="N m", target="joint",
               expresses="actuator forcerange", signature="residual only when |tau| is near a bound"),
        Effect(name="gain_mismatch", unit="ratio", target="joint",
               expresses="actuator gainprm/biasprm scale",
               signature="residual torque ~ position error (kp) and velocity (kd)"),
        Effect(name="encoder_offset", unit="rad", target="joint",
               expresses="constant offset of the measured joint position",
               signature="constant residual in position, gravity-dependent torque residual"),
        Effect(name="payload_mass", unit="kg", target="body",
               expresses="body mass (and inertia)", signature="residual ~ gravity torque of the body"),
        Effect(name="backlash", unit="rad", target="joint",
               expresses="a second hinge on the joint's axis (the link side), limited to the play",
               signature="dead zone after velocity reversals"),
    )
}  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class Injection:
    """An effect with its value on some joints (or one body)."""

    effect: str
    targets: tuple[str, ...]
    value: float


def parse_injection(text: str) -> Injection:
    """Parse ``EFFECT:TARGET[,TARGET...]=VALUE`` (e.g. ``coulomb_friction:left_knee_joint=2``).

    Raises:
        InputError: Naming the part that is wrong.
    """
    try:
        head, value_text = text.split("=", 1)
        name, targets_text = head.split(":", 1)
    except ValueError:
        raise InputError(
            f"--inject {text!r}: expected EFFECT:JOINT[,JOINT...]=VALUE, "
            "e.g. coulomb_friction:left_knee_joint=2.0"
        ) from None
    if name not in EFFECTS:
        raise InputError(f"--inject {text!r}: unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    try:
        value = float(value_text)
    except ValueError:
        raise InputError(f"--inject {text!r}: value {value_text!r} is not a number") from None
    if not np.isfinite(value):
        raise InputError(f"--inject {text!r}: value must be finite")
    targets = tuple(t for t in targets_text.split(",") if t)
    if not targets:
        raise InputError(f"--inject {text!r}: name at least one joint (or a body for payload_mass)")
    return Injection(effect=name, targets=targets, value=value)


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
    a.forcerange = np.array([-abs(v), abs(v)])


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
    if v <= 0:
        raise InputError(f"backlash on {joint!r} must be positive (total play in rad)")
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
    """Add effects to a model spec (in place)."""
    for inj in injections:
        fn = APPLY.get(inj.effect)
        if fn is None:
            raise InputError(f"effect {inj.effect!r} cannot be injected yet")
        for target in inj.targets:
            fn(spec, target, inj.value)
