"""Robot models, their actuators, and the registry."""

from humimic.robots.actuators import ActuatorRecipe, JointActuator, MotorSpec
from humimic.robots.model import export_nominal, nominal_model, nominal_spec
from humimic.robots.registry import ROBOTS, RobotConfig, get_robot, robot_names

__all__ = [
    "ROBOTS",
    "ActuatorRecipe",
    "JointActuator",
    "MotorSpec",
    "RobotConfig",
    "export_nominal",
    "get_robot",
    "nominal_model",
    "nominal_spec",
    "robot_names",
]
