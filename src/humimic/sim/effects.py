"""The vocabulary of physical effects a robot model can lack (names are part of the report format).

Each effect is named delta items (:meth:`Effect.items`: a parameter change or a structural
effect of :mod:`humimic.sim.delta`), so a robot built with an injected effect and one built
with an identified effect mean the same thing. Sysid scores values on a compiled model
(``humimic.real2sim.correction``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.sim.delta import ADDS_JOINTS, Change, Item, Kind, Op, RobotDelta, Structural


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
    change: tuple[Kind, str, Op] | None = None
    """The parameter it changes and how (:data:`~humimic.sim.delta.PARAMETERS`); ``None``: a
    structural effect (:data:`~humimic.sim.delta.STRUCTURAL`)."""

    @property
    def adds_joints(self) -> bool:
        """Whether the effect adds joints to the model (a model with a fixed joint layout, the
        tracking simulation's, cannot take it)."""
        return self.name in ADDS_JOINTS

    def items(self, targets: tuple[str, ...], value: float, source: str = "") -> tuple[Item, ...]:
        """The effect with ``value`` on ``targets`` (joints, or bodies), as delta items."""
        if self.change is None:
            return (Structural(effect=self.name, names=targets, value=value, source=source),)
        kind, name, op = self.change
        return (Change(op=op, kind=kind, field=name, names=targets, value=(value,),
                       source=source),)  # fmt: skip


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(change=("joint", "frictionloss", "add"),
               name="coulomb_friction", unit="N m", target="joint",
               expresses="joint frictionloss", signature="residual torque ~ sign(qdot)",
               meaning="friction added to the joint: it only resists motion"),
        Effect(change=("joint", "damping", "add"),
               name="viscous_damping", unit="N m s/rad", target="joint",
               expresses="joint damping", signature="residual torque ~ qdot",
               meaning="damping added to the joint: negative damping would feed energy in"),
        Effect(change=("joint", "armature", "add"),
               name="armature", unit="kg m^2", target="joint",
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
        Effect(change=("actuator", "force_limit", "set"),
               name="torque_limit", unit="N m", target="joint",
               expresses="actuator forcerange", signature="residual only when |tau| is near a bound",
               sign="positive", meaning="the bound on |torque|"),
        Effect(change=("actuator", "gain", "scale"),
               name="gain_mismatch", unit="ratio", target="joint",
               expresses="actuator gainprm/biasprm scale",
               signature="residual torque ~ position error (kp) and velocity (kd)",
               sign="positive",
               meaning="applied / commanded PD gains: 0 is no drive, below 0 positive feedback"),
        Effect(name="encoder_offset", unit="rad", target="joint",
               expresses="constant offset of the measured joint position",
               signature="constant residual in position, gravity-dependent torque residual",
               sign="signed", meaning="the encoder reads this much more than the true angle"),
        Effect(change=("body", "mass", "add"),
               name="payload_mass", unit="kg", target="body",
               expresses="body mass (and inertia)", signature="residual ~ gravity torque of the body",
               meaning="mass added to the body"),
        Effect(change=("body", "contact_timeconst", "set"),
               name="contact_softness", unit="s", target="body",
               expresses="solref[0] of the body's floor colliders",
               signature="residual on the stance leg's joints, growing with its load",
               sign="positive",
               meaning="the time constant of the body's contact with the floor (MuJoCo's "
                       "solref[0], 0.02 by default): larger is softer"),
        Effect(change=("body", "contact_friction", "set"),
               name="contact_friction", unit="ratio", target="body",
               expresses="friction[0] of the body's geoms that decide its floor contact",
               signature="the stance foot slides: residual on the base and the stance leg "
                         "when the foot's tangential load nears value x its normal load",
               meaning="the sliding friction coefficient of the body's contact with the "
                       "floor: 0 is frictionless"),
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


def as_delta(injections: Iterable[Injection]) -> RobotDelta:
    """Injections as one delta (each effect's items, in order).

    Raises:
        InputError: An unknown effect or a value of the wrong sign, naming the injection.
    """
    items: list[Item] = []
    for inj in injections:
        effect = EFFECTS.get(inj.effect)
        if effect is None:
            raise InputError(f"unknown effect {inj.effect!r}; known: {', '.join(EFFECTS)}")
        problem = value_problem(inj.effect, float(inj.value))
        if problem is not None:
            raise InputError(f"{inj.where}: {problem}")
        items += effect.items(inj.targets, inj.value, source=inj.where)
    return RobotDelta(tuple(items))


def apply_to_spec(spec: mujoco.MjSpec, injections: Iterable[Injection]) -> None:
    """Add effects to a model spec (in place): :func:`as_delta` applied.

    Raises:
        InputError: An unknown effect, a value of the wrong sign, a joint or body that is not
            in the model.
    """
    as_delta(injections).on_spec(spec)
