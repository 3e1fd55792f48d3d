"""Configuration of the motion-tracking environment: frozen dataclasses and factory functions.

``g1_tracking()`` is the G1 task with mjlab's tracking defaults. Domain randomization comes in
named profiles (``none``, ``default``; :func:`dr_profile`) or from a YAML file
(:func:`~humimic.sim.randomization.load_dr_profile`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

from humimic.errors import InputError, UnknownNameError
from humimic.robots.registry import get_robot
from humimic.sim.lqr import LqrWeights
from humimic.sim.physics import Physics
from humimic.sim.randomization import (
    DomainRandomization,
    Range,
    dr_default,
    dr_profile,
)
from humimic.sim.setup import DEFAULT_SIM_DT, SimSetup, WarpOptions
from humimic.tracking import rewards as rew
from humimic.tracking import terminations as term
from humimic.tracking.actions import ACTION_BASES, ActionBase


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
        dr_replay: Share of resets that replay the domain-randomization draw of a recently
            failed episode (:class:`~humimic.sim.randomization.FailedDraws`) instead of a
            fresh one: training visits the physics the policy falls on more often. 0: none.
            Independent of ``enabled``; evaluation never replays.
        dr_replay_size: Failed draws kept for the replay.
    """

    enabled: bool = True
    bin_s: float = 1.0
    alpha: float = 0.001
    uniform_ratio: float = 0.1
    kernel_size: int = 3
    kernel_lambda: float = 0.8
    dr_replay: float = 0.0
    dr_replay_size: int = 256


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
        action_base: What the scaled action is added to (:mod:`.actions`): ``default`` (the
            default pose, BeyondMimic's), ``reference`` (the next frame's reference joint
            positions), ``feedforward`` (the PD targets stored by ``humimic refine``) or
            ``feedback`` (those plus time-varying LQR feedback around the refined trajectory).
        feedback: Costs of the ``feedback`` base's LQR.
        feedback_limit: The ``feedback`` base's correction is clipped to this [rad] per joint.
        feedback_delay: Policy steps of command latency the ``feedback`` base's LQR is
            designed for (:func:`humimic.sim.lqr.tvlqr_gains`' ``delay``): it issues the
            stored target of the step its command will act on and feeds back the commands it
            issued and that have not acted yet. 0: none.
        action_scale: PD target = base + ``action_scale * effort_limit / kp * action`` per
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
        backend: The simulator: ``cpu`` (MuJoCo, :class:`~humimic.sim.backend.MujocoCpuBackend`)
            or ``warp`` (MuJoCo Warp on the env's device, ``humimic[gpu]``:
            :class:`~humimic.sim.warp_backend.MujocoWarpBackend`).
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
    sim_dt: float = DEFAULT_SIM_DT
    decimation: int = 4
    episode_length_s: float = 10.0
    anchor_body: str
    body_names: tuple[str, ...]
    ee_body_names: tuple[str, ...]
    undesired_contact_bodies: tuple[str, ...] = ()
    action_base: ActionBase = "default"
    feedback: LqrWeights = field(default_factory=LqrWeights)
    feedback_limit: float = 0.5
    feedback_delay: int = 0
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

    def sim_setup(self) -> SimSetup:
        """What the task simulates: its bodies, contacts and physics on its backend."""
        return SimSetup(
            robot=self.robot,
            body_names=self.body_names,
            contact_body_names=self.undesired_contact_bodies,
            com_body=self.anchor_body,
            sim_dt=self.sim_dt,
            physics=self.physics,
            backend=self.backend,
            warp=self.warp,
            step_method=self.step_method,
            num_threads=self.num_threads,
        )

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the field."""
        for name in ("sim_dt", "episode_length_s", "action_scale", "feedback_limit"):
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
        if self.action_base not in ACTION_BASES:
            raise InputError(
                f"tracking.action_base: expected one of {', '.join(ACTION_BASES)}, got "
                f"{self.action_base!r}"
            )
        if not (isinstance(self.feedback_delay, int) and 0 <= self.feedback_delay <= 10):
            raise InputError(
                f"tracking.feedback_delay: expected 0-10 policy steps, got {self.feedback_delay!r}"
            )
        if self.feedback_delay and self.action_base != "feedback":
            raise InputError(
                "tracking.feedback_delay: only the 'feedback' action base has an LQR to "
                f"design for a delay (the action base is {self.action_base!r})"
            )
        if not (math.isfinite(self.adaptive.dr_replay) and 0 <= self.adaptive.dr_replay < 1):
            raise InputError(
                f"tracking.adaptive.dr_replay: expected a share in [0, 1), got "
                f"{self.adaptive.dr_replay}"
            )
        if self.adaptive.dr_replay_size < 1:
            raise InputError(
                f"tracking.adaptive.dr_replay_size: must be at least 1, got "
                f"{self.adaptive.dr_replay_size}"
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
    """BeyondMimic's reward terms with mjlab's stds and weights (see :mod:`.rewards`).

    Tracking terms are ``exp(-err / std**2)`` with the errors of BeyondMimic (Liao et al.,
    "BeyondMimic: From Motion Tracking to Versatile Humanoid Control via Guided Diffusion",
    2025); the default stds and weights are mjlab's (``mjlab/tasks/tracking/tracking_env_cfg.py``),
    except for ``undesired_contacts`` (see :func:`~humimic.tracking.rewards.undesired_contacts`)
    and the anchor position (mjlab: std 0.3, weight 0.5). At std 0.3 m a 100 mm drift of the
    torso still earns 89 % of the term and the other terms measure bodies relative to the
    anchor, so nothing held the robot to the clip's world position (the global MPJPE of a
    30-minute CPU run was 115-199 mm; BENCHMARKS.md, issue 25):

    ========================  ======  ======
    term                      std     weight
    ========================  ======  ======
    anchor position           0.15    1.0
    anchor orientation        0.4     0.5
    body positions (rel.)     0.3     1.0
    body orientations (rel.)  0.4     1.0
    body linear velocities    1.0     1.0
    body angular velocities   3.14    1.0
    action rate L2            --      -0.1
    joint limits              --      -10.0
    undesired contacts        --      -0.1
    ========================  ======  ======
    """
    return {
        "anchor_pos": TermConfig(func=rew.anchor_pos_error_exp, weight=1.0, params={"std": 0.15}),
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
    return _task("g1", G1_EE_BODIES, undesired, dr)


def _task(
    robot: str, ee: tuple[str, ...], undesired: tuple[str, ...], dr: str | DomainRandomization
) -> TrackingConfig:
    """A tracking task of the robot's key bodies, anchored at its torso, with BeyondMimic's
    reward and termination terms, and humimic's CPU recipe: actions are residuals around the
    refined motion's controls with LQR feedback (the ``feedback`` base, BENCHMARKS.md, issue
    25; ``action_base="default"`` is BeyondMimic's)."""
    r = get_robot(robot)
    return TrackingConfig(
        robot=robot,
        action_base="feedback",
        anchor_body=r.torso_body,
        body_names=r.key_bodies,
        ee_body_names=ee,
        undesired_contact_bodies=undesired,
        rewards=default_rewards(),
        terminations=default_terminations(ee),
        dr=dr_profile(dr) if isinstance(dr, str) else dr,
    )


