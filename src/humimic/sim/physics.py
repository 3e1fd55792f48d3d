"""Physics files: one fixed robot, as changes to the nominal model (YAML).

:class:`Physics` is the file's content; :func:`load_physics` reads a file or a shipped one
(:data:`SHIPPED`), :func:`write_physics` writes one.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import mujoco
import yaml

from humimic.errors import InputError
from humimic.io import atomic_write_text, read_yaml
from humimic.sim.delta import ALL as _ALL
from humimic.sim.delta import Change, Item, Kind, RobotDelta
from humimic.sim.effects import Injection, as_delta, parse_injection

_KEYS = (
    "description",
    "robot",
    "floor_friction",
    "mass_scale",
    "com_offset",
    "kp_scale",
    "kd_scale",
    "armature_scale",
    "effects",
)

SHIPPED = ("backpack", "worn_knees")
"""Physics files shipped with humimic (``src/humimic/configs/physics/NAME.yaml``)."""


@dataclass(frozen=True, kw_only=True)
class Physics:
    """A fixed robot: changes to the nominal model.

    A physics file describes a robot whose physics differ from the nominal model in known
    ways: the "real" robot of ``humimic eval --physics`` and ``humimic loop --real`` (values
    training never sampled), or a model corrected by ``humimic sysid diagnose`` (``humimic
    train --physics``). Every value is fixed for the whole run; domain randomization, where
    asked for, acts on top of it. Example::

        description: A backpack and a slow bus.
        robot: g1                       # optional; checked against the run's robot
        floor_friction: 0.35            # sliding friction of the floor and the robot's colliders
        mass_scale: 1.05                # every link, or a mapping {body: scale}
        com_offset: {torso_link: [-0.06, 0.0, 0.05]}   # CoM moved [m], body frame
        kp_scale: {left_knee_joint: 0.8}               # number (every joint) or mapping
        kd_scale: 1.0
        armature_scale: 1.0
        effects:                        # the real2sim vocabulary (docs/real2sim.md), as in
          - payload_mass:torso_link=4.0 # ``humimic sysid simulate --inject``
          - delay:left_knee_joint,right_knee_joint=0.03

    Attributes:
        name: The file's stem (or a shipped name).
        description: Free text.
        robot: Registry name the file is written for (``None``: any).
        floor_friction: Sliding friction of the floor and every robot collider.
        mass_scale: Body -> mass and inertia multiplier (``*``: every body).
        com_offset: Body -> CoM offset [m] in the body frame.
        kp_scale: Joint -> PD stiffness multiplier (``*``: every actuated joint).
        kd_scale: Joint -> PD damping multiplier.
        armature_scale: Joint -> armature multiplier.
        effects: Effects of the real2sim vocabulary.
        source: The file it was read from (empty when built in code), for messages.
    """

    name: str
    description: str = ""
    robot: str | None = None
    floor_friction: float | None = None
    mass_scale: dict[str, float] = field(default_factory=dict)
    com_offset: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    kp_scale: dict[str, float] = field(default_factory=dict)
    kd_scale: dict[str, float] = field(default_factory=dict)
    armature_scale: dict[str, float] = field(default_factory=dict)
    effects: tuple[Injection, ...] = ()
    source: str = ""

    @property
    def where(self) -> str:
        """The physics, as messages name it (its file, when it has one)."""
        return self.source or f"physics {self.name!r}"

    @property
    def parameters(self) -> RobotDelta:
        """The file's parameter fields (everything but :attr:`effects`) as delta items, in
        the order they are applied: floor friction, masses, CoM offsets, kp, kd, armature.

        """
        items: list[Item] = []
        if self.floor_friction is not None:
            items.append(Change(op="set", kind="floor", field="friction", names=(_ALL,),
                                value=(self.floor_friction,), source=self._at("floor_friction")))  # fmt: skip
        items += self._scales("mass_scale", "body", "mass")
        for name, off in self.com_offset.items():
            items.append(Change(op="add", kind="body", field="com", names=(name,),
                                value=tuple(off), source=self._at("com_offset")))  # fmt: skip
        items += self._scales("kp_scale", "actuator", "kp")
        items += self._scales("kd_scale", "actuator", "kd")
        items += self._scales("armature_scale", "joint", "armature")
        return RobotDelta(tuple(items))

    @property
    def delta(self) -> RobotDelta:
        """Everything the physics changes, in the order it is applied: :attr:`parameters`,
        then :attr:`effects`."""
        return self.parameters + as_delta(self.effects)

    def _at(self, key: str) -> str:
        return f"{self.where}: {key}"

    def _scales(self, key: str, kind: Kind, name: str) -> list[Item]:
        m: dict[str, float] = getattr(self, key)
        return [Change(op="scale", kind=kind, field=name, names=(k,), value=(v,),
                       source=self._at(key)) for k, v in m.items()]  # fmt: skip

    def edit(self, spec: mujoco.MjSpec) -> None:
        """Apply every change (:attr:`delta`) to a model spec of the robot (in place).

        Raises:
            InputError: If a body or joint is not in the model (naming the file and field:
                an effect read from a file names its file).
        """
        self.delta.on_spec(spec)

    def edit_parameters(self, spec: mujoco.MjSpec) -> None:
        """Apply the parameter changes (:attr:`parameters`) to a spec.

        Raises:
            InputError: If a body or joint is not in the model (naming the file and field).
        """
        self.parameters.on_spec(spec)

    def as_dict(self) -> dict[str, Any]:
        """The file's content (what :func:`write_physics` writes)."""
        out: dict[str, Any] = {"description": self.description}
        if self.robot is not None:
            out["robot"] = self.robot
        if self.floor_friction is not None:
            out["floor_friction"] = self.floor_friction
        for key in ("mass_scale", "kp_scale", "kd_scale", "armature_scale"):
            m = getattr(self, key)
            if m:
                out[key] = m[_ALL] if set(m) == {_ALL} else dict(m)
        if self.com_offset:
            out["com_offset"] = {k: list(v) for k, v in self.com_offset.items()}
        if self.effects:
            out["effects"] = [
                f"{e.effect}:{','.join(e.targets)}={e.value:.6g}" for e in self.effects
            ]
        return out


