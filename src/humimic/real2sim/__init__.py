"""Real2sim: robot logs, the simulator's residual against them, and the effects it lacks.

Robot-log I/O, simulated logs with undeclared effects, the k-step prediction error of a model,
the diagnosis that finds and sizes the effects a model lacks, and a learned residual for what no
effect explains (docs/real2sim.md). The effect vocabulary is :mod:`humimic.sim.effects`.
"""

from humimic.real2sim.diagnose import Diagnosis, Finding, diagnose_log
from humimic.real2sim.residual import KStepError, kstep_error
from humimic.real2sim.robotlog import RobotLog, read_robot_log, write_robot_log
from humimic.real2sim.simulate import LogSettings, simulate_log

__all__ = [
    "Diagnosis",
    "Finding",
    "KStepError",
    "LogSettings",
    "RobotLog",
    "diagnose_log",
    "kstep_error",
    "read_robot_log",
    "simulate_log",
    "write_robot_log",
]
