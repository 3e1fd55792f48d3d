"""Retargeting human motion to robots: kinematic (mink IK)."""

from humimic.retarget.api import Retargeter, RetargetOutput
from humimic.retarget.kinematic import KinematicResult, KinematicRetargeter
from humimic.retarget.metrics import QualityReport, evaluate

__all__ = [
    "KinematicResult",
    "KinematicRetargeter",
    "QualityReport",
    "RetargetOutput",
    "Retargeter",
    "evaluate",
]
