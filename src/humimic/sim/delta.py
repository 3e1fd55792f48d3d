"""One type for "this robot differs from the nominal one": :class:`RobotDelta`.

A delta is an ordered list of items. A :class:`Change` is an operation (``set``, ``scale`` or
``add``) on one parameter (:data:`PARAMETERS`) of named bodies, joints, actuators or the floor;
a :class:`Structural` effect changes what the model is made of (a delay buffer, a drive filter,
an encoder reference, a play joint). Physics files, the effect vocabulary (``--inject``, sysid
claims) and domain randomization draws (:meth:`~humimic.sim.params.PhysicsParams.delta`) are
all applied to a model spec here, by :meth:`RobotDelta.on_spec`. Units are SI and fixed in the
tables below: masses in kg, lengths in m, times (delays, time constants) in s, angles in rad.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from humimic.errors import InputError

if TYPE_CHECKING:  # MuJoCo loads on use: a DR profile is read without it.
    import mujoco

Op = Literal["set", "scale", "add"]
Kind = Literal["body", "joint", "actuator", "floor"]

ALL = "*"
"""The name that selects every object a parameter applies to."""


@dataclass(frozen=True, kw_only=True)
class Parameter:
    """One parameter a :class:`Change` may act on.

    Attributes:
        kind: What it belongs to (an actuator is named by the joint it drives).
        unit: Unit of ``add`` and ``set`` values (``scale`` values are ratios).
        ops: The operations it takes.
        meaning: What it is, for docs and messages.
        every: Which objects :data:`ALL` selects (default: all of the kind).
    """

    kind: Kind
    unit: str
    ops: tuple[Op, ...]
    meaning: str
    apply: Callable[[mujoco.MjSpec, Any, str, Op, tuple[float, ...]], None]
    every: Callable[[Any], bool] = lambda _: True


def _scaled(prm: Any, i: int, s: float) -> np.ndarray:
    p = np.array(prm, dtype=np.float64)
    p[i] *= s
    return p


def _floor_friction(spec: mujoco.MjSpec, g: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    fr = np.array(g.friction, dtype=np.float64)
    fr[0] = v[0]
    g.friction = fr


def _mass(spec: mujoco.MjSpec, b: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    if op == "add":  # A point mass at the CoM: the inertia about the CoM is unchanged.
        b.mass = b.mass + v[0]
        return
    s = v[0]  # Uniformly denser: mass and inertia scale together.
    b.mass = b.mass * s
    b.inertia = np.asarray(b.inertia) * s
    full = np.asarray(b.fullinertia)
    if not np.isnan(full[0]):
        b.fullinertia = full * s


def _com(spec: mujoco.MjSpec, b: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    b.ipos = np.asarray(b.ipos) + np.asarray(v, dtype=np.float64)


def _contact_friction(spec: mujoco.MjSpec, b: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    from humimic.sim.contacts import floor_colliders, spec_geoms

    for g in spec_geoms(spec, name, floor_colliders):
        g.friction = np.array([v[0], g.friction[1], g.friction[2]])


def _contact_timeconst(
    spec: mujoco.MjSpec, b: Any, name: str, op: Op, v: tuple[float, ...]
) -> None:
    from humimic.sim.contacts import soft_geoms, spec_geoms

    for g in spec_geoms(spec, name, soft_geoms):
        g.solref = np.array([v[0], g.solref[1]])


def _armature(spec: mujoco.MjSpec, j: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    j.armature = j.armature * v[0] if op == "scale" else j.armature + v[0]


def _frictionloss(spec: mujoco.MjSpec, j: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    j.frictionloss = j.frictionloss + v[0]


def _damping(spec: mujoco.MjSpec, j: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    d = np.array(j.damping, dtype=np.float64)  # MuJoCo 4: [linear, ...] coefficients.
    d[0] += v[0]
    j.damping = d


def _kp(spec: mujoco.MjSpec, a: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    a.gainprm = _scaled(a.gainprm, 0, v[0])
    a.biasprm = _scaled(a.biasprm, 1, v[0])


def _kd(spec: mujoco.MjSpec, a: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    a.biasprm = _scaled(a.biasprm, 2, v[0])


def _gain(spec: mujoco.MjSpec, a: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    a.gainprm = np.asarray(a.gainprm) * v[0]
    a.biasprm = np.asarray(a.biasprm) * v[0]


def _force_limit(spec: mujoco.MjSpec, a: Any, name: str, op: Op, v: tuple[float, ...]) -> None:
    import mujoco

    a.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    a.forcerange = np.array([-v[0], v[0]])


def _hinge(j: Any) -> bool:
    import mujoco

    return j.type == mujoco.mjtJoint.mjJNT_HINGE


PARAMETERS: dict[tuple[Kind, str], Parameter] = {
    ("floor", "friction"): Parameter(kind="floor", unit="ratio", ops=("set",), apply=_floor_friction,
        meaning="sliding friction of the floor and of every robot collider"),
    ("body", "mass"): Parameter(kind="body", unit="kg", ops=("scale", "add"), apply=_mass,
        every=lambda b: b.mass > 0,
        meaning="mass: scale scales the inertia with it, add is a point mass at the CoM"),
    ("body", "com"): Parameter(kind="body", unit="m", ops=("add",), apply=_com,
        meaning="CoM position in the body frame (x, y, z)"),
    ("body", "contact_friction"): Parameter(kind="body", unit="ratio", ops=("set",),
        apply=_contact_friction,
        meaning="sliding friction of the body's geoms that decide its floor contact"),
    ("body", "contact_timeconst"): Parameter(kind="body", unit="s", ops=("set",),
        apply=_contact_timeconst,
        meaning="time constant (solref[0]) of the body's floor contact"),
    ("joint", "armature"): Parameter(kind="joint", unit="kg m^2", ops=("scale", "add"),
        apply=_armature, every=_hinge, meaning="rotor inertia"),
    ("joint", "frictionloss"): Parameter(kind="joint", unit="N m", ops=("add",),
        apply=_frictionloss, meaning="Coulomb friction"),
    ("joint", "damping"): Parameter(kind="joint", unit="N m s/rad", ops=("add",), apply=_damping,
        meaning="viscous damping"),
    ("actuator", "kp"): Parameter(kind="actuator", unit="N m/rad", ops=("scale",), apply=_kp,
        meaning="PD stiffness"),
    ("actuator", "kd"): Parameter(kind="actuator", unit="N m s/rad", ops=("scale",), apply=_kd,
        meaning="PD damping"),
    ("actuator", "gain"): Parameter(kind="actuator", unit="ratio", ops=("scale",), apply=_gain,
        meaning="every gain and bias term (applied / commanded PD gains)"),
    ("actuator", "force_limit"): Parameter(kind="actuator", unit="N m", ops=("set",),
        apply=_force_limit, meaning="bound on |torque|"),
}  # fmt: skip
"""Every parameter a :class:`Change` acts on, by (kind, name)."""


def _delay(spec: mujoco.MjSpec, a: Any, name: str, value: float) -> None:
    a.delay = value
    a.nsample = max(a.nsample, 2, int(np.ceil(value / spec.option.timestep)) + 2)


def _lag(spec: mujoco.MjSpec, a: Any, name: str, value: float) -> None:
    import mujoco

    a.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
    prm = np.zeros(10)
    prm[0] = value
    a.dynprm = prm
    a.actdim = 1
    a.actearly = True  # The filtered command drives the joint in the same step.


def _encoder_offset(spec: mujoco.MjSpec, j: Any, name: str, value: float) -> None:
    j.ref = j.ref + value
    j.range = np.asarray(j.range) + value


def _backlash(spec: mujoco.MjSpec, j: Any, name: str, value: float) -> None:
    import mujoco

    from humimic.sim.joints import PLAY_SUFFIX

    play = j.parent.add_joint(name=name + PLAY_SUFFIX, type=mujoco.mjtJoint.mjJNT_HINGE)
    play.axis, play.pos = j.axis, j.pos
    play.limited = mujoco.mjtLimited.mjLIMITED_TRUE
    play.range = np.array([-value / 2, value / 2])
    play.armature = 1e-4  # The gear train's own inertia between the two sides.
    play.solref_limit = np.array([0.002, 1.0])  # A stiff stop (two physics steps).


STRUCTURAL: dict[str, tuple[Kind, str, Callable[[mujoco.MjSpec, Any, str, float], None]]] = {
    "delay": ("actuator", "s", _delay),
    "lag": ("actuator", "s", _lag),
    "encoder_offset": ("joint", "rad", _encoder_offset),
    "backlash": ("joint", "rad", _backlash),
}
"""Effects that change the model's structure, by name: (kind, unit, applier). ``delay``: the
actuator's history buffer; ``lag``: a first-order ``filterexact`` drive filter (its time
constant); ``encoder_offset``: the joint's reference (the coordinate of the body's modelled
pose) and range moved by the value; ``backlash``: a second hinge on the joint's axis (the link
side), free within +-value/2 and stopped stiffly at the ends."""

ADDS_JOINTS = frozenset({"backlash"})
"""Structural effects that add joints (a model with a fixed joint layout cannot take them)."""


@dataclass(frozen=True, kw_only=True)
class Change:
    """``op`` the parameter ``kind.field`` of ``names`` by ``value`` (see :data:`PARAMETERS`).

    Attributes:
        names: Bodies, joints or actuators (by the joint they drive); ``("*",)``: every one
            the parameter applies to. The floor is ``("*",)``.
        value: One number, or three for ``body.com`` (x, y, z).
        source: What gave it (a file and field, a flag), prefixed to messages.
    """

    op: Op
    kind: Kind
    field: str
    names: tuple[str, ...]
    value: tuple[float, ...]
    source: str = ""

    def __post_init__(self) -> None:
        p = PARAMETERS.get((self.kind, self.field))
        if p is None:
            raise ValueError(f"no parameter {self.kind}.{self.field}; known: {_known()}")
        if self.op not in p.ops:
            raise ValueError(f"{self.kind}.{self.field} takes {'/'.join(p.ops)}, not {self.op}")


@dataclass(frozen=True, kw_only=True)
class Structural:
    """A structural effect (:data:`STRUCTURAL`) with ``value`` on ``names``."""

    effect: str
    names: tuple[str, ...]
    value: float
    source: str = ""

    def __post_init__(self) -> None:
        if self.effect not in STRUCTURAL:
            raise ValueError(
                f"no structural effect {self.effect!r}; known: {', '.join(STRUCTURAL)}"
            )


Item = Change | Structural


def _known() -> str:
    return ", ".join(f"{k}.{f}" for k, f in PARAMETERS)


_WHAT = {"body": "body", "joint": "joint", "actuator": "actuated joint", "floor": "floor"}


def _objects(spec: mujoco.MjSpec, kind: Kind) -> dict[str, Any]:
    if kind == "body":
        return {b.name: b for b in spec.bodies if b.name != "world"}
    if kind == "joint":
        return {j.name: j for j in spec.joints}
    return {a.target: a for a in reversed(spec.actuators)}  # The first of a joint's.


def _selected(
    spec: mujoco.MjSpec, kind: Kind, names: tuple[str, ...], every: Callable[[Any], bool]
) -> list[tuple[str, Any]]:
    if kind == "floor":
        return [(ALL, g) for g in spec.geoms if g.contype or g.conaffinity]
    objs = _objects(spec, kind)
    if ALL in names:
        return [(n, o) for n, o in objs.items() if every(o)]
    missing = [n for n in names if n not in objs]
    if missing:
        raise InputError(f"no {_WHAT[kind]} {missing[0]!r} in the robot")
    return [(n, objs[n]) for n in names]


def apply_item(spec: mujoco.MjSpec, item: Item) -> None:
    """Apply one item to a spec (in place).

    Raises:
        InputError: A name that is not in the model, prefixed with the item's source.
    """
    try:
        if isinstance(item, Change):
            p = PARAMETERS[(item.kind, item.field)]
            for name, obj in _selected(spec, item.kind, item.names, p.every):
                p.apply(spec, obj, name, item.op, item.value)
        else:
            kind, _, fn = STRUCTURAL[item.effect]
            for name, obj in _selected(spec, kind, item.names, lambda _: True):
                fn(spec, obj, name, item.value)
    except InputError as e:
        raise InputError(f"{item.source}: {e}" if item.source else str(e)) from None


@dataclass(frozen=True)
class RobotDelta:
    """How a robot differs from its nominal model: changes applied in order.

    Attributes:
        items: :class:`Change` and :class:`Structural` items, applied first to last.
    """

    items: tuple[Item, ...] = ()

    def __add__(self, other: RobotDelta) -> RobotDelta:
        return RobotDelta(self.items + other.items)

    @property
    def structural(self) -> tuple[Structural, ...]:
        """The structural items (they need a spec; parameter changes also act on arrays)."""
        return tuple(i for i in self.items if isinstance(i, Structural))

    @property
    def adds_joints(self) -> tuple[Structural, ...]:
        """The items that add joints (:data:`ADDS_JOINTS`)."""
        return tuple(i for i in self.structural if i.effect in ADDS_JOINTS)

    def on_spec(self, spec: mujoco.MjSpec) -> None:
        """Apply every item to a model spec, in order (in place).

        Raises:
            InputError: A body, joint or actuator that is not in the model (naming the item's
                source).
        """
        for item in self.items:
            apply_item(spec, item)


__all__ = [
    "ADDS_JOINTS",
    "ALL",
    "PARAMETERS",
    "STRUCTURAL",
    "Change",
    "Item",
    "Parameter",
    "RobotDelta",
    "Structural",
    "apply_item",
]