def _number(v: Any, where: str, positive: bool = False, nonnegative: bool = False) -> float:
    """A finite number from a file, refused (naming ``where``) if it has the wrong sign."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise InputError(f"{where}: expected a number, got {v!r}")
    if not math.isfinite(v):
        raise InputError(f"{where}: expected a finite number, got {v!r}")
    if positive and v <= 0:
        raise InputError(f"{where}: must be positive, got {v!r}")
    if nonnegative and v < 0:
        raise InputError(f"{where}: must be >= 0, got {v!r}")
    return float(v)


def _scale_map(v: Any, where: str) -> dict[str, float]:
    if isinstance(v, Mapping):
        if _ALL in v and len(v) > 1:
            raise InputError(f"{where}: give one number for every one, or name them, not both")
        return {str(k): _number(x, f"{where}.{k}", positive=True) for k, x in v.items()}
    return {_ALL: _number(v, where, positive=True)}


def parse_physics(data: Any, name: str, where: str) -> Physics:
    """A :class:`Physics` from a parsed YAML mapping; ``where`` names it in errors."""
    if not isinstance(data, Mapping):
        raise InputError(f"{where}: expected a mapping of physics fields")
    unknown = [k for k in data if k not in _KEYS]
    if unknown:
        raise InputError(f"{where}: unknown field {unknown[0]!r}; known: {', '.join(_KEYS)}")
    com: dict[str, tuple[float, float, float]] = {}
    raw_com = data.get("com_offset") or {}
    if not isinstance(raw_com, Mapping):
        raise InputError(f"{where}: com_offset must map bodies to [x, y, z]")
    for body, off in raw_com.items():
        if not isinstance(off, list | tuple) or len(off) != 3:
            raise InputError(f"{where}: com_offset.{body}: expected [x, y, z] in m")
        xyz = [_number(x, f"{where}: com_offset.{body}") for x in off]
        com[str(body)] = (xyz[0], xyz[1], xyz[2])
    effects = data.get("effects") or []
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        raise InputError(f"{where}: effects must be a list of EFFECT:TARGET[,TARGET]=VALUE")
    friction = data.get("floor_friction")
    robot = data.get("robot")
    if robot is not None and not isinstance(robot, str):
        raise InputError(f"{where}: robot: expected a robot name, got {robot!r}")
    # Each effect's value is checked for its physical sign (see humimic.sim.effects.EFFECTS).
    parsed = tuple(
        parse_injection(e, where=f"{where}: effects[{i}]") for i, e in enumerate(effects)
    )
    return Physics(
        name=name,
        source=where,
        description=str(data.get("description") or ""),
        robot=robot,
        # A friction coefficient is >= 0 (0: a frictionless floor).
        floor_friction=None
        if friction is None
        else _number(friction, f"{where}: floor_friction", nonnegative=True),
        mass_scale=_scale_map(data["mass_scale"], f"{where}: mass_scale")
        if "mass_scale" in data
        else {},
        com_offset=com,
        kp_scale=_scale_map(data["kp_scale"], f"{where}: kp_scale") if "kp_scale" in data else {},
        kd_scale=_scale_map(data["kd_scale"], f"{where}: kd_scale") if "kd_scale" in data else {},
        armature_scale=_scale_map(data["armature_scale"], f"{where}: armature_scale")
        if "armature_scale" in data
        else {},
        effects=parsed,
    )


def physics_path(name_or_path: str | os.PathLike[str]) -> Path:
    """The file of a shipped name or a path.

    Raises:
        InputError: If neither a shipped name nor an existing file.
    """
    text = str(name_or_path)
    if text in SHIPPED:
        res = resources.files("humimic") / "configs" / "physics" / f"{text}.yaml"
        return Path(str(res))
    path = Path(text)
    if not path.is_file():
        raise InputError(
            f"physics {text!r}: no such file, and not a shipped one ({', '.join(SHIPPED)})"
        )
    return path


def load_physics(name_or_path: str | os.PathLike[str]) -> Physics:
    """Read a physics file (or a shipped one by name).

    Raises:
        InputError: For a missing file, bad YAML or a bad field (named).
    """
    path = physics_path(name_or_path)
    return parse_physics(read_yaml(path), path.stem, str(path))


def write_physics(physics: Physics, path: str | os.PathLike[str]) -> Path:
    """Write a physics file (atomically)."""
    text = f"# humimic physics file: {physics.name}\n" + yaml.safe_dump(
        physics.as_dict(), sort_keys=False
    )
    atomic_write_text(Path(path), text)
    return Path(path)


__all__ = [
    "SHIPPED",
    "Physics",
    "load_physics",
    "parse_physics",
    "physics_path",
    "write_physics",
]
