"""Whole-body motion tracking (BeyondMimic) on MuJoCo, trained with rsl_rl PPO.

Modules: :mod:`.config` (task and domain-randomization configs), :mod:`.env` (the rsl_rl
``VecEnv``), :mod:`.backend` (the simulator protocol and the MuJoCo CPU backend),
:mod:`.rewards` / :mod:`.terminations` (MDP terms), :mod:`.dr` (parameter sampling),
:mod:`.state` (the tensors terms read), :mod:`.math` (torch rotations), :mod:`.rsl` (the one
boundary to rsl_rl).
"""

from humimic.tracking.backend import (
    MujocoCpuBackend,
    PhysicsBackend,
    PhysicsParams,
    PhysicsReadout,
    training_model,
)
from humimic.tracking.config import (
    DR_PROFILES,
    TRACKING_TASKS,
    AdaptiveSampling,
    DomainRandomization,
    ObservationNoise,
    ResetNoise,
    TermConfig,
    TrackingConfig,
    dr_default,
    dr_none,
    dr_profile,
    g1_tracking,
    load_dr_profile,
    t1_tracking,
    tracking_task,
)
from humimic.tracking.env import TrackingEnv, build_backend, tracking_model
from humimic.tracking.rsl import PpoConfig, tracking_ppo, train_cfg
from humimic.tracking.state import TrackingState

__all__ = [
    "DR_PROFILES",
    "TRACKING_TASKS",
    "AdaptiveSampling",
    "DomainRandomization",
    "MujocoCpuBackend",
    "ObservationNoise",
    "PhysicsBackend",
    "PhysicsParams",
    "PhysicsReadout",
    "PpoConfig",
    "ResetNoise",
    "TermConfig",
    "TrackingConfig",
    "TrackingEnv",
    "TrackingState",
    "build_backend",
    "dr_default",
    "dr_none",
    "dr_profile",
    "g1_tracking",
    "load_dr_profile",
    "t1_tracking",
    "tracking_model",
    "tracking_ppo",
    "tracking_task",
    "train_cfg",
    "training_model",
]
