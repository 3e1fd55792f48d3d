"""The robot registry: every robot humimic knows, as typed data."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from humimic.errors import UnknownNameError
from humimic.robots.actuators import ActuatorRecipe, g1_actuators, t1_actuators


@dataclass(frozen=True, kw_only=True)
class RobotConfig:
    """What humimic needs to know about a humanoid beyond its MJCF.

    Attributes:
        name: Registry name.
        description: One line for listings.
        menagerie_dir: Folder name in MuJoCo Menagerie.
        xml: Scene file inside that folder (robot plus floor).
        robot_descriptions_module: ``robot_descriptions`` module name, for online fallback.
        license: Licence of the model files (shown by ``humimic robots list``).
        root_body: The floating base body.
        feet: Side (``left``/``right``) -> foot body. Maps must put their feet on these bodies;
            the bodies' collision geoms are the feet's contact geometry.
        self_collision: Pairs of body-name groups that must not interpenetrate (checked by the
            retargeter and the quality report). Each group is a tuple of body names.
        actuators: Gain recipe for the PD servos.
        floor_geom: Name of the floor geom in the scene.
    """

    name: str
    description: str
    menagerie_dir: str
    xml: str = "scene.xml"
    robot_descriptions_module: str | None = None
    license: str
    root_body: str
    feet: dict[str, str]
    self_collision: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = ()
    actuators: ActuatorRecipe
    floor_geom: str = "floor"


def _g1_arm(side: str) -> tuple[str, ...]:
    return tuple(
        f"{side}_{b}_link"
        for b in ("shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")
    )


def _g1_leg(side: str) -> tuple[str, ...]:
    return tuple(f"{side}_{b}_link" for b in ("hip_yaw", "knee", "ankle_pitch", "ankle_roll"))


def g1() -> RobotConfig:
    """Unitree G1, 29 DoF (MuJoCo Menagerie ``unitree_g1``, BSD-3-Clause)."""
    trunk = ("pelvis", "torso_link", "left_hip_roll_link", "right_hip_roll_link")
    thighs = ("left_hip_yaw_link", "right_hip_yaw_link", "left_knee_link", "right_knee_link")
    return RobotConfig(
        name="g1",
        description="Unitree G1 humanoid, 29 DoF",
        menagerie_dir="unitree_g1",
        robot_descriptions_module="g1_mj_description",
        license="BSD-3-Clause (Unitree Robotics), via MuJoCo Menagerie",
        root_body="pelvis",
        feet={"left": "left_ankle_roll_link", "right": "right_ankle_roll_link"},
        self_collision=(
            (_g1_arm("left"), (*trunk, *thighs)),
            (_g1_arm("right"), (*trunk, *thighs)),
            (_g1_leg("left"), _g1_leg("right")),
        ),
        actuators=g1_actuators(),
    )


def t1() -> RobotConfig:
    """Booster T1, 23 DoF (MuJoCo Menagerie ``booster_t1``, Apache-2.0)."""
    return RobotConfig(
        name="t1",
        description="Booster T1 humanoid, 23 DoF",
        menagerie_dir="booster_t1",
        robot_descriptions_module="t1_mj_description",
        license="Apache-2.0 (Booster Robotics), via MuJoCo Menagerie",
        root_body="Trunk",
        feet={"left": "left_foot_link", "right": "right_foot_link"},
        self_collision=(
            (("AL3", "left_hand_link"), ("Trunk", "Hip_Yaw_Left", "Shank_Left")),
            (("AR3", "right_hand_link"), ("Trunk", "Hip_Yaw_Right", "Shank_Right")),
            (
                ("Hip_Yaw_Left", "Shank_Left", "left_foot_link"),
                ("Hip_Yaw_Right", "Shank_Right", "right_foot_link"),
            ),
        ),
        actuators=t1_actuators(),
    )


ROBOTS: dict[str, Callable[[], RobotConfig]] = {"g1": g1, "t1": t1}
"""Registry: name -> factory."""


def get_robot(name: str) -> RobotConfig:
    """Look a robot up by name; :class:`UnknownNameError` lists the registered ones."""
    try:
        return ROBOTS[name]()
    except KeyError:
        raise UnknownNameError(
            f"unknown robot {name!r}; registered robots: {', '.join(sorted(ROBOTS))}"
        ) from None


def robot_names() -> list[str]:
    return sorted(ROBOTS)
