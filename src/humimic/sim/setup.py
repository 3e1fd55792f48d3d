"""One description of a simulation (robot, read-out, physics, backend) and the two builders of it.

Tracking and dynamics retargeting both describe what they simulate as a :class:`SimSetup`;
:func:`build_model` compiles its training model and :func:`build_backend` the batched backend.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Literal

import mujoco
import numpy as np
import torch

from humimic.errors import InputError
from humimic.robots.registry import get_robot
from humimic.sim.backend import MujocoCpuBackend, PhysicsBackend, StepMethod
from humimic.sim.effects import EFFECTS
from humimic.sim.models import training_model
from humimic.sim.physics import Physics

DEFAULT_SIM_DT = 0.005
"""Physics step of the training model [s] (200 Hz, mjlab's tracking task)."""

BackendName = Literal["cpu", "warp"]


@dataclass(frozen=True, kw_only=True)
class WarpOptions:
    """Settings of the MuJoCo Warp backend.

    Attributes:
        nconmax: Contacts per world, pooled over worlds (default: a bound no floor contact
            state exceeds, :func:`humimic.sim.warp_backend.capacity`).
        njmax: Constraint rows per world (default: likewise a bound).
        cuda_graph: Replay each env step's physics as a captured CUDA graph.
    """

    nconmax: int | None = None
    njmax: int | None = None
    cuda_graph: bool = True


@dataclass(frozen=True, kw_only=True)
class SimSetup:
    """What is simulated and how.

    Attributes:
        robot: Registry name of the robot.
        body_names: Bodies whose pose and velocity are read (the root first).
        contact_body_names: Bodies whose floor contacts are counted.
        foot_body_names: Bodies whose net floor contact force is read (default: the robot's
            feet).
        com_body: The body whose CoM :attr:`~humimic.sim.params.PhysicsParams.com_offset`
            moves (default: none).
        sim_dt: Physics step [s].
        physics: Fixed changes to the nominal model (a physics file).
        backend: ``cpu`` (:class:`~humimic.sim.backend.MujocoCpuBackend`) or ``warp``
            (:class:`~humimic.sim.warp_backend.MujocoWarpBackend`, ``humimic[gpu]``).
        warp: Settings of the ``warp`` backend.
        step_method: CPU stepping: ``rollout`` (``mujoco.rollout``) or ``threads``.
        num_threads: CPU simulation threads (default: all cores).
    """

    robot: str
    body_names: tuple[str, ...]
    contact_body_names: tuple[str, ...] = ()
    foot_body_names: tuple[str, ...] | None = None
    com_body: str | None = None
    sim_dt: float = DEFAULT_SIM_DT
    physics: Physics | None = None
    backend: BackendName = "cpu"
    warp: WarpOptions = field(default_factory=WarpOptions)
    step_method: StepMethod = "rollout"
    num_threads: int | None = None

    @property
    def feet(self) -> tuple[str, ...]:
        """The foot bodies read (the robot's feet unless given)."""
        if self.foot_body_names is not None:
            return self.foot_body_names
        return tuple(get_robot(self.robot).feet.values())


def key_body_setup(robot: str) -> SimSetup:
    """The setup that reads a robot's key bodies
    (:attr:`~humimic.robots.registry.RobotConfig.key_bodies`), CoM offsets on its torso."""
    r = get_robot(robot)
    return SimSetup(robot=r.name, body_names=r.key_bodies, com_body=r.torso_body)


def build_model(
    setup: SimSetup, *, menagerie_root: str | os.PathLike[str] | None = None
) -> mujoco.MjModel:
    """The training model of a setup (mesh-free, with the read-out sensors), with the changes
    of ``setup.physics``.

    Raises:
        InputError: If the physics file is written for another robot.
        UnknownNameError: If a body is not in the robot.
    """
    ph = setup.physics
    if ph is not None and ph.robot is not None and ph.robot != setup.robot:
        raise InputError(f"{ph.where}: written for {ph.robot!r}, not {setup.robot!r}")
    if ph is not None:
        for inj in ph.effects:
            if EFFECTS[inj.effect].adds_joints:
                raise InputError(
                    f"{ph.where}: {inj.where}: {inj.effect} adds joints, which the simulation's "
                    "fixed joint layout cannot take (it is simulated in sysid logs only)"
                )
    return training_model(
        get_robot(setup.robot),
        body_names=setup.body_names,
        contact_body_names=setup.contact_body_names,
        foot_body_names=setup.feet,
        timestep=setup.sim_dt,
        menagerie_root=menagerie_root,
        edit=None if ph is None else ph.edit,
    )


def build_backend(
    setup: SimSetup,
    num_envs: int,
    *,
    model: mujoco.MjModel | None = None,
    per_env_models: bool = False,
    menagerie_root: str | os.PathLike[str] | None = None,
    device: str | torch.device = "cpu",
) -> PhysicsBackend:
    """The batched backend of a setup: ``setup.backend`` on ``device``.

    Args:
        setup: What to simulate.
        num_envs: Number of envs.
        model: A model from :func:`build_model` (building one takes seconds; reuse it).
        per_env_models: Let every env have its own physics parameters (``set_params``).
        menagerie_root: Where the robot files are.
        device: The torch device of the ``warp`` backend.
    """
    if model is None:
        model = build_model(setup, menagerie_root=menagerie_root)
    backend = _backend(setup, model, num_envs, per_env_models, device)
    if per_env_models and setup.physics is not None:
        # DR's friction draws are stated for the robot's own colliders; a physics file that
        # changed their friction (a slippery floor, a sysid claim) scales them, rather than
        # being replaced by them.
        g = backend.layout.collider_geoms
        own = build_model(replace(setup, physics=None), menagerie_root=menagerie_root)
        assert own.ngeom == model.ngeom  # A physics file changes geoms, it adds none.
        mine, theirs = own.geom_friction[g, 0], model.geom_friction[g, 0]
        ratio = np.where(mine > 0, theirs / np.where(mine > 0, mine, 1.0), 1.0)
        if not np.allclose(ratio, 1.0):
            backend.layout = replace(backend.layout, friction_ratio=ratio)
    return backend


def _backend(
    setup: SimSetup,
    model: mujoco.MjModel,
    num_envs: int,
    per_env_models: bool,
    device: str | torch.device,
) -> PhysicsBackend:
    names = {
        "body_names": setup.body_names,
        "contact_body_names": setup.contact_body_names,
        "foot_body_names": setup.feet,
        "com_body": setup.com_body,
        "per_env_models": per_env_models,
    }
    if setup.backend == "warp":
        from humimic.sim.warp_backend import MujocoWarpBackend

        w = setup.warp
        return MujocoWarpBackend(
            model, num_envs, device=device, nconmax=w.nconmax, njmax=w.njmax,
            cuda_graph=w.cuda_graph, **names,
        )  # fmt: skip
    return MujocoCpuBackend(
        model, num_envs, method=setup.step_method, nthread=setup.num_threads, **names
    )
