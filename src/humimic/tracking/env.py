"""The whole-body motion-tracking environment (BeyondMimic on MuJoCo): :class:`TrackingEnv`,
an rsl_rl ``VecEnv``, and :func:`build_backend` / :func:`tracking_model`, the simulator it runs on.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace

import mujoco
import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from humimic import transforms as tf
from humimic.errors import HumimicError, InputError
from humimic.motion import Motion
from humimic.robots.registry import get_robot
from humimic.sim import randomization as dr_mod
from humimic.sim.backend import PhysicsBackend, TensorBackend
from humimic.sim.setup import build_backend as sim_build_backend
from humimic.sim.setup import build_model
from humimic.tracking.actions import STORED_BASES, base_table, stored_states
from humimic.tracking.config import TrackingConfig
from humimic.tracking.math import (
    quat_apply_inverse,
    quat_conj_mul,
    quat_log,
    rot6d_from_quat,
    subtract_frame_transforms,
)
from humimic.tracking.state import TrackingState


def build_backend(
    cfg: TrackingConfig,
    num_envs: int,
    *,
    model: mujoco.MjModel | None = None,
    menagerie_root: str | os.PathLike[str] | None = None,
    device: str | torch.device = "cpu",
) -> PhysicsBackend:
    """The backend a :class:`TrackingEnv` of ``cfg`` needs: ``cfg.backend`` on ``device``, with
    per-env models where domain randomization changes the model.

    Args:
        cfg: The task.
        num_envs: Number of envs.
        model: A model from :func:`tracking_model` (building one takes seconds; reuse it).
        menagerie_root: Where the robot files are.
        device: The env's torch device; the ``warp`` backend simulates on it.
    """
    return sim_build_backend(
        cfg.sim_setup(), num_envs, model=model, per_env_models=cfg.dr.randomizes_model,
        menagerie_root=menagerie_root, device=device,
    )  # fmt: skip


def tracking_model(
    cfg: TrackingConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> mujoco.MjModel:
    """The training model of ``cfg`` (mesh-free, with the read-out sensors), with the changes
    of ``cfg.physics`` when it has a physics file."""
    return build_model(cfg.sim_setup(), menagerie_root=menagerie_root)


class TrackingEnv(VecEnv):
    """Whole-body motion tracking, implementing rsl_rl's ``VecEnv``.

    A policy at 50 Hz sets PD position targets ``base + offset + scale * action`` of every
    joint (the base: the default pose, the reference or stored feedforward, :mod:`.actions`) of a floating-base humanoid simulated at 200 Hz, and is rewarded for following a
    reference motion (Liao et al., "BeyondMimic: From Motion Tracking to Versatile Humanoid
    Control via Guided Diffusion", 2025). Episodes start at a reference frame (reference state
    initialization, with noise) chosen by BeyondMimic's adaptive sampling, and end on a
    tracking failure (see :mod:`.terminations`), at the episode length, or at the end of the
    clip (time-outs).

    Observation groups (all float32, Shape: (num_envs, D)):

    * ``policy`` (deployable, noisy when the DR profile says so): reference joint positions and
      velocities of the current frame, the reference anchor pose in the robot anchor frame
      (position, 6D rotation), projected gravity and angular velocity of the base (base
      frame), joint positions (relative to the default) and velocities, the last action.
    * ``critic``: the policy content without noise, the normalized physics parameters ``e``
      (:func:`humimic.sim.randomization.normalize`), the base linear velocity (base frame),
      the tracked bodies' positions and 6D orientations in the robot anchor frame, and the
      feet's floor contact forces.
    * ``proprio_history``: the last ``history_length`` policy observations, oldest first.
    * ``physics``: the normalized physics parameters ``e`` alone (what a privileged teacher's
      actor adds to ``policy``).
    * ``base_lin_vel``: the base's linear velocity (base frame), noisy as ``policy`` is: what a
      robot's state estimator gives, and what the ``mlp-velocity`` student reads beside
      ``policy`` and ``proprio_history``.

    All reward, termination and observation math is torch on batched tensors (the state lives
    in :class:`~humimic.tracking.state.TrackingState`); the simulator is reached only through a
    :class:`~humimic.sim.backend.PhysicsBackend`.

    Args:
        cfg: The task.
        motion: The reference clip, at the policy rate (``1 / cfg.step_dt`` frames per second).
        num_envs: Number of parallel envs.
        device: Torch device of the observations, rewards and buffers.
        backend: The simulator; default: :func:`build_backend`.
        model: A prebuilt training model for the default backend.

    Raises:
        InputError: If the motion does not fit the robot or the policy rate.
    """

    cfg: TrackingConfig  # rsl_rl types it ``dict | object``.

    def __init__(
        self,
        cfg: TrackingConfig,
        motion: Motion,
        num_envs: int,
        *,
        device: str | torch.device = "cpu",
        backend: PhysicsBackend | None = None,
        model: mujoco.MjModel | None = None,
    ) -> None:
        cfg.validate()
        self.cfg = cfg
        self.num_envs = num_envs
        self.device = torch.device(device)
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        self.step_dt = cfg.step_dt
        self.max_episode_length = math.ceil(cfg.episode_length_s / cfg.step_dt)
        where = f"{motion.source or 'the motion'}: "
        if motion.robot != cfg.robot:
            raise InputError(
                f"{where}the motion is for robot {motion.robot!r}, the task for {cfg.robot!r}"
            )
        if abs(motion.fps * cfg.step_dt - 1.0) > 1e-6:
            raise InputError(
                f"{where}the motion has {motion.fps} frames per second; the policy runs at "
                f"{1.0 / cfg.step_dt:g} Hz: resample the motion to that rate"
            )
        if motion.num_frames < 2:
            raise InputError(f"{where}the motion needs at least 2 frames")
        self.backend: PhysicsBackend = backend or build_backend(
            cfg, num_envs, model=model, device=self.device
        )
        be = self.backend
        # A backend on the env's device hands tensors over without a host round trip.
        self._tensor_backend: TensorBackend | None = None
        if isinstance(be, TensorBackend) and be.device == self.device:
            self._tensor_backend = be
        self._tensor_io = self._tensor_backend is not None
        if be.num_envs != num_envs:
            raise InputError(f"the backend has {be.num_envs} envs, the env {num_envs}")
        self.joint_names = be.joint_names
        self.num_actions = len(self.joint_names)
        J = self.num_actions
        if be.nq != 7 + J or be.nv != 6 + J:
            raise InputError(
                f"the robot must be a free-floating base plus its {J} actuated joints "
                f"(nq = {be.nq}, nv = {be.nv})"
            )
        robot = get_robot(cfg.robot)

        # Reference motion tensors, reordered to the backend's joints and tracked bodies.
        try:
            jidx = [motion.joint_names.index(j) for j in self.joint_names]
            bidx = [motion.body_names.index(b) for b in cfg.body_names]
            root_m = motion.body_names.index(robot.root_body)
        except ValueError as e:
            raise InputError(f"the motion lacks a joint or body of the task: {e}") from None
        dev = self.device

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32, device=dev)

        self._m_joint_pos = t(motion.joint_pos[:, jidx])
        self._m_joint_vel = t(motion.joint_vel[:, jidx])
        self._m_body_pos = t(motion.body_pos_w[:, bidx])
        self._m_body_quat = t(motion.body_quat_w[:, bidx])
        self._m_body_lin_vel = t(motion.body_lin_vel_w[:, bidx])
        self._m_body_ang_vel = t(motion.body_ang_vel_w[:, bidx])
        # One packed table of what every step reads: one gather per step instead of six.
        T, Bt = motion.num_frames, len(bidx)
        self._m_packed = torch.cat(
            [self._m_joint_pos, self._m_joint_vel, self._m_body_pos.reshape(T, -1),
             self._m_body_quat.reshape(T, -1), self._m_body_lin_vel.reshape(T, -1),
             self._m_body_ang_vel.reshape(T, -1)], dim=1,
        )  # fmt: skip
        self._m_split = [len(jidx), len(jidx), 3 * Bt, 4 * Bt, 3 * Bt, 3 * Bt]
        self.num_frames = motion.num_frames
        # What actions are added to (None: the default pose), indexed by the step's frame.
        table = base_table(cfg.action_base, motion, jidx, cfg.sim_dt, cfg.decimation)
        self._base = None if table is None else t(table)
        self._ref_np = self._reset_reference(motion, jidx, root_m)
        self._gains: torch.Tensor | None = None
        if cfg.action_base == "feedback":
            assert self._base is not None  # base_table gave the stored targets.
            self._gains, self._fb_qpos, self._fb_qvel = self._feedback_setup(
                motion, model, self._base, cfg.feedback_delay
            )
            self._fb_queue = torch.zeros(
                num_envs, cfg.feedback_delay, self._gains.shape[1], device=dev
            )
        # Other bases of the same motion, built when first asked for (base_targets).
        self._base_source = (motion, jidx, model)
        self._other_bases: dict[str, tuple[torch.Tensor, tuple[torch.Tensor, ...] | None]] = {}

        # Robot constants.
        self.default_joint_pos = t(be.default_joint_pos)
        self.action_scale = t(cfg.action_scale * be.effort_limit / be.kp)
        rng_ = be.joint_range
        mid, half = rng_.mean(axis=1), 0.5 * (rng_[:, 1] - rng_[:, 0]) * cfg.soft_limit_factor
        soft = t(np.stack([mid - half, mid + half], axis=1))
        self._soft_lo, self._soft_hi = mid - half, mid + half
        rn = cfg.reset
        ranges = np.array([*rn.pose, *rn.velocity] + [rn.joint_pos] * J, dtype=np.float64)
        self._reset_lo, self._reset_hi = ranges[:, 0], ranges[:, 1]
        push = np.array([*cfg.dr.push_lin_vel, *cfg.dr.push_ang_vel], dtype=np.float64)
        self._push_lo, self._push_hi = push[:, 0], push[:, 1]

        self.state = TrackingState.zeros(
            num_envs=num_envs,
            body_names=cfg.body_names,
            anchor_body=cfg.anchor_body,
            root_body=robot.root_body,
            num_joints=J,
            num_contact_bodies=len(be.contact_body_names),
            num_feet=len(be.foot_body_names),
            num_frames=self.num_frames,
            device=dev,
        )
        self.state.default_joint_pos.copy_(self.default_joint_pos)
        self.state.soft_joint_limits.copy_(soft)
        # The reference fields are views of one buffer that a single gather of the packed
        # table fills (see _update_reference).
        st, Bs = self.state, len(cfg.body_names)
        self._ref_buf = torch.zeros(num_envs, self._m_packed.shape[1], device=dev)
        jp, jv, bp, bq, bl, ba = self._ref_buf.split(self._m_split, dim=1)
        st.ref_joint_pos, st.ref_joint_vel = jp, jv
        st.ref_body_pos_w, st.ref_body_quat_w = bp.view(-1, Bs, 3), bq.view(-1, Bs, 4)
        st.ref_body_lin_vel_w, st.ref_body_ang_vel_w = bl.view(-1, Bs, 3), ba.view(-1, Bs, 3)
        st.ref_body_quat_w[..., 0] = 1.0
        # Likewise the simulator's state: one float64 -> float32 copy per read.
        nb, C, F = len(be.body_names), len(be.contact_body_names), len(be.foot_body_names)
        self._read_split = [J, J, 3 * nb, 4 * nb, 3 * nb, 3 * nb, C, F]
        self._read_np = np.zeros((num_envs, sum(self._read_split)))
        self._read_np_t = torch.from_numpy(self._read_np)  # A view: the copy is a tensor op.
        self._read_buf = torch.zeros(num_envs, sum(self._read_split), device=dev)
        jp, jv, bp, bq, bl, ba, cf, ff = self._read_buf.split(self._read_split, dim=1)
        st.joint_pos, st.joint_vel, st.contact_found, st.foot_force = jp, jv, cf, ff
        st.body_pos_w, st.body_quat_w = bp.view(-1, nb, 3), bq.view(-1, nb, 4)
        st.body_lin_vel_w, st.body_ang_vel_w = bl.view(-1, nb, 3), ba.view(-1, nb, 3)

        # Buffers (written in place: rsl_rl steps under torch.inference_mode()).
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=dev)
        self._gen = torch.Generator(device=dev).manual_seed(cfg.seed)
        self._lin_vel_gen = torch.Generator(device=dev).manual_seed(cfg.seed + 7919)
        self._rng = np.random.default_rng(cfg.seed)
        self._dr_pool = dr_mod.SamplePool(
            cfg.dr,
            num_bodies=be.num_bodies_total,
            num_joints=J,
            rng=self._rng,
            com_column=be.layout.com_column,
        )
        self._reset_noise = dr_mod.Blocks(self._draw_reset_noise)
        # Replay of failed episodes' draws: each env's current draw, kept to be recorded.
        self._replay: dr_mod.FailedDraws | None = None
        self._env_rows: list[np.ndarray] = []
        if cfg.adaptive.dr_replay > 0:
            self._replay = dr_mod.FailedDraws(
                cfg.adaptive.dr_replay,
                cfg.adaptive.dr_replay_size,
                np.random.default_rng([cfg.seed, 0x5EED]),
            )
        max_delay = int(cfg.dr.action_delay[1])
        self._cmd_hist = torch.zeros(num_envs, max_delay + 1, J, device=dev)
        self._delay = torch.zeros(num_envs, dtype=torch.long, device=dev)
        self._joint_offset = torch.zeros(num_envs, J, device=dev)
        self._params_dim = dr_mod.param_dim(be.num_bodies_total, J)
        self._params_e = torch.zeros(num_envs, self._params_dim, device=dev)
        self._push_timer = torch.full((num_envs,), math.inf, device=dev)
        self._rewards = torch.zeros(num_envs, device=dev)
        self._targets = self.default_joint_pos.repeat(num_envs, 1)
        self._terminated = torch.zeros(num_envs, dtype=torch.bool, device=dev)
        self._time_outs = torch.zeros(num_envs, dtype=torch.bool, device=dev)
        self._arange = torch.arange(num_envs, device=dev)
        self._gravity = torch.tensor([0.0, 0.0, -1.0], device=dev).expand(num_envs, 3)

        # Adaptive sampling (BeyondMimic): failure rates per bin of the clip.
        ad = cfg.adaptive
        self._bin_count = int(self.num_frames // max(ad.bin_s / cfg.step_dt, 1.0)) + 1
        self._bin_failed = torch.zeros(self._bin_count, device=dev)
        kernel = torch.tensor([ad.kernel_lambda**i for i in range(ad.kernel_size)], device=dev)
        self._kernel = (kernel / kernel.sum()).view(1, 1, -1)
        self._weights = torch.zeros(self._bin_count, device=dev)

        # Observation buffers.
        B, F = len(cfg.body_names), len(be.foot_body_names)
        self._policy_dim = 2 * J + 3 + 6 + 3 + 3 + 3 * J
        self._critic_dim = self._policy_dim + self._params_dim + 3 + 9 * B + F
        self._policy = torch.zeros(num_envs, self._policy_dim, device=dev)
        self._critic = torch.zeros(num_envs, self._critic_dim, device=dev)
        self._base_lin_vel = torch.zeros(num_envs, 3, device=dev)
        self._history = torch.zeros(num_envs, cfg.history_length, self._policy_dim, device=dev)
        self._fresh = torch.ones(num_envs, dtype=torch.bool, device=dev)
        self._noise_scale = self._make_noise_scale()
        scale = self.step_dt if cfg.reward_dt_scale else 1.0
        self._rew_weights = torch.tensor(
            [tc.weight * scale for tc in cfg.rewards.values()], device=dev
        ).unsqueeze(1)
        self._rew_buf = torch.zeros(len(cfg.rewards), num_envs, device=dev)
        self._term_buf = torch.zeros(len(cfg.terminations), num_envs, dtype=torch.bool, device=dev)
        is_timeout = [tc.time_out for tc in cfg.terminations.values()]
        self._timeout_rows = torch.tensor(
            [k for k, t in enumerate(is_timeout) if t], dtype=torch.long, device=dev
        )
        self._terminal_rows = torch.tensor(
            [k for k, t in enumerate(is_timeout) if not t], dtype=torch.long, device=dev
        )
        self._log_keys = [f"term_{k}" for k in cfg.terminations] + [f"rew_{k}" for k in cfg.rewards]
        self._log_keys.append("sampling_entropy")

        self._update_failure_stats()  # The initial sampling weights (no failures yet).
        self._reset_idx(self._arange)
        self._read_backend()
        self._update_reference()
        self._after_physics_fn, self._observe_fn = self._after_physics, self._observe
        if cfg.torch_compile:
            self._compile_math()
        self._compute_observations()

    # ------------------------------------------------------------------------------- API

    def get_observations(self) -> TensorDict:
        """Current observations: groups ``policy``, ``critic``, ``proprio_history``, ``physics``,
        ``base_lin_vel``."""
        return TensorDict(
            {
                "policy": self._policy.clone(),
                "critic": self._critic.clone(),
                "proprio_history": self._history.reshape(self.num_envs, -1).clone(),
                "physics": self._params_e.clone(),
                "base_lin_vel": self._base_lin_vel.clone(),
            },
            batch_size=[self.num_envs],
            device=self.device,
        )

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Apply actions for one policy step; done envs are reset before returning.

        Args:
            actions: Shape: (num_envs, num_actions).

        Returns:
            Observations, rewards Shape: (num_envs,), dones Shape: (num_envs,) bool, and extras
            with ``time_outs`` (a subset of the dones) and ``log`` (scalar tensors).
        """
        s, cfg = self.state, self.cfg
        a = actions.detach().to(self.device, torch.float32)
        s.last_action.copy_(s.action)
        s.action.copy_(a)
        # DR's action delay holds back the whole command, the base included (a latency
        # between the controller and the drives).
        if self._cmd_hist.shape[1] > 1:
            self._cmd_hist[:, 1:] = self._cmd_hist[:, :-1].clone()
        self._cmd_hist[:, 0] = self._action_base() + self.action_scale * a
        self._queue_command(self._cmd_hist[:, 0])
        targets = self._cmd_hist[self._arange, self._delay] + self._joint_offset
        self._targets = targets
        if self._tensor_backend is not None:
            self._tensor_backend.set_ctrl_tensor(targets)
        else:
            self.backend.set_ctrl(targets.detach().cpu().double().numpy())
        self.backend.step(cfg.decimation)

        ep = self.episode_length_buf  # rsl_rl may have replaced it: read it fresh.
        ep += 1
        s.frame.add_(1).clamp_(max=self.num_frames - 1)
        self._gather_backend()
        # Terminations, rewards and failure statistics, before any reset.
        with torch.inference_mode():  # The env's math never needs autograd (see _compile_math).
            logged = self._after_physics_fn()
        log = dict(zip(self._log_keys, logged.unbind(), strict=True))
        dones = self._terminated | self._time_outs

        done_ids = dones.nonzero(as_tuple=False).flatten()
        reset = done_ids.numel() > 0
        if reset:
            failed = (
                None if self._replay is None else (self._terminated & ~self._time_outs)[done_ids]
            )
            self._reset_idx(done_ids, failed)
        pushed = self._apply_pushes()
        if reset or pushed:  # One read of the new states for resets and pushes together.
            self._read_backend()
        if reset:
            self._update_reference()  # For the observations (rewards: next step's).
        self._compute_observations()
        extras = {"time_outs": self._time_outs.clone(), "log": log}
        return self.get_observations(), self._rewards.clone(), dones, extras

    @property
    def reference_joint_pos(self) -> torch.Tensor:
        """The reference's joint positions, in the env's joint order. Shape: (frames, J)."""
        return self._m_joint_pos

    @property
    def joint_targets(self) -> torch.Tensor:
        """The PD position targets sent to the backend at the last step (after the action
        delay and joint offsets of DR). Shape: (num_envs, J)."""
        return self._targets

    @property
    def physics_params(self) -> torch.Tensor:
        """The normalized physics parameters ``e`` of every env. Shape: (num_envs, D)."""
        return self._params_e

    @property
    def sampling_weights(self) -> torch.Tensor:
        """Start-bin sampling probabilities of the adaptive sampler. Shape: (bins,)."""
        return self._weights

    def _compute_weights(self) -> torch.Tensor:
        ad = self.cfg.adaptive
        n = self._bin_count
        if not ad.enabled:
            return torch.full((n,), 1.0 / n, device=self.device)
        p = self._bin_failed + ad.uniform_ratio / n
        padded = torch.cat([p, p[-1:].expand(ad.kernel_size - 1)])
        out = torch.nn.functional.conv1d(padded.view(1, 1, -1), self._kernel).view(n)
        return out / out.sum()

    def action_for_targets(self, targets: torch.Tensor) -> torch.Tensor:
        """The action whose PD targets are ``targets`` at every env's current frame (before
        DR's joint offsets and delay): ``(targets - base) / scale``. Shape: (num_envs, J)."""
        return (targets - self._action_base()) / self.action_scale

    def base_targets(self, base: str) -> torch.Tensor:
        """The PD targets of the action base ``base`` (:mod:`.actions`) at every env's current
        frame for a zero action: the env's own base or another one of the same motion (a
        student that acts around a different base than its teacher learns the teacher's
        actions moved by the difference, :mod:`.distill`). Shape: (num_envs, J).

        Raises:
            InputError: A base the motion cannot give (:func:`.actions.base_table`). Another
                env's ``feedback`` base is designed for no command latency.
        """
        if base == self.cfg.action_base:
            return self._action_base()
        if base == "default":
            return self.default_joint_pos.expand(self.num_envs, -1)
        if base not in self._other_bases:
            motion, jidx, model = self._base_source
            cfg = self.cfg
            table = torch.as_tensor(
                base_table(base, motion, jidx, cfg.sim_dt, cfg.decimation),
                dtype=torch.float32, device=self.device,
            )  # fmt: skip
            fb = self._feedback_setup(motion, model, table, 0) if base == "feedback" else None
            self._other_bases[base] = (table, fb)
        table, fb = self._other_bases[base]
        f = self.state.frame
        if fb is None:
            return table[f]
        return table[f] + self._feedback(f, *fb)

    def _action_base(self) -> torch.Tensor:
        """The action base (:mod:`.actions`) at every env's current frame."""
        if self._base is None:
            return self.default_joint_pos.expand(self.num_envs, -1)
        f = self.state.frame
        if self._gains is None:
            return self._base[f]
        d = self.cfg.feedback_delay
        ff = self._base[(f + d).clamp(max=self._base.shape[0] - 1)]
        # The commands in flight, oldest first (tvlqr_gains' delayed state).
        queue = self._fb_queue.reshape(self.num_envs, -1) if d else None
        return ff + self._feedback(f, self._gains, self._fb_qpos, self._fb_qvel, queue)

    def _feedback(
        self,
        f: torch.Tensor,
        gains: torch.Tensor,
        ref_qpos: torch.Tensor,
        ref_qvel: torch.Tensor,
        queue: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The LQR correction ``K_f (x - x_f)`` at frames ``f``, clipped to the task's
        ``feedback_limit``; ``queue``: the commands in flight of a delay design."""
        dx = self._state_deviation(ref_qpos[f], ref_qvel[f])
        if queue is not None:
            dx = torch.cat([dx, queue], dim=1)
        fb = torch.einsum("nij,nj->ni", gains[f], dx)
        lim = self.cfg.feedback_limit
        return fb.clamp(-lim, lim)

    def _state_deviation(self, ref_q: torch.Tensor, ref_v: torch.Tensor) -> torch.Tensor:
        """The simulated state minus ``(ref_q, ref_v)`` (Shape: (num_envs, nq), (num_envs,
        nv)) in the tangent space, as ``mj_differentiatePos(ref, x)`` and the velocities: root
        position, root rotation vector in the body frame, joints, then the velocities (the
        state of :func:`humimic.sim.lqr.tvlqr_gains`). Shape: (num_envs, 2 nv)."""
        r = self.backend.read()
        qpos = torch.as_tensor(r.qpos, dtype=torch.float32, device=self.device)
        qvel = torch.as_tensor(r.qvel, dtype=torch.float32, device=self.device)
        return torch.cat([qpos[:, :3] - ref_q[:, :3],
                          quat_log(quat_conj_mul(ref_q[:, 3:7], qpos[:, 3:7])),
                          qpos[:, 7:] - ref_q[:, 7:], qvel - ref_v], dim=1)  # fmt: skip

    def _queue_command(self, command: torch.Tensor) -> None:
        """Remember a command the delay-aware LQR issued, as its deviation from the stored
        target of the step it will act on."""
        d = self.cfg.feedback_delay
        if self._gains is None or not d:
            return
        f = (self.state.frame + d).clamp(max=self._base.shape[0] - 1)  # type: ignore[union-attr]
        self._fb_queue[:, :-1] = self._fb_queue[:, 1:].clone()
        self._fb_queue[:, -1] = command - self._base[f]  # type: ignore[index]

    def _feedback_setup(
        self, motion: Motion, model: mujoco.MjModel | None, table: torch.Tensor, delay: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The ``feedback`` base's time-varying LQR gains around the refined trajectory (with
        ``table`` its stored targets, designed for ``delay`` steps of latency), on the robot's
        nominal model (the one ``humimic refine`` plans on): neither DR nor a physics file
        changes the controller, so a policy meets an unseen robot with the base it trained
        with. Returns the gains (Shape: (T, J, n)) and the trajectory's qpos and qvel."""
        from humimic.sim.lqr import tvlqr_gains

        states = stored_states(motion, self.cfg.decimation)
        assert states is not None  # base_table checked it.
        qpos, qvel = states
        nominal = self.cfg.physics is None
        m = (
            model
            if model is not None and nominal
            else tracking_model(replace(self.cfg, physics=None))
        )
        K = tvlqr_gains(m, qpos, qvel, table[:-1].double().cpu().numpy(),
                        self.cfg.decimation, self.cfg.feedback, delay=delay)  # fmt: skip
        K = np.concatenate([K, np.zeros_like(K[-1:])])  # The last frame: no control step.
        dev = self.device
        return (
            torch.as_tensor(K, dtype=torch.float32, device=dev),
            torch.as_tensor(qpos, dtype=torch.float32, device=dev),
            torch.as_tensor(qvel, dtype=torch.float32, device=dev),
        )

    def close(self) -> None:
        """Release the backend's threads."""
        close = getattr(self.backend, "close", None)
        if close is not None:
            close()

    # -------------------------------------------------------------------------- internals

    def _gather_backend(self) -> None:
        """The backend's state into one float64 array (one numpy concatenation), which
        :meth:`_after_physics` copies into the buffer the state's fields view; a tensor
        backend writes that buffer itself."""
        if self._tensor_backend is not None:
            self._tensor_backend.read_into(self._read_buf)
            return
        r, n = self.backend.read(), self.num_envs
        parts = (
            r.qpos[:, 7:], r.qvel[:, 6:], r.body_pos_w, r.body_quat_w, r.body_lin_vel_w,
            r.body_ang_vel_w, r.contact_found, r.foot_force,
        )  # fmt: skip
        np.concatenate([p.reshape(n, -1) for p in parts], axis=1, out=self._read_np)

    def _read_backend(self) -> None:
        """The backend's state into the state's fields (one float32 conversion)."""
        self._gather_backend()
        if not self._tensor_io:
            self._read_buf.copy_(self._read_np_t)

    def _after_physics(self) -> torch.Tensor:
        """The step's tensor math after the physics (after :meth:`_gather_backend`): the
        state and the reference, terminations, rewards, failure statistics. Returns the
        logged values (``_log_keys``)."""
        if not self._tensor_io:
            self._read_buf.copy_(self._read_np_t)
        self._update_reference()
        logged = self._compute_terms()
        self._update_failure_stats()
        return torch.cat([logged, self._sampling_entropy().view(1)])

    def _update_reference(self) -> None:
        """The reference at each env's frame: one gather into the buffer the state's
        reference fields view (the relative reference is :meth:`_compute_terms`'s)."""
        torch.index_select(self._m_packed, 0, self.state.frame, out=self._ref_buf)

    def _compute_terms(self) -> torch.Tensor:
        """The relative reference, then every termination and reward term into the rows of
        one buffer each, so that sums and logged means are one operation each whatever the
        number of terms. Returns the logged means (terminations, then rewards)."""
        self.state.update_relative()
        cfg, terms, values = self.cfg, self._term_buf, self._rew_buf
        for k, tc in enumerate(cfg.terminations.values()):
            terms[k] = tc.func(self, **tc.params)
        for k, tc in enumerate(cfg.rewards.values()):
            values[k] = tc.func(self, **tc.params)
        values *= self._rew_weights
        torch.any(terms.index_select(0, self._timeout_rows), dim=0, out=self._time_outs)
        torch.any(terms.index_select(0, self._terminal_rows), dim=0, out=self._terminated)
        torch.sum(values, dim=0, out=self._rewards)
        return torch.cat([terms.mean(dim=1, dtype=torch.float32), values.mean(dim=1)])

    def _compile_math(self) -> None:
        """Compile :meth:`_after_physics` and :meth:`_observe` (whole graphs, fixed shapes)
        and run them once, so that a failure shows here and the first step does not stall.
        An eager run first fills the caches they read (tracked-body indices, rotation forms);
        the buffers the runs write are restored afterwards. They always run under
        ``torch.inference_mode`` (as rsl_rl collects rollouts), which keeps one compiled graph
        each: a change of grad mode would compile them again."""
        written = (self._bin_failed, self._weights, self._fresh, self._history)
        kept = [t.clone() for t in written]
        with torch.inference_mode():
            noise = None if self._noise_scale is None else torch.zeros_like(self._policy)
            self._after_physics()
            self._observe(noise)
        try:
            after = torch.compile(self._after_physics, dynamic=False, fullgraph=True)
            observe = torch.compile(self._observe, dynamic=False, fullgraph=True)
            with torch.inference_mode():
                after()
                observe(noise)
        except Exception as e:  # Any compiler failure, reported with its cause.
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise HumimicError(
                f"torch.compile of the tracking env's math failed ({first}); on the CPU it "
                "needs a working C++ compiler. Run without compiling (torch_compile=False, "
                "no --compile)."
            ) from e
        for buf, old in zip(written, kept, strict=True):
            buf.copy_(old)
        self._after_physics_fn, self._observe_fn = after, observe

    def _rand(
        self, lo: torch.Tensor | float, hi: torch.Tensor | float, shape: tuple[int, ...]
    ) -> torch.Tensor:
        u = torch.rand(shape, generator=self._gen, device=self.device)
        return lo + (hi - lo) * u

    def _sample_frames(self, n: int) -> torch.Tensor:
        T = self.num_frames
        if self.cfg.start_frame is not None:
            return torch.full((n,), min(self.cfg.start_frame, T - 2), device=self.device)
        if self.cfg.adaptive.enabled:
            bins = torch.multinomial(
                self.sampling_weights, n, replacement=True, generator=self._gen
            )
            u = torch.rand(n, generator=self._gen, device=self.device)
            frames = ((bins.float() + u) / self._bin_count * (T - 1)).long()
        else:
            frames = torch.randint(0, T - 1, (n,), generator=self._gen, device=self.device)
        return frames.clamp(0, T - 2)

    def _update_failure_stats(self) -> None:
        """Fold this step's failures (terminations that are not time-outs) into the failure
        rate of each bin and recompute the sampling weights (no host sync: a scatter, not a
        test for failures)."""
        failed = (self._terminated & ~self._time_outs).float()
        bins = torch.div(self.state.frame * self._bin_count, self.num_frames, rounding_mode="floor")
        now = torch.zeros_like(self._bin_failed).scatter_add_(
            0, bins.clamp(0, self._bin_count - 1), failed
        )
        a = self.cfg.adaptive.alpha
        self._bin_failed.mul_(1.0 - a).add_(a * now)
        self._weights.copy_(self._compute_weights())

    def _sampling_entropy(self) -> torch.Tensor:
        p = self._weights
        h = -(p * (p + 1e-12).log()).sum()
        return h / math.log(self._bin_count) if self._bin_count > 1 else h * 0 + 1

    def _reset_idx(self, ids: torch.Tensor, failed: torch.Tensor | None = None) -> None:
        """Reset some envs in the backend and in the env's buffers. The caller reads the
        backend's new state (:meth:`_read_backend`, :meth:`_update_reference`) afterwards.

        Args:
            failed: Which of ``ids`` ended by failing (their draws are kept for the replay,
                :attr:`~humimic.tracking.config.AdaptiveSampling.dr_replay`). Shape: (len(ids),), bool.
        """
        cfg, s, n = self.cfg, self.state, int(ids.numel())
        frames = self._sample_frames(n)
        s.frame[ids] = frames

        # Domain randomization.
        ids_np = ids.cpu().numpy()
        rows = self._dr_pool.take_rows(n)
        if self._replay is not None:
            if not self._env_rows:  # The first reset (every env): the arrays to keep.
                self._env_rows = [np.zeros((self.num_envs, *a.shape[1:]), a.dtype) for a in rows]
            elif failed is not None:
                lost = ids_np[failed.cpu().numpy()]
                self._replay.record(tuple(a[lost] for a in self._env_rows))
            rows = self._replay.mix(rows)
            for kept, a in zip(self._env_rows, rows, strict=True):
                kept[ids_np] = a
        smp, e = self._dr_pool.as_sample(rows)
        if cfg.dr.randomizes_model:
            self.backend.set_params(ids_np, smp.physics)
        dev = self.device
        self._joint_offset[ids] = torch.as_tensor(smp.joint_offset, dtype=torch.float32, device=dev)
        self._delay[ids] = torch.as_tensor(smp.action_delay, dtype=torch.long, device=dev)
        self._params_e[ids] = torch.as_tensor(e, dtype=torch.float32, device=dev)

        # Reference state initialization with noise, in float64 for the backend: a few envs
        # per step, where numpy's small-array calls cost a fraction of torch's.
        qpos, qvel = self._reset_state(frames.cpu().numpy())
        self.backend.reset_to(ids_np, qpos, qvel)

        s.action[ids] = 0.0
        s.last_action[ids] = 0.0
        # Before the first command, the drives hold the start frame's base.
        start = self.default_joint_pos.expand(n, -1) if self._base is None else self._base[frames]
        self._cmd_hist[ids] = start.unsqueeze(1).expand(-1, self._cmd_hist.shape[1], -1)
        d = self.cfg.feedback_delay
        if self._gains is not None and d:
            # The episode starts on the plan: the commands in flight are the stored targets
            # a controller designed for d steps of latency issued (the one issued i + 1
            # steps ago acts d - i - 1 steps from now).
            self._fb_queue[ids] = 0.0
            age = torch.arange(self._cmd_hist.shape[1], device=self.device)
            f = (frames.to(self.device)[:, None] + d - 1 - age).clamp(0, self._base.shape[0] - 1)  # type: ignore[union-attr]
            self._cmd_hist[ids] = self._base[f]  # type: ignore[index]
        self.episode_length_buf[ids] = 0
        self._fresh[ids] = True
        if cfg.dr.push_interval_s is not None:
            lo, hi = cfg.dr.push_interval_s
            self._push_timer[ids] = self._rand(lo, hi, (n,))

    def _reset_reference(
        self, motion: Motion, jidx: list[int], root_m: int
    ) -> dict[str, np.ndarray]:
        """The reference states episodes start from (float64): the motion's frames and their
        finite-difference velocities, or, with the ``feedforward`` base, the simulated states
        the stored controls continue from (:func:`~humimic.tracking.actions.stored_states`)."""
        if self.cfg.action_base in STORED_BASES:
            states = stored_states(motion, self.cfg.decimation)
            assert states is not None  # base_table has checked the dynamic section.
            qpos, qvel = states
            quat = qpos[:, 3:7] / np.linalg.norm(qpos[:, 3:7], axis=-1, keepdims=True)
            rot = tf.quat_to_matrix(quat)
            return {
                "root_pos": qpos[:, :3].copy(),
                "root_quat": quat,
                "root_rot": rot,
                "root_lin_vel": qvel[:, :3].copy(),
                "root_ang_vel": np.einsum("nij,nj->ni", rot, qvel[:, 3:6]),
                "joint_pos": np.ascontiguousarray(qpos[:, 7:]),
                "joint_vel": np.ascontiguousarray(qvel[:, 6:]),
            }
        root_quat = motion.qpos[:, 3:7].astype(np.float64)
        root_quat /= np.linalg.norm(root_quat, axis=-1, keepdims=True)
        return {
            "root_pos": motion.qpos[:, :3].astype(np.float64),
            "root_quat": root_quat,
            "root_rot": tf.quat_to_matrix(root_quat),
            "root_lin_vel": motion.body_lin_vel_w[:, root_m].astype(np.float64),
            "root_ang_vel": motion.body_ang_vel_w[:, root_m].astype(np.float64),
            "joint_pos": np.ascontiguousarray(motion.joint_pos[:, jidx], dtype=np.float64),
            "joint_vel": np.ascontiguousarray(motion.joint_vel[:, jidx], dtype=np.float64),
        }

    def _draw_reset_noise(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` draws of the reset noise: the uniform offsets (root pose, root velocity,
        joints; Shape: (n, 12 + J)), and the root orientation noise as a rotation matrix
        (Shape: (n, 3, 3)) and as the matrix of left quaternion multiplication (Shape:
        (n, 4, 4))."""
        u = self._rng.uniform(self._reset_lo, self._reset_hi, size=(n, len(self._reset_lo)))
        q = tf.quat_from_euler_xyz(u[:, 3:6])
        left = np.stack([tf.quat_mul(q, e) for e in np.eye(4)], axis=-1)
        return u, tf.quat_to_matrix(q), left

    def _reset_state(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference's states at ``frames`` with the reset noise of the config (drawn in
        blocks: a reset step resets a few envs, where numpy's per-call cost dominates).

        Returns:
            qpos Shape: (n, nq), qvel Shape: (n, nv), float64.
        """
        r, n = self._ref_np, len(frames)
        u, noise_rot, noise_left = self._reset_noise.take(n)
        root_quat = np.einsum("nij,nj->ni", noise_left, r["root_quat"][frames])
        root_rot = noise_rot @ r["root_rot"][frames]
        jp = np.clip(r["joint_pos"][frames] + u[:, 12:], self._soft_lo, self._soft_hi)
        qpos = np.concatenate([r["root_pos"][frames] + u[:, :3], root_quat, jp], axis=-1)
        ang_vel_b = np.einsum("nji,nj->ni", root_rot, r["root_ang_vel"][frames] + u[:, 9:12])
        lin_vel_w = r["root_lin_vel"][frames] + u[:, 6:9]
        return qpos, np.concatenate([lin_vel_w, ang_vel_b, r["joint_vel"][frames]], axis=-1)

    def _apply_pushes(self) -> bool:
        """Push the envs whose timer ran out; returns whether any was pushed (the caller then
        reads the backend)."""
        dr = self.cfg.dr
        if dr.push_interval_s is None:
            return False
        self._push_timer -= self.step_dt
        ids = (self._push_timer <= 0).nonzero(as_tuple=False).flatten()
        if ids.numel() == 0:
            return False
        n = int(ids.numel())
        lo, hi = dr.push_interval_s
        self._push_timer[ids] = self._rand(lo, hi, (n,))
        dqvel = np.zeros((n, self.backend.nv))
        dqvel[:, :6] = self._rng.uniform(self._push_lo, self._push_hi, size=(n, 6))
        self.backend.push(ids.cpu().numpy(), dqvel)
        return True

    def _make_noise_scale(self) -> torch.Tensor | None:
        noise = self.cfg.dr.obs_noise
        if noise is None:
            return None
        J = self.num_actions
        parts = [
            torch.zeros(2 * J),
            torch.full((3,), noise.anchor_pos),
            torch.full((6,), noise.anchor_ori),
            torch.full((3,), noise.projected_gravity),
            torch.full((3,), noise.base_ang_vel),
            torch.full((J,), noise.joint_pos),
            torch.full((J,), noise.joint_vel),
            torch.zeros(J),
        ]
        return torch.cat(parts).to(self.device)

    def _observation_math(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The noise-free ``policy`` and ``critic`` observations (pure tensor math)."""
        s = self.state
        root_quat = s.root_quat_w
        anchor_pos_b, anchor_quat_b = subtract_frame_transforms(
            s.anchor_pos_w, s.anchor_quat_w, s.ref_anchor_pos_w, s.ref_anchor_quat_w
        )
        # Gravity, angular and linear velocity in the root frame: one rotation of three vectors.
        root_vecs = torch.stack(
            [self._gravity, s.body_ang_vel_w[:, s.root_index], s.body_lin_vel_w[:, s.root_index]],
            dim=1,
        )
        gravity_b, root_ang_vel_b, root_lin_vel_b = quat_apply_inverse(
            root_quat[:, None], root_vecs
        ).unbind(1)
        policy = torch.cat(
            [
                s.ref_joint_pos,
                s.ref_joint_vel,
                anchor_pos_b,
                rot6d_from_quat(anchor_quat_b),
                gravity_b,
                root_ang_vel_b,
                s.joint_pos - s.default_joint_pos,
                s.joint_vel,
                s.action,
            ],
            dim=-1,
        )
        B = len(s.body_names)
        body_pos_b, body_quat_b = subtract_frame_transforms(
            s.anchor_pos_w[:, None], s.anchor_quat_w[:, None], s.body_pos_w, s.body_quat_w
        )
        critic = torch.cat(
            [
                policy,
                self._params_e,
                root_lin_vel_b,
                body_pos_b.reshape(-1, 3 * B),
                rot6d_from_quat(body_quat_b).reshape(-1, 6 * B),
                s.foot_force,
            ],
            dim=-1,
        )
        return policy, critic

    def _compute_observations(self) -> None:
        with torch.inference_mode():
            noise = None
            if self._noise_scale is not None:
                noise = torch.rand(self._policy.shape, generator=self._gen, device=self.device)
            self._observe_fn(noise)
            # The base's linear velocity (a student's group): the critic's, noised from its
            # own generator (the other draws stay as they were before the group existed).
            start = self._policy_dim + self._params_dim
            lin_vel = self._critic[:, start : start + 3]
            obs_noise = self.cfg.dr.obs_noise
            if obs_noise is not None and obs_noise.base_lin_vel > 0:
                u = torch.rand(lin_vel.shape, generator=self._lin_vel_gen, device=self.device)
                lin_vel = lin_vel + (2.0 * u - 1.0) * obs_noise.base_lin_vel
            self._base_lin_vel.copy_(lin_vel)

    def _observe(self, noise: torch.Tensor | None) -> None:
        """Observations into their buffers: ``noise`` (uniform in [0, 1), or None) scaled to
        the DR's observation noise, the history shifted, the history of fresh envs filled
        with their first observation."""
        policy, critic = self._observation_math()
        self._critic.copy_(critic)
        if noise is not None and self._noise_scale is not None:
            policy = policy + (2.0 * noise - 1.0) * self._noise_scale
        self._policy.copy_(policy)
        h = self._history
        if h.shape[1] > 1:
            h[:, :-1] = h[:, 1:].clone()
        h[:, -1] = policy
        h.copy_(torch.where(self._fresh[:, None, None], policy[:, None], h))
        self._fresh.zero_()


__all__ = ["TrackingEnv", "build_backend", "tracking_model"]
