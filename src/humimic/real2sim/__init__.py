"""Real2sim: robot logs, the simulator's residual against them, and the effects it lacks.

Issue 4, in progress: the effect vocabulary, realistic logs with injected (undeclared)
effects, robot-log I/O, the k-step prediction error of a model, and a diagnosis that finds and
sizes joint friction, damping, armature and drive gain mismatches (docs/real2sim.md).
"""

from humimic.real2sim.diagnose import Diagnosis, Finding, diagnose_log
from humimic.real2sim.effects import EFFECTS, Effect, Injection, parse_injection
from humimic.real2sim.residual import KStepError, kstep_error
from humimic.real2sim.robotlog import RobotLog, read_robot_log, write_robot_log
from humimic.real2sim.simulate import LogSettings, fixed_base_spec, simulate_log

__all__ = [
    "EFFECTS",
    "Diagnosis",
    "Effect",
    "Finding",
    "Injection",
    "KStepError",
    "LogSettings",
    "RobotLog",
    "diagnose_log",
    "fixed_base_spec",
    "kstep_error",
    "parse_injection",
    "read_robot_log",
    "simulate_log",
    "write_robot_log",
]
