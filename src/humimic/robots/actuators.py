"""Actuator models: PD position servos with explicit gains, effort limits and armature
(:class:`ActuatorRecipe`, and the recipes of the registered robots). Pure data: no simulator
imports.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from humimic.errors import UnknownNameError


def as_written(x: float) -> float:
    """``x`` to six significant digits, as MuJoCo's XML writer prints it: a number set in a
    spec this way survives an MJCF round trip (``robots export``) exactly."""
    return float(f"{x:.6g}")


@dataclass(frozen=True, kw_only=True)
class MotorSpec:
    """One motor (or motor group) as seen from the joint it drives.

    Attributes:
        armature: Reflected rotor inertia at the joint [kg m^2].
        effort_limit: Peak torque at the joint [N m].
        velocity_limit: Maximum joint speed [rad/s].
    """

    armature: float
    effort_limit: float
    velocity_limit: float


@dataclass(frozen=True, kw_only=True)
class JointActuator:
    """The resolved servo of one joint: what the simulator gets, with every number explicit."""

    joint: str
    kp: float
    kd: float
    effort_limit: float
    armature: float
    velocity_limit: float


@dataclass(frozen=True, kw_only=True)
class ActuatorRecipe:
    """Rotor-inertia gain recipe.

    The recipe (after BeyondMimic and mjlab) derives the gains from the reflected rotor
    inertia (armature) ``I`` of each motor so that every joint servo behaves like a
    second-order system with the same natural frequency ``wn`` and damping ratio ``zeta``
    about its own rotor::

        kp = I * wn**2
        kd = 2 * zeta * I * wn

    Two motors driving one joint through a linkage (the G1's ankles and waist roll/pitch)
    double the armature and the effort limit (``G1_MOTOR_2X5020``).

    Attributes:
        motors: Joint-name regular expression -> motor. Every actuated joint must match
            exactly one pattern.
        natural_frequency_hz: Servo natural frequency.
        damping_ratio: Servo damping ratio.
    """

    motors: dict[str, MotorSpec]
    natural_frequency_hz: float = 10.0
    damping_ratio: float = 2.0

    def resolve(self, joint_names: list[str]) -> dict[str, JointActuator]:
        """Resolve one :class:`JointActuator` per joint name.

        Raises:
            UnknownNameError: If a joint matches no pattern or several.
        """
        wn = 2.0 * math.pi * self.natural_frequency_hz
        out: dict[str, JointActuator] = {}
        for joint in joint_names:
            hits = [p for p in self.motors if re.fullmatch(p, joint)]
            if len(hits) != 1:
                what = "no motor pattern" if not hits else f"several motor patterns {hits}"
                raise UnknownNameError(f"joint {joint!r} matches {what}")
            m = self.motors[hits[0]]
            # Six significant digits: the numbers survive an MJCF round trip exactly, and the
            # gains follow from the armature the simulator actually gets.
            arm = as_written(m.armature)
            out[joint] = JointActuator(
                joint=joint,
                kp=as_written(arm * wn**2),
                kd=as_written(2.0 * self.damping_ratio * arm * wn),
                effort_limit=m.effort_limit,
                armature=arm,
                velocity_limit=m.velocity_limit,
            )
        return out


# Unitree motors, reflected rotor inertia from the gear train (BeyondMimic, mjlab).
G1_MOTOR_5020 = MotorSpec(armature=0.003609725, effort_limit=25.0, velocity_limit=37.0)
G1_MOTOR_7520_14 = MotorSpec(armature=0.010177520, effort_limit=88.0, velocity_limit=32.0)
G1_MOTOR_7520_22 = MotorSpec(armature=0.025101925, effort_limit=139.0, velocity_limit=20.0)
G1_MOTOR_4010 = MotorSpec(armature=0.00425, effort_limit=5.0, velocity_limit=22.0)
G1_MOTOR_2X5020 = MotorSpec(armature=2 * 0.003609725, effort_limit=50.0, velocity_limit=37.0)


def g1_actuators() -> ActuatorRecipe:
    """Unitree G1 (29 DoF): motor per joint, 10 Hz natural frequency, damping ratio 2."""
    return ActuatorRecipe(
        motors={
            r".*_hip_(pitch|yaw)_joint|waist_yaw_joint": G1_MOTOR_7520_14,
            r".*_hip_roll_joint|.*_knee_joint": G1_MOTOR_7520_22,
            r".*_ankle_(pitch|roll)_joint|waist_(roll|pitch)_joint": G1_MOTOR_2X5020,
            r".*_shoulder_(pitch|roll|yaw)_joint|.*_elbow_joint|.*_wrist_roll_joint": G1_MOTOR_5020,
            r".*_wrist_(pitch|yaw)_joint": G1_MOTOR_4010,
        }
    )


def t1_actuators() -> ActuatorRecipe:
    """Booster T1 (23 DoF).

    Booster publishes no rotor inertias; these armatures are chosen so that the recipe gives
    gains near the vendor's MuJoCo model (kp 75 on the legs) and the effort limits are the model's.
    """
    leg = MotorSpec(armature=0.019, effort_limit=60.0, velocity_limit=12.0)
    hip = MotorSpec(armature=0.019, effort_limit=45.0, velocity_limit=12.0)
    hip_ry = MotorSpec(armature=0.012, effort_limit=30.0, velocity_limit=12.0)
    ankle_p = MotorSpec(armature=0.008, effort_limit=20.0, velocity_limit=12.0)
    ankle_r = MotorSpec(armature=0.006, effort_limit=15.0, velocity_limit=12.0)
    arm = MotorSpec(armature=0.005, effort_limit=18.0, velocity_limit=12.0)
    head = MotorSpec(armature=0.002, effort_limit=7.0, velocity_limit=12.0)
    waist = MotorSpec(armature=0.012, effort_limit=30.0, velocity_limit=12.0)
    return ActuatorRecipe(
        motors={
            r".*_Knee_Pitch": leg,
            r".*_Hip_Pitch": hip,
            r".*_Hip_(Roll|Yaw)": hip_ry,
            r".*_Ankle_Pitch": ankle_p,
            r".*_Ankle_Roll": ankle_r,
            r".*_(Shoulder|Elbow)_.*": arm,
            r"AAHead_yaw|Head_pitch": head,
            r"Waist": waist,
        }
    )


def h1_actuators() -> ActuatorRecipe:
    """Unitree H1 (19 DoF).

    The model's own numbers (Menagerie ``unitree_h1``): every joint's armature is its default
    0.1 kg m^2, the effort limits are its motors' ``ctrlrange`` (hips and torso 200, knees 300,
    ankles, shoulder pitch and roll 40, shoulder yaw and elbows 18 N m). The model gives no
    joint speeds: 20 rad/s is a stated default (the G1's slowest motor's), not a measured
    figure.
    """
    speed = 20.0

    def motor(effort: float) -> MotorSpec:
        return MotorSpec(armature=0.1, effort_limit=effort, velocity_limit=speed)

    return ActuatorRecipe(
        motors={
            r".*_hip_(yaw|roll|pitch)|torso": motor(200.0),
            r".*_knee": motor(300.0),
            r".*_ankle|.*_shoulder_(pitch|roll)": motor(40.0),
            r".*_shoulder_yaw|.*_elbow": motor(18.0),
        }
    )


def berkeley_humanoid_actuators() -> ActuatorRecipe:
    """Berkeley Humanoid (12 DoF, legs only; Menagerie ``berkeley_humanoid``).

    The model's own numbers: armatures and effort limits per joint class (hip roll and
    abduction 0.0056 kg m^2 and 20 N m, hip flexion 0.007614 and 30, knee 0.0056 and 30, ankle
    flexion 0.0056 and 20, ankle abduction 0.0004941 and 5). The model gives no joint speeds:
    20 rad/s is a stated default, not a measured figure.
    """
    speed = 20.0
    return ActuatorRecipe(
        motors={
            r"L[LR]_H(R|AA)": MotorSpec(armature=0.0056, effort_limit=20.0, velocity_limit=speed),
            r"L[LR]_HFE": MotorSpec(armature=0.007614, effort_limit=30.0, velocity_limit=speed),
            r"L[LR]_KFE": MotorSpec(armature=0.0056, effort_limit=30.0, velocity_limit=speed),
            r"L[LR]_FFE": MotorSpec(armature=0.0056, effort_limit=20.0, velocity_limit=speed),
            r"L[LR]_FAA": MotorSpec(armature=0.0004941, effort_limit=5.0, velocity_limit=speed),
        }
    )


def apollo_actuators() -> ActuatorRecipe:
    """Apptronik Apollo (32 DoF; Menagerie ``apptronik_apollo``).

    The model's own numbers: each joint's armature and its ``actuatorfrcrange`` as the effort
    limit (where the left and right joints' armatures differ in the fifth digit, each keeps
    its own). The model gives no joint speeds: 20 rad/s is a stated default, not a measured
    figure.
    """
    speed = 20.0
    table = {
        r"torso_yaw|[lr]_hip_ie": (0.231424, 120.0),
        r"torso_roll": (1.56493, 414.0),
        r"torso_pitch": (0.970692, 315.0),
        r"neck_yaw|[lr]_wrist_roll": (0.0368, 10.6),
        r"neck_roll": (0.00305531, 34.2),
        r"neck_pitch": (0.00256298, 34.2),
        r"l_shoulder_aa": (0.0982771, 78.0),
        r"r_shoulder_aa": (0.098338, 78.0),
        r"l_shoulder_ie": (0.0823104, 67.0),
        r"r_shoulder_ie": (0.0823191, 67.0),
        r"[lr]_shoulder_fe": (0.112768, 114.0),
        r"[lr]_elbow_fe": (0.102645, 114.0),
        r"l_wrist_yaw": (0.00329371, 34.2),
        r"r_wrist_yaw": (0.0032937, 34.2),
        r"l_wrist_pitch": (0.00288074, 34.2),
        r"r_wrist_pitch": (0.00288075, 34.2),
        r"l_hip_aa": (0.399395, 494.0),
        r"r_hip_aa": (0.399396, 494.0),
        r"[lr]_hip_fe": (0.187096, 342.0),
        r"[lr]_knee_fe": (0.292264, 336.0),
        r"[lr]_ankle_ie": (0.121874, 120.0),
        r"[lr]_ankle_pd": (0.205456, 150.0),
    }
    return ActuatorRecipe(
        motors={
            p: MotorSpec(armature=arm, effort_limit=eff, velocity_limit=speed)
            for p, (arm, eff) in table.items()
        }
    )


def op3_actuators() -> ActuatorRecipe:
    """Robotis OP3 (20 DoF; Menagerie ``robotis_op3``): one Dynamixel XM430-W350 per joint.

    The model's own numbers: armature 0.045 kg m^2 and effort limit 5 N m on every joint, and
    the natural frequency (3.45 Hz) at which the recipe gives the model's own kp of 21.1 N m/rad
    (the 10 Hz of the larger robots would ask kp 178 of a 5 N m servo). Speed: the XM430-W350's
    no-load 46 rev/min at 12 V (4.8 rad/s), the motor's datasheet figure, not the model's.
    """
    motor = MotorSpec(armature=0.045, effort_limit=5.0, velocity_limit=4.8)
    wn = math.sqrt(21.1 / 0.045)
    return ActuatorRecipe(motors={r".*": motor}, natural_frequency_hz=wn / (2.0 * math.pi))
