"""Build and step robot models: backends, model builders, physics parameters, domain
randomization, the effect vocabulary and physics files.

It imports robots and core modules only; it knows no MDP, reward or diagnosis. The MuJoCo Warp
backend is :mod:`humimic.sim.warp_backend` (imported on use: it needs ``humimic[gpu]``).
"""

from humimic.sim.backend import MujocoCpuBackend, PhysicsBackend, PhysicsReadout, TensorBackend
from humimic.sim.effects import EFFECTS, Correction, Effect, Injection, parse_injection
from humimic.sim.models import PHYSICS_DT, fixed_base_spec, prediction_spec, training_model
from humimic.sim.params import ModelLayout, PhysicsParams, physics_copies
from humimic.sim.physics import SHIPPED, Physics, load_physics, write_physics
from humimic.sim.randomization import (
    DR_PROFILES,
    DomainRandomization,
    ObservationNoise,
    dr_default,
    dr_none,
    dr_profile,
    load_dr_profile,
)
from humimic.sim.setup import (
    DEFAULT_SIM_DT,
    SimSetup,
    WarpOptions,
    build_backend,
    build_model,
    key_body_setup,
)

__all__ = [
    "DEFAULT_SIM_DT",
    "DR_PROFILES",
    "EFFECTS",
    "PHYSICS_DT",
    "SHIPPED",
    "Correction",
    "DomainRandomization",
    "Effect",
    "Injection",
    "ModelLayout",
    "MujocoCpuBackend",
    "ObservationNoise",
    "Physics",
    "PhysicsBackend",
    "PhysicsParams",
    "PhysicsReadout",
    "SimSetup",
    "TensorBackend",
    "WarpOptions",
    "build_backend",
    "build_model",
    "dr_default",
    "dr_none",
    "dr_profile",
    "fixed_base_spec",
    "key_body_setup",
    "load_dr_profile",
    "load_physics",
    "parse_injection",
    "physics_copies",
    "prediction_spec",
    "training_model",
    "write_physics",
]
