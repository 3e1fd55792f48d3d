"""The robot registry: every robot humimic knows, as typed data."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from humimic.errors import UnknownNameError
from humimic.robots.actuators import (
    ActuatorRecipe,
    apollo_actuators,
    berkeley_humanoid_actuators,
    g1_actuators,
    h1_actuators,
    op3_actuators,
    t1_actuators,
)


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
        actuators: Gain recipe for the PD servos.
        key_bodies: The bodies whose poses stand for a motion of the robot, the root first:
            what whole-body tracking follows and dynamics retargeting scores (mjlab's tracked
            bodies on the G1).
        torso_body: The upper-body link that anchors a tracked reference (BeyondMimic's anchor)
            and whose CoM domain randomization moves.
        floor_geom: Name of the floor geom in the scene.
        joint_ranges: Joint name -> (lower, upper) [rad] for a model that gives its joints no
            range (Menagerie's OP3): stated ranges, applied when the model is built. Empty: the
            model's own.
        model_file: The scene MJCF of a robot a user added (``humimic robots add``); None for
            the registered robots, found by ``menagerie_dir`` and ``xml``.
    """

    name: str
    description: str
    menagerie_dir: str
    xml: str = "scene.xml"
    robot_descriptions_module: str | None = None
    license: str
    root_body: str
    feet: dict[str, str]
    actuators: ActuatorRecipe
    key_bodies: tuple[str, ...]
    torso_body: str
    floor_geom: str = "floor"
    joint_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    model_file: Path | None = None


def g1() -> RobotConfig:
    """Unitree G1, 29 DoF (MuJoCo Menagerie ``unitree_g1``, BSD-3-Clause)."""
    return RobotConfig(
        name="g1",
        description="Unitree G1 humanoid, 29 DoF",
        menagerie_dir="unitree_g1",
        robot_descriptions_module="g1_mj_description",
        license="BSD-3-Clause (Unitree Robotics), via MuJoCo Menagerie",
        root_body="pelvis",
        feet={"left": "left_ankle_roll_link", "right": "right_ankle_roll_link"},
        actuators=g1_actuators(),
        key_bodies=(
            "pelvis",
            *(f"left_{b}_link" for b in ("hip_roll", "knee", "ankle_roll")),
            *(f"right_{b}_link" for b in ("hip_roll", "knee", "ankle_roll")),
            "torso_link",
            *(f"left_{b}_link" for b in ("shoulder_roll", "elbow", "wrist_yaw")),
            *(f"right_{b}_link" for b in ("shoulder_roll", "elbow", "wrist_yaw")),
        ),
        torso_body="torso_link",
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
        actuators=t1_actuators(),
        key_bodies=(
            *("Trunk", "Waist"),
            *("Hip_Roll_Left", "Shank_Left", "left_foot_link"),
            *("Hip_Roll_Right", "Shank_Right", "right_foot_link"),
            *("AL1", "AL3", "left_hand_link"),
            *("AR1", "AR3", "right_hand_link"),
        ),
        torso_body="Trunk",
    )


def h1() -> RobotConfig:
    """Unitree H1, 19 DoF (MuJoCo Menagerie ``unitree_h1``, BSD-3-Clause). No wrists: the
    hand is the end of the elbow link."""
    return RobotConfig(
        name="h1",
        description="Unitree H1 humanoid, 19 DoF",
        menagerie_dir="unitree_h1",
        robot_descriptions_module="h1_mj_description",
        license="BSD-3-Clause (Unitree Robotics), via MuJoCo Menagerie",
        root_body="pelvis",
        feet={"left": "left_ankle_link", "right": "right_ankle_link"},
        actuators=h1_actuators(),
        key_bodies=(
            "pelvis",
            *(f"left_{b}_link" for b in ("hip_roll", "knee", "ankle")),
            *(f"right_{b}_link" for b in ("hip_roll", "knee", "ankle")),
            "torso_link",
            *(f"left_{b}_link" for b in ("shoulder_roll", "elbow")),
            *(f"right_{b}_link" for b in ("shoulder_roll", "elbow")),
        ),
        torso_body="torso_link",
    )


def berkeley_humanoid() -> RobotConfig:
    """Berkeley Humanoid, 12 DoF, legs only (MuJoCo Menagerie ``berkeley_humanoid``,
    BSD-3-Clause). The torso is the base and the anchor."""
    return RobotConfig(
        name="berkeley_humanoid",
        description="Berkeley Humanoid, 12 DoF, legs only",
        menagerie_dir="berkeley_humanoid",
        xml="scene.xml",
        license="BSD-3-Clause (Hybrid Robotics), via MuJoCo Menagerie",
        root_body="torso",
        feet={"left": "ll_faa", "right": "lr_faa"},
        actuators=berkeley_humanoid_actuators(),
        key_bodies=("torso", "ll_hfe", "ll_kfe", "ll_faa", "lr_hfe", "lr_kfe", "lr_faa"),
        torso_body="torso",
    )