T1_EE_BODIES = ("left_foot_link", "right_foot_link", "left_hand_link", "right_hand_link")


def t1_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Booster T1 whole-body tracking, with the G1 task's terms and weights (not tuned for the
    T1). The trunk is the anchor; every body but the feet is an undesired floor contact."""
    feet = ("left_foot_link", "right_foot_link")
    undesired = (
        *(b for b in get_robot("t1").key_bodies if b not in feet),
        *("H1", "H2", "AL2", "AR2", "Hip_Pitch_Left", "Hip_Pitch_Right"),
    )
    return _task("t1", T1_EE_BODIES, undesired, dr)


H1_EE_BODIES = ("left_ankle_link", "right_ankle_link", "left_elbow_link", "right_elbow_link")
"""The H1's feet and hands (no wrists: a hand is the end of its elbow link)."""


def h1_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Unitree H1 whole-body tracking, with the G1 task's terms and weights (not tuned for the
    H1). The torso is the anchor; every body but the feet is an undesired floor contact."""
    feet = ("left_ankle_link", "right_ankle_link")
    undesired = (
        *(b for b in get_robot("h1").key_bodies if b not in feet),
        *(f"{s}_{b}_link" for s in ("left", "right")
          for b in ("hip_yaw", "hip_pitch", "shoulder_pitch", "shoulder_yaw")),
    )  # fmt: skip
    return _task("h1", H1_EE_BODIES, undesired, dr)


def berkeley_humanoid_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Berkeley Humanoid (legs only) whole-body tracking, with the G1 task's terms and weights
    (not tuned for it). The torso is the anchor; the feet are the end effectors; every other
    body is an undesired floor contact."""
    feet = ("ll_faa", "lr_faa")
    undesired = (
        *(b for b in get_robot("berkeley_humanoid").key_bodies if b not in feet),
        *(f"{s}_{b}" for s in ("ll", "lr") for b in ("hr", "haa", "ffe")),
    )
    return _task("berkeley_humanoid", feet, undesired, dr)


