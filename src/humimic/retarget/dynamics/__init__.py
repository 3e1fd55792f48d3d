"""Dynamics retargeting: a kinematic reference made into one the simulated robot can replay.

:mod:`.sampler` optimizes it (sampling MPC with an :mod:`.ilqr` polish), :mod:`.inverse`
reads the torques and flight the reference asks for, :mod:`.replays` replays controls
open-loop and checks them, :mod:`.refinement` composes them into ``humimic refine``.
"""

from humimic.retarget.dynamics.inverse import (
    FLIGHT_CLEARANCE,
    inverse_dynamics_torques,
    reference_flight,
)
from humimic.retarget.dynamics.plans import DynamicsResult, knot_weights
from humimic.retarget.dynamics.refinement import refine
from humimic.retarget.dynamics.replays import (
    check_replay,
    evaluate_replay,
    perturbed_models,
    physics_steps_per_frame,
    replay,
)
from humimic.retarget.dynamics.sampler import DynamicsRetargeter

__all__ = [
    "FLIGHT_CLEARANCE",
    "DynamicsResult",
    "DynamicsRetargeter",
    "check_replay",
    "evaluate_replay",
    "inverse_dynamics_torques",
    "knot_weights",
    "perturbed_models",
    "physics_steps_per_frame",
    "reference_flight",
    "refine",
    "replay",
]
