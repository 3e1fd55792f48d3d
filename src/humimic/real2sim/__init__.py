"""Real2sim: robot logs, the simulator's residual against them, and the effects it lacks.

This is the first slice of issue 4: the effect vocabulary, realistic logs with injected
(undeclared) effects, robot-log I/O, and the k-step prediction error of the nominal model.
Attribution, identification and the corrected model come next.
"""

from humimic.real2sim.effects import EFFECTS, Effect, Injection, parse_injection
from humimic.real2sim.residual import KStepError, kstep_error
from humimic.real2sim.robotlog import RobotLog, read_robot_log, write_robot_log
from humimic.real2sim.simulate import LogSettings, fixed_base_spec, simulate_log

__all__ = [
    "EFFECTS",
    "Effect",
    "Injection",
    "KStepError",
    "LogSettings",
    "RobotLog",
    "fixed_base_spec",
    "kstep_error",
    "parse_injection",
    "read_robot_log",
    "simulate_log",
    "write_robot_log",
]