def apollo() -> RobotConfig:
    """Apptronik Apollo, 32 DoF (MuJoCo Menagerie ``apptronik_apollo``, Apache-2.0). Its
    contacts are explicit pairs in the model file; :func:`humimic.robots.nominal_spec` makes
    its collision geoms collide as the other robots' do."""
    return RobotConfig(
        name="apollo",
        description="Apptronik Apollo humanoid, 32 DoF",
        menagerie_dir="apptronik_apollo",
        license="Apache-2.0 (Apptronik), via MuJoCo Menagerie",
        root_body="base_link",
        feet={"left": "l_foot_link", "right": "r_foot_link"},
        actuators=apollo_actuators(),
        key_bodies=(
            "base_link",
            *(f"l_{b}_link" for b in ("hip_aa", "knee_fe", "foot")),
            *(f"r_{b}_link" for b in ("hip_aa", "knee_fe", "foot")),
            "torso_link",
            *(f"l_{b}_link" for b in ("shoulder_ie", "elbow_fe", "wrist_pitch")),
            *(f"r_{b}_link" for b in ("shoulder_ie", "elbow_fe", "wrist_pitch")),
        ),
        torso_body="torso_link",
    )


def _op3_ranges() -> dict[str, tuple[float, float]]:
    """Stated joint ranges for the OP3, whose model gives none: a human's range of motion
    (after the ranges the G1 and H1 give their joints), in the signs of the OP3's joint axes
    (worked out from the model: which way each joint moves the foot or the hand), not
    ROBOTIS's figures. Knees bend one way only; the elbows both (the three-joint arm reaches
    one elbow pose with its shoulder pitch turned either way, so neither sign is the "wrong"
    bend); the shoulder roll is 0 with the arms out sideways, as the model's zero pose has."""
    r = {
        "head_pan": (-1.4, 1.4),
        "head_tilt": (-0.7, 0.7),
        "l_sho_pitch": (-2.8, 2.8),
        "l_sho_roll": (-1.4, 1.75),  # + lowers the left arm from the sideways zero pose.
        "l_el": (-2.4, 2.4),
        "l_hip_yaw": (-0.8, 0.8),
        "l_hip_roll": (-0.8, 0.45),  # + brings the left foot in (adduction).
        "l_hip_pitch": (-2.0, 0.5),  # + swings the left leg back (extension).
        "l_knee": (0.0, 2.4),  # + bends the left knee.
        "l_ank_pitch": (-0.9, 0.6),  # + lifts the left toes (dorsiflexion).
        "l_ank_roll": (-0.5, 0.5),
    }
    mirrored = {"l_sho_pitch", "l_el", "l_hip_yaw", "l_ank_roll", "head_pan", "head_tilt"}
    out = dict(r)
    for name, (lo, hi) in r.items():
        if name.startswith("l_"):
            out["r_" + name[2:]] = (lo, hi) if name in mirrored else (-hi, -lo)
    return out


def op3() -> RobotConfig:
    """Robotis OP3, 20 DoF, 0.5 m (MuJoCo Menagerie ``robotis_op3``, Apache-2.0). Its model
    gives no joint ranges: :func:`_op3_ranges` states them."""
    return RobotConfig(
        name="op3",
        description="Robotis OP3 humanoid, 20 DoF, 0.5 m",
        menagerie_dir="robotis_op3",
        license="Apache-2.0 (ROBOTIS), via MuJoCo Menagerie",
        root_body="body_link",
        feet={"left": "l_ank_roll_link", "right": "r_ank_roll_link"},
        actuators=op3_actuators(),
        key_bodies=(
            "body_link",
            *(f"l_{b}_link" for b in ("hip_pitch", "knee", "ank_roll")),
            *(f"r_{b}_link" for b in ("hip_pitch", "knee", "ank_roll")),
            "head_tilt_link",
            *(f"l_{b}_link" for b in ("sho_roll", "el")),
            *(f"r_{b}_link" for b in ("sho_roll", "el")),
        ),
        torso_body="body_link",
        joint_ranges=_op3_ranges(),
    )


ROBOTS: dict[str, Callable[[], RobotConfig]] = {
    "apollo": apollo,
    "berkeley_humanoid": berkeley_humanoid,
    "g1": g1,
    "h1": h1,
    "op3": op3,
    "t1": t1,
}
"""Registry: name -> factory."""


def get_robot(name: str, source: str | None = None) -> RobotConfig:
    """Look a robot up by name: a registered one, else one the user added (``humimic robots
    add``, :mod:`humimic.robots.user`); :class:`UnknownNameError` lists them all.

    Args:
        name: Registry name.
        source: Where the name came from, for the message: a flag (``"--robot"``) or a file.
    """
    from humimic.robots.user import load_user_robot, user_robot_folder

    if name in ROBOTS:
        return ROBOTS[name]()
    if user_robot_folder(name) is not None:
        return RobotConfig(**load_user_robot(name))
    where = f"{source}: " if source else ""
    raise UnknownNameError(f"{where}unknown robot {name!r}; robots: {', '.join(robot_names())}")


def robot_names() -> list[str]:
    """The registered robots and the ones the user added, sorted."""
    from humimic.robots.user import user_robot_names

    return sorted({*ROBOTS, *user_robot_names()})
