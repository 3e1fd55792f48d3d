"""Robot models, their actuators, and the registry.

Names load on first use, so that reading the registry does not import MuJoCo.
"""

from typing import TYPE_CHECKING

from humimic.lazy import lazy_attributes

if TYPE_CHECKING:
    from humimic.robots.actuators import ActuatorRecipe, JointActuator, MotorSpec
    from humimic.robots.model import export_nominal, nominal_model, nominal_spec
    from humimic.robots.registry import ROBOTS, RobotConfig, get_robot, robot_names

_WHERE = {
    "ActuatorRecipe": "humimic.robots.actuators",
    "JointActuator": "humimic.robots.actuators",
    "MotorSpec": "humimic.robots.actuators",
    "export_nominal": "humimic.robots.model",
    "nominal_model": "humimic.robots.model",
    "nominal_spec": "humimic.robots.model",
    "ROBOTS": "humimic.robots.registry",
    "RobotConfig": "humimic.robots.registry",
    "get_robot": "humimic.robots.registry",
    "robot_names": "humimic.robots.registry",
}
"""Name -> the module that defines it."""


__getattr__ = lazy_attributes(__name__, _WHERE)

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