APOLLO_EE_BODIES = ("l_foot_link", "r_foot_link", "l_wrist_pitch_link", "r_wrist_pitch_link")


def apollo_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Apptronik Apollo whole-body tracking, with the G1 task's terms and weights (not tuned
    for it). The torso is the anchor; every body with collision geometry but the feet is an
    undesired floor contact."""
    feet = ("l_foot_link", "r_foot_link")
    undesired = (
        *(b for b in get_robot("apollo").key_bodies if b not in feet),
        *(f"{s}_{b}_link" for s in "lr" for b in ("hip_fe", "shoulder_fe", "wrist_roll")),
    )
    return _task("apollo", APOLLO_EE_BODIES, undesired, dr)


OP3_EE_BODIES = ("l_ank_roll_link", "r_ank_roll_link", "l_el_link", "r_el_link")
"""The OP3's feet and hands (no wrists: a hand is the end of its forearm link)."""


def op3_tracking(dr: str | DomainRandomization = "default") -> TrackingConfig:
    """Robotis OP3 whole-body tracking, with the G1 task's terms and weights (not tuned for
    a 0.5 m robot). The torso is the anchor; every body with collision geometry but the feet
    is an undesired floor contact."""
    feet = ("l_ank_roll_link", "r_ank_roll_link")
    undesired = (
        *(b for b in get_robot("op3").key_bodies if b not in feet),
        "head_pan_link",
        *(f"{s}_{b}_link" for s in "lr"
          for b in ("hip_yaw", "hip_roll", "ank_pitch", "sho_pitch")),
    )  # fmt: skip
    return _task("op3", OP3_EE_BODIES, undesired, dr)


TRACKING_TASKS: dict[str, Callable[..., TrackingConfig]] = {
    "apollo": apollo_tracking,
    "berkeley_humanoid": berkeley_humanoid_tracking,
    "g1": g1_tracking,
    "h1": h1_tracking,
    "op3": op3_tracking,
    "t1": t1_tracking,
}
"""Registered tracking tasks: robot name -> task factory taking a DR profile."""


def added_robot_tracking(robot: str, dr: str | DomainRandomization = "default") -> TrackingConfig:
    """The tracking task of a robot the user added (``humimic robots add``): the G1 task's
    terms and weights, its key bodies tracked, its torso the anchor, its feet and hands (the
    last key body of each arm, where found) the end effectors, every other key body an
    undesired floor contact."""
    from humimic.robots.user import user_robot_hands

    r = get_robot(robot)
    feet = tuple(r.feet[s] for s in ("left", "right"))
    hands = user_robot_hands(robot)
    undesired = tuple(b for b in r.key_bodies if b not in feet)
    return _task(robot, (*feet, *hands), undesired, dr)


def tracking_task(robot: str, dr: str | DomainRandomization = "default") -> TrackingConfig:
    """The tracking task of a robot: its registered one, or :func:`added_robot_tracking` for
    a robot the user added.

    Raises:
        UnknownNameError: If ``robot`` is neither registered nor added.
    """
    if robot in TRACKING_TASKS:
        return TRACKING_TASKS[robot](dr)
    from humimic.robots.user import user_robot_folder

    if user_robot_folder(robot) is not None:
        return added_robot_tracking(robot, dr)
    raise UnknownNameError(
        f"no tracking task for robot {robot!r}; registered: {', '.join(sorted(TRACKING_TASKS))}"
    )
