"""Whole-body motion tracking (BeyondMimic) on MuJoCo, trained with rsl_rl PPO.

Modules: :mod:`.config` (the task), :mod:`.env` (the rsl_rl ``VecEnv``), :mod:`.rewards` /
:mod:`.terminations` (MDP terms), :mod:`.state` (the tensors terms read), :mod:`.math` (torch
rotations), :mod:`.rsl` (the one boundary to rsl_rl). The simulator is :mod:`humimic.sim`.
"""

from humimic.tracking.config import (
    TRACKING_TASKS,
    AdaptiveSampling,
    ResetNoise,
    TermConfig,
    TrackingConfig,
    g1_tracking,
    t1_tracking,
    tracking_task,
)
from humimic.tracking.env import TrackingEnv, tracking_backend, tracking_model
from humimic.tracking.rsl import PpoConfig, tracking_ppo, train_cfg
from humimic.tracking.state import TrackingState

__all__ = [
    "TRACKING_TASKS",
    "AdaptiveSampling",
    "PpoConfig",
    "ResetNoise",
    "TermConfig",
    "TrackingConfig",
    "TrackingEnv",
    "TrackingState",
    "g1_tracking",
    "t1_tracking",
    "tracking_backend",
    "tracking_model",
    "tracking_ppo",
    "tracking_task",
    "train_cfg",
]
