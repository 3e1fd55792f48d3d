"""The names that settings choose from, as ``Literal`` types built from the registries, so that
tyro checks them and ``--help`` lists them."""

from __future__ import annotations

from importlib import resources
from typing import TYPE_CHECKING, Literal

from humimic.configs.retarget import RETARGET_CONFIGS
from humimic.robots.registry import robot_names
from humimic.sim.randomization import DR_PROFILES


def shipped_physics() -> tuple[str, ...]:
    """The physics files shipped with humimic (``configs/physics/NAME.yaml``), by name."""
    folder = resources.files("humimic") / "configs" / "physics"
    return tuple(
        sorted(e.name[: -len(".yaml")] for e in folder.iterdir() if e.name.endswith(".yaml"))
    )


ActionBaseName = Literal["default", "reference", "feedforward", "feedback"]
"""What a tracking policy's action is added to (:mod:`humimic.tracking.actions`)."""

if TYPE_CHECKING:
    RobotName = str
    RetargetPreset = str
    PhysicsChoice = str
    DrChoice = str
else:
    RobotName = Literal[tuple(robot_names())]
    """A registered robot (:data:`humimic.robots.registry.ROBOTS`) or one the user added
    (``humimic robots add``, in ``$HUMIMIC_ROBOTS_DIR``)."""
    RetargetPreset = Literal[tuple(RETARGET_CONFIGS)]
    """A named retargeting configuration (:data:`humimic.configs.RETARGET_CONFIGS`)."""
    PhysicsChoice = Literal[shipped_physics()] | str
    """A shipped physics file's name, or the path of a physics file."""
    DrChoice = Literal[tuple(DR_PROFILES)] | str
    """A domain-randomization profile (:data:`humimic.sim.randomization.DR_PROFILES`), or the
    path of a profile file."""

__all__ = [
    "ActionBaseName",
    "DrChoice",
    "PhysicsChoice",
    "RetargetPreset",
    "RobotName",
    "shipped_physics",
]
