"""Configuration of the motion-tracking environment: frozen dataclasses and factory functions.

``g1_tracking()`` is the G1 task with mjlab's tracking defaults. Domain randomization comes in
named profiles (``none``, ``default``; :func:`dr_profile`) or from a YAML file
(:func:`load_dr_profile`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import torch

from humimic.errors import InputError, UnknownNameError
from humimic.io import read_yaml
from humimic.tracking import rewards as rew
from humimic.tracking import terminations as term
from humimic.tracking.physics import Physics

Range = tuple[float, float]


@dataclass(frozen=True, kw_only=True)
class TermConfig:
    """One reward or termination term.

    Attributes:
        func: ``func(env, **params) -> Tensor`` of Shape: (num_envs,).
        weight: Reward weight (unused for terminations).
        params: Keyword arguments of ``func``.
        time_out: For terminations: a time limit, not a failure (PPO bootstraps it).
    """

    func: Callable[..., torch.Tensor]
    weight: float = 1.0
    params: dict[str, Any] = field(default_factory=dict)
    time_out: bool = False


@dataclass(frozen=True, kw_only=True)
class ObservationNoise:
    """Uniform noise half-widths added to the policy observations (mjlab's tracking values).

    Attributes:
        anchor_pos: Reference anchor position in the robot anchor frame [m].
        anchor_ori: Its 6D rotation.
        projected_gravity: Gravity in the base frame.
        base_ang_vel: Base angular velocity [rad/s].
        joint_pos: [rad]. joint_vel: [rad/s].
    """

    anchor_pos: float = 0.25
    anchor_ori: float = 0.05
    projected_gravity: float = 0.05
    base_ang_vel: float = 0.2
    joint_pos: float = 0.01
    joint_vel: float = 0.5


@dataclass(frozen=True, kw_only=True)
class DomainRandomization:
    """Per-env physics randomization, sampled at every reset. Ranges are ``(low, high)``.

    Attributes:
        friction: Floor and collider sliding friction (uniform).
        mass_scale: Per-link mass (and inertia) multiplier (log-uniform).
        com_offset: Anchor-body CoM offset per axis x, y, z [m] (uniform).
        kp_scale: Per-joint stiffness multiplier (log-uniform).
        kd_scale: Per-joint damping multiplier (log-uniform).
        armature_scale: Per-joint armature multiplier (log-uniform).
        joint_offset: Per-joint offset of the default joint position, i.e. of the PD targets,
            modelling encoder calibration error [rad] (uniform).
        action_delay: Delay of the actions in policy steps, integers inclusive (uniform).
        push_interval_s: Time between pushes [s]; ``None`` disables pushes.
        push_lin_vel: Base linear velocity change per axis x, y, z [m/s] (world frame).
        push_ang_vel: Base angular velocity change per axis [rad/s] (base frame).
        obs_noise: Policy observation noise; ``None`` disables it.
    """

    friction: Range = (1.0, 1.0)
    mass_scale: Range = (1.0, 1.0)
    com_offset: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    kp_scale: Range = (1.0, 1.0)
    kd_scale: Range = (1.0, 1.0)
    armature_scale: Range = (1.0, 1.0)
    joint_offset: Range = (0.0, 0.0)
    action_delay: tuple[int, int] = (0, 0)
    push_interval_s: Range | None = None
    push_lin_vel: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    push_ang_vel: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    obs_noise: ObservationNoise | None = None

    @property
    def randomizes_model(self) -> bool:
        """Whether any parameter of the physics model varies (needs per-env models)."""
        ranges = [self.friction, self.mass_scale, *self.com_offset, self.kp_scale]
        ranges += [self.kd_scale, self.armature_scale]
        return any(lo != hi for lo, hi in ranges)

    def validate(self, where: str = "dr") -> None:
        """Check every range; :class:`InputError` names the field."""

        def check(name: str, r: Any, positive: bool = False) -> None:
            ok = isinstance(r, tuple) and len(r) == 2
            ok = ok and all(isinstance(v, int | float) and math.isfinite(v) for v in r)
            if not ok or r[0] > r[1]:
                raise InputError(f"{where}.{name}: expected [low, high] numbers, got {r!r}")
            if positive and r[0] <= 0:
                raise InputError(f"{where}.{name}: scales must be positive, got {r!r}")

        check("friction", self.friction)
        if self.friction[0] < 0:
            raise InputError(f"{where}.friction: must not be negative, got {self.friction!r}")
        for name in ("mass_scale", "kp_scale", "kd_scale", "armature_scale"):
            check(name, getattr(self, name), positive=True)
        check("joint_offset", self.joint_offset)
        check("action_delay", self.action_delay)
        if self.action_delay[0] < 0 or any(int(v) != v for v in self.action_delay):
            raise InputError(f"{where}.action_delay: expected whole policy steps >= 0")
        for name in ("com_offset", "push_lin_vel", "push_ang_vel"):
            axes = getattr(self, name)
            if not (isinstance(axes, tuple) and len(axes) == 3):
                raise InputError(f"{where}.{name}: expected three [low, high] ranges (x, y, z)")
            for axis, r in zip("xyz", axes, strict=True):
                check(f"{name}.{axis}", r)
        if self.push_interval_s is not None:
            check("push_interval_s", self.push_interval_s, positive=True)


def dr_none() -> DomainRandomization:
    """No randomization: nominal physics, no delay, no pushes, no observation noise."""
    return DomainRandomization()


def dr_default() -> DomainRandomization:
    """The default sim-to-real profile.

    mjlab's tracking values where it has them (friction 0.3-1.2, torso CoM offset
    +-0.025/0.05/0.05 m, default joint offset +-0.01 rad, pushes every 1-3 s with its velocity
    ranges, its observation noise); mass, gain and armature scales of +-10 % and 0-1 policy
    steps of action delay are humimic's choice.
    """
    return DomainRandomization(
        friction=(0.3, 1.2),
        mass_scale=(0.9, 1.1),
        com_offset=((-0.025, 0.025), (-0.05, 0.05), (-0.05, 0.05)),
        kp_scale=(0.9, 1.1),
        kd_scale=(0.9, 1.1),
        armature_scale=(0.9, 1.1),
        joint_offset=(-0.01, 0.01),
        action_delay=(0, 1),
        push_interval_s=(1.0, 3.0),
        push_lin_vel=((-0.5, 0.5), (-0.5, 0.5), (-0.2, 0.2)),
        push_ang_vel=((-0.52, 0.52), (-0.52, 0.52), (-0.78, 0.78)),
        obs_noise=ObservationNoise(),
    )


DR_PROFILES: dict[str, Callable[[], DomainRandomization]] = {
    "none": dr_none,
    "default": dr_default,
}
"""Named domain-randomization profiles: name -> factory."""


def dr_profile(name: str) -> DomainRandomization:
    """A named profile; :class:`UnknownNameError` lists the known ones."""
    try:
        return DR_PROFILES[name]()
    except KeyError:
        raise UnknownNameError(
            f"unknown domain-randomization profile {name!r}; known: {', '.join(DR_PROFILES)}"
        ) from None


def _as_range(value: Any, where: str) -> Any:
    if isinstance(value, list | tuple):
        if value and all(isinstance(v, list | tuple) for v in value):
            return tuple(_as_range(v, where) for v in value)
        return tuple(value)
    raise InputError(f"{where}: expected a [low, high] list, got {value!r}")


def load_dr_profile(path: str | os.PathLike[str]) -> DomainRandomization:
    """Read a domain-randomization profile from YAML.

    The file is a mapping of :class:`DomainRandomization` fields. ``base: <profile>`` starts
    from a named profile (default ``none``); ``obs_noise`` is a mapping of
    :class:`ObservationNoise` fields, ``true`` for the defaults, or ``null``.

    Example::

        base: default
        friction: [0.5, 1.0]
        action_delay: [0, 2]
        obs_noise: {joint_vel: 1.0}

    Raises:
        InputError: Naming the file and the field, for unknown keys and bad values.
    """
    p = Path(path)
    raw = read_yaml(p)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise InputError(f"{p}: expected a mapping of domain-randomization fields")
    raw = dict(raw)
    base_name = raw.pop("base", "none")
    try:
        base = dr_profile(str(base_name))
    except UnknownNameError as e:
        raise InputError(f"{p}: base: {e}") from None
    known = {f.name for f in fields(DomainRandomization)}
    updates: dict[str, Any] = {}
    for key, value in raw.items():
        if key not in known:
            raise InputError(
                f"{p}: unknown field {key!r}; expected one of: base, {', '.join(sorted(known))}"
            )
        where = f"{p}: {key}"
        if key == "obs_noise":
            updates[key] = _obs_noise(value, where)
        elif key == "push_interval_s" and value is None:
            updates[key] = None
        else:
            updates[key] = _as_range(value, where)
    dr = replace(base, **updates)
    dr.validate(where=str(p))
    return dr


def _obs_noise(value: Any, where: str) -> ObservationNoise | None:
    if value is None or value is False:
        return None
    if value is True:
        return ObservationNoise()
    if not isinstance(value, dict):
        raise InputError(f"{where}: expected a mapping, true or null, got {value!r}")
    known = {f.name for f in fields(ObservationNoise)}
    for key, v in value.items():
        if key not in known:
            raise InputError(
                f"{where}: unknown field {key!r}; expected one of: {', '.join(sorted(known))}"
            )
        if not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise InputError(f"{where}.{key}: expected a number >= 0, got {v!r}")
    return ObservationNoise(**{k: float(v) for k, v in value.items()})


@dataclass(frozen=True, kw_only=True)
class ResetNoise:
    """Noise of reference state initialization (mjlab's tracking values).

    Attributes:
        pose: Root pose offsets x, y, z [m], roll, pitch, yaw [rad] (uniform).
        velocity: Root velocity offsets x, y, z [m/s], roll, pitch, yaw [rad/s] (uniform).
        joint_pos: Joint position offset [rad] (uniform), clipped to the soft limits.
    """

    pose: tuple[Range, Range, Range, Range, Range, Range] = (
        (-0.05, 0.05),
        (-0.05, 0.05),
        (-0.01, 0.01),
        (-0.1, 0.1),
        (-0.1, 0.1),
        (-0.2, 0.2),
    )
    velocity: tuple[Range, Range, Range, Range, Range, Range] = (
        (-0.5, 0.5),
        (-0.5, 0.5),
        (-0.2, 0.2),
        (-0.52, 0.52),
        (-0.52, 0.52),
        (-0.78, 0.78),
    )
    joint_pos: Range = (-0.1, 0.1)


@dataclass(frozen=True, kw_only=True)
class AdaptiveSampling:
    """BeyondMimic's adaptive sampling of start frames (mjlab's values).

    The clip is cut into bins of ``bin_s`` seconds. Failures raise their bin's weight (an
    exponential moving average with rate ``alpha`` per step); the weights are mixed with a
    uniform share ``uniform_ratio`` and smoothed towards earlier bins by a kernel
    ``lambda**k``, ``k < kernel_size`` (a failure is often caused a little before it shows).

    Attributes:
        enabled: Without it, start frames are uniform.
        bin_s: Bin length [s].
        alpha: Update rate of the failure average.
        uniform_ratio: Uniform share of the sampling weights.
        kernel_size: Smoothing kernel length (bins).
        kernel_lambda: Smoothing kernel decay.
    """

    enabled: bool = True
    bin_s: float = 1.0
    alpha: float = 0.001
    uniform_ratio: float = 0.1
    kernel_size: int = 3
    kernel_lambda: float = 0.8


@dataclass(frozen=True, kw_only=True)
class WarpOptions:
    """Settings of the MuJoCo Warp backend.

    Attributes:
        nconmax: Contacts per world, pooled over worlds (default: a bound no floor contact
            state exceeds, :func:`humimic.tracking.warp_backend.capacity`).
        njmax: Constraint rows per world (default: likewise a bound).
        cuda_graph: Replay each env step's physics as a captured CUDA graph.
    """

    nconmax: int | None = None
    njmax: int | None = None
    cuda_graph: bool = True


@dataclass(frozen=True, kw_only=True)
class TrackingConfig:
    """The motion-tracking task.

    Attributes:
        robot: Registry name of the robot.
        sim_dt: Physics step [s] (200 Hz).
        decimation: Physics steps per policy step (policy at 50 Hz).
        episode_length_s: Episode length [s]; the clip's end also ends an episode (time-out).
        anchor_body: The body whose pose anchors the reference (BeyondMimic: the torso).
        body_names: Tracked bodies (must include the anchor and the robot's root).
        ee_body_names: Bodies of the end-effector height termination.
        undesired_contact_bodies: Bodies that should not touch the floor.
        action_scale: PD target = default + ``action_scale * effort_limit / kp * action`` per
            joint (BeyondMimic's scaling).
        soft_limit_factor: Soft joint limits are this fraction of the range, centred.
        rewards: Reward terms.
        terminations: Termination terms.
        reward_dt_scale: Multiply rewards by the policy step (as mjlab/Isaac Lab do).
        dr: Domain randomization.
        physics: Fixed changes to the nominal model (a physics file: a "real" robot, or a
            model corrected by sysid); domain randomization acts on top of them.
        reset: Reference-state-initialization noise.
        adaptive: Adaptive start-frame sampling.
        history_length: Policy observations stacked in the ``proprio_history`` group.
        backend: The simulator: ``cpu`` (MuJoCo, :class:`~humimic.tracking.backend.MujocoCpuBackend`)
            or ``warp`` (MuJoCo Warp on the env's device, ``humimic[gpu]``:
            :class:`~humimic.tracking.warp_backend.MujocoWarpBackend`).
        warp: Settings of the ``warp`` backend.
        step_method: CPU stepping: ``rollout`` (``mujoco.rollout``) or ``threads``.
        num_threads: Simulation threads (default: all cores).
        torch_compile: Compile the env's tensor math (the relative reference, terminations,
            rewards and observation math) with ``torch.compile`` at construction. On the CPU
            it needs a C++ compiler and takes seconds (cached afterwards); it cuts the env's
            own cost per step by about half at a few dozen envs (BENCHMARKS.md).
        seed: Seed of the environment's random numbers.
        start_frame: Start every episode at this frame (evaluation); default: sampled.
    """

    robot: str = "g1"
    sim_dt: float = 0.005
    decimation: int = 4
    episode_length_s: float = 10.0
    anchor_body: str
    body_names: tuple[str, ...]
    ee_body_names: tuple[str, ...]
    undesired_contact_bodies: tuple[str, ...] = ()
    action_scale: float = 0.25
    soft_limit_factor: float = 0.9
    rewards: dict[str, TermConfig]
    terminations: dict[str, TermConfig]
    reward_dt_scale: bool = True
    dr: DomainRandomization = field(default_factory=dr_default)
    physics: Physics | None = None
    reset: ResetNoise = field(default_factory=ResetNoise)
    adaptive: AdaptiveSampling = field(default_factory=AdaptiveSampling)
    history_length: int = 5
    backend: Literal["cpu", "warp"] = "cpu"
    warp: WarpOptions = field(default_factory=WarpOptions)
    step_method: Literal["rollout", "threads"] = "rollout"
    num_threads: int | None = None
    torch_compile: bool = False
    seed: int = 0
    start_frame: int | None = None

    @property
    def step_dt(self) -> float:
        """Policy step [s]."""
        return self.sim_dt * self.decimation

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field."""
        for name in ("sim_dt", "episode_length_s", "action_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"tracking.{name}: must be a positive number, got {v}")
        if self.decimation < 1:
            raise InputError(f"tracking.decimation: must be at least 1, got {self.decimation}")
        if self.history_length < 1:
            raise InputError(
                f"tracking.history_length: must be at least 1, got {self.history_length}"
            )
        if not 0 < self.soft_limit_factor <= 1:
            raise InputError(
                f"tracking.soft_limit_factor: must be in (0, 1], got {self.soft_limit_factor}"
            )
        if self.backend not in ("cpu", "warp"):
            raise InputError(f"tracking.backend: expected 'cpu' or 'warp', got {self.backend!r}")
        if self.anchor_body not in self.body_names:
            raise InputError(f"tracking.anchor_body: {self.anchor_body!r} is not in body_names")
        missing = [b for b in self.ee_body_names if b not in self.body_names]
        if missing:
            raise InputError(f"tracking.ee_body_names: {missing} are not in body_names")
        self.dr.validate(where="tracking.dr")


def default_rewards() -> dict[str, TermConfig]:
    """BeyondMimic's reward terms with mjlab's stds and weights (see :mod:`.rewards`)."""
    return {
        "anchor_pos": TermConfig(func=rew.anchor_pos_error_exp, weight=0.5, params={"std": 0.3}),
        "anchor_ori": TermConfig(func=rew.anchor_ori_error_exp, weight=0.5, params={"std": 0.4}),
        "body_pos": TermConfig(func=rew.body_pos_error_exp, weight=1.0, params={"std": 0.3}),
        "body_ori": TermConfig(func=rew.body_ori_error_exp, weight=1.0, params={"std": 0.4}),
        "body_lin_vel": TermConfig(
            func=rew.body_lin_vel_error_exp, weight=1.0, params={"std": 1.0}
        ),
        "body_ang_vel": TermConfig(
            func=rew.body_ang_vel_error_exp, weight=1.0, params={"std": 3.14}
        ),
        "action_rate_l2": TermConfig(func=rew.action_rate_l2, weight=-0.1),
        "joint_limit": TermConfig(func=rew.joint_pos_limits, weight=-10.0),
        "undesired_contacts": TermConfig(func=rew.undesired_contacts, weight=-0.1),
    }


def default_terminations(ee_body_names: tuple[str, ...]) -> dict[str, TermConfig]:
    """mjlab's tracking terminations (see :mod:`.terminations`)."""
    return {
        "time_out": TermConfig(func=term.time_out, time_out=True),
        "anchor_height": TermConfig(func=term.anchor_height_error, params={"threshold": 0.25}),
        "anchor_ori": TermConfig(func=term.anchor_ori_error, params={"threshold": 0.8}),
        "ee_height": TermConfig(
            func=term.ee_height_error, params={"threshold": 0.25, "body_names": ee_body_names}
        ),
    }


G1_TRACKED_BODIES = (
    "pelvis",
    "left_hip_roll_link",
    "left_knee_link",
    "left_ankle_roll_link",
    "right_hip_roll_link",
    "right_knee_link",
    "right_ankle_roll_link",
    "torso_link",
    "left_shoulder_roll_link",
    "left_elbow_link",
    "left_wrist_yaw_link",
    "right_shoulder_roll_link",
    "right_elbow_link",
    "right_wrist_yaw_link",
)
"""mjlab's tracked G1 bodies."""

G1_EE_BODIES = (
    "left_ankle_roll_link",
    "right_ankle_roll_link",
    "left_wrist_yaw_link",
    "right_wrist_yaw_link",
)


def g1_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Unitree G1 whole-body tracking with mjlab's defaults.

    Args:
        dr: A profile name (``none``, ``default``) or a :class:`DomainRandomization`.
    """
    undesired = (
        "pelvis",
        *(f"{s}_{b}_link" for s in ("left", "right") for b in ("hip_pitch", "hip_roll", "hip_yaw")),
        *(f"{s}_{b}_link" for s in ("left", "right") for b in ("knee", "ankle_pitch")),
        "torso_link",
        *(
            f"{s}_{b}_link"
            for s in ("left", "right")
            for b in ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow")
        ),
        *(f"{s}_{b}_link" for s in ("left", "right") for b in ("wrist_roll", "wrist_pitch")),
    )
    return _task("g1", "torso_link", G1_TRACKED_BODIES, G1_EE_BODIES, undesired, dr)


def _task(
    robot: str,
    anchor: str,
    bodies: tuple[str, ...],
    ee: tuple[str, ...],
    undesired: tuple[str, ...],
    dr: str | DomainRandomization,
) -> TrackingConfig:
    """A tracking task with BeyondMimic's reward and termination terms."""
    return TrackingConfig(
        robot=robot,
        anchor_body=anchor,
        body_names=bodies,
        ee_body_names=ee,
        undesired_contact_bodies=undesired,
        rewards=default_rewards(),
        terminations=default_terminations(ee),
        dr=dr_profile(dr) if isinstance(dr, str) else dr,
    )


T1_TRACKED_BODIES = (
    "Trunk",
    "Waist",
    "Hip_Roll_Left",
    "Shank_Left",
    "left_foot_link",
    "Hip_Roll_Right",
    "Shank_Right",
    "right_foot_link",
    "AL1",
    "AL3",
    "left_hand_link",
    "AR1",
    "AR3",
    "right_hand_link",
)
T1_EE_BODIES = ("left_foot_link", "right_foot_link", "left_hand_link", "right_hand_link")


def t1_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Booster T1 whole-body tracking, with the G1 task's terms and weights (not tuned for the
    T1). The trunk is the anchor; every body but the feet is an undesired floor contact."""
    feet = ("left_foot_link", "right_foot_link")
    undesired = (
        *(b for b in T1_TRACKED_BODIES if b not in feet),
        *("H1", "H2", "AL2", "AR2", "Hip_Pitch_Left", "Hip_Pitch_Right"),
    )
    return _task("t1", "Trunk", T1_TRACKED_BODIES, T1_EE_BODIES, undesired, dr)


TRACKING_TASKS: dict[str, Callable[..., TrackingConfig]] = {"g1": g1_tracking, "t1": t1_tracking}
"""Registered tracking tasks: robot name -> task factory taking a DR profile."""


def tracking_task(robot: str, dr: str | DomainRandomization = "default") -> TrackingConfig:
    """The registered tracking task of a robot.

    Raises:
        UnknownNameError: If no task is registered for ``robot``.
    """
    if robot not in TRACKING_TASKS:
        raise UnknownNameError(
            f"no tracking task for robot {robot!r}; registered: {', '.join(sorted(TRACKING_TASKS))}"
        )
    return TRACKING_TASKS[robot](dr)
