"""Build and step robot models: backends, model builders, robot deltas (how a robot differs
from its nominal model), physics parameters, domain randomization, the effect vocabulary and
physics files.

It imports robots and core modules only; it knows no MDP, reward or diagnosis. The MuJoCo Warp
backend is :mod:`humimic.sim.warp_backend` (it needs ``humimic[gpu]``). Names load on first use,
so that reading a profile or a physics file does not import torch.
"""

from typing import TYPE_CHECKING

from humimic.lazy import lazy_attributes

if TYPE_CHECKING:
    from humimic.sim.backend import MujocoCpuBackend, PhysicsBackend, PhysicsReadout, TensorBackend
    from humimic.sim.delta import Change, RobotDelta, Structural
    from humimic.sim.effects import EFFECTS, Effect, Injection, parse_injection
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
        dr_wide,
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

_WHERE = {
    "Change": "humimic.sim.delta",
    "DEFAULT_SIM_DT": "humimic.sim.setup",
    "DR_PROFILES": "humimic.sim.randomization",
    "DomainRandomization": "humimic.sim.randomization",
    "EFFECTS": "humimic.sim.effects",
    "Effect": "humimic.sim.effects",
    "Injection": "humimic.sim.effects",
    "ModelLayout": "humimic.sim.params",
    "MujocoCpuBackend": "humimic.sim.backend",
    "ObservationNoise": "humimic.sim.randomization",
    "PHYSICS_DT": "humimic.sim.models",
    "Physics": "humimic.sim.physics",
    "PhysicsBackend": "humimic.sim.backend",
    "PhysicsParams": "humimic.sim.params",
    "PhysicsReadout": "humimic.sim.backend",
    "RobotDelta": "humimic.sim.delta",
    "SHIPPED": "humimic.sim.physics",
    "SimSetup": "humimic.sim.setup",
    "Structural": "humimic.sim.delta",
    "TensorBackend": "humimic.sim.backend",
    "WarpOptions": "humimic.sim.setup",
    "build_backend": "humimic.sim.setup",
    "build_model": "humimic.sim.setup",
    "dr_default": "humimic.sim.randomization",
    "dr_wide": "humimic.sim.randomization",
    "dr_none": "humimic.sim.randomization",
    "dr_profile": "humimic.sim.randomization",
    "fixed_base_spec": "humimic.sim.models",
    "key_body_setup": "humimic.sim.setup",
    "load_dr_profile": "humimic.sim.randomization",
    "load_physics": "humimic.sim.physics",
    "parse_injection": "humimic.sim.effects",
    "physics_copies": "humimic.sim.params",
    "prediction_spec": "humimic.sim.models",
    "training_model": "humimic.sim.models",
    "write_physics": "humimic.sim.physics",
}
"""Name -> the module that defines it."""


__getattr__ = lazy_attributes(__name__, _WHERE)

__all__ = [
    "DEFAULT_SIM_DT",
    "DR_PROFILES",
    "EFFECTS",
    "PHYSICS_DT",
    "SHIPPED",
    "Change",
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
    "RobotDelta",
    "SimSetup",
    "Structural",
    "TensorBackend",
    "WarpOptions",
    "build_backend",
    "build_model",
    "dr_default",
    "dr_none",
    "dr_profile",
    "dr_wide",
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
