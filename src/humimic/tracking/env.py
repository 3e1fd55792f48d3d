"""The whole-body motion-tracking environment (BeyondMimic on MuJoCo): :class:`TrackingEnv`,
an rsl_rl ``VecEnv``, and :func:`tracking_backend` / :func:`tracking_model`, the simulator it runs on.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import mujoco
import numpy as np
import torch
from tensordict import TensorDict

from humimic.errors import HumimicError, InputError
from humimic.motion import Motion
from humimic.robots.registry import get_robot
from humimic.sim import randomization as dr_mod
from humimic.sim.backend import PhysicsBackend, TensorBackend
from humimic.sim.setup import build_backend as sim_build_backend
from humimic.sim.setup import build_model
from humimic.tracking import observations as obs
from humimic.tracking.bases import BaseTargets
from humimic.tracking.command import MotionCommand, as_clips
from humimic.tracking.config import TrackingConfig
from humimic.tracking.events import Events
from humimic.tracking.rsl import VecEnv
from humimic.tracking.state import TrackingState


def tracking_backend(
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


def _check_motions(cfg: TrackingConfig, motion: Motion | Sequence[Motion]) -> None:
    """Raise :class:`InputError` naming a clip's file if it does not fit the task."""
    for clip in as_clips(motion):
        _check_motion(cfg, clip)


def _check_motion(cfg: TrackingConfig, motion: Motion) -> None:
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
        motion: The reference clip, or a library of clips (one policy for all: each episode
            follows one clip, started where clips fail most), at the policy rate
            (``1 / cfg.step_dt`` frames per second).
        num_envs: Number of parallel envs.
        device: Torch device of the observations, rewards and buffers.
        backend: The simulator; default: :func:`tracking_backend`.
        model: A prebuilt training model for the default backend.

    Raises:
        InputError: If the motion does not fit the robot or the policy rate.
    """

    cfg: TrackingConfig  # rsl_rl types it ``dict | object``.

    def __init__(
        self,
        cfg: TrackingConfig,
        motion: Motion | Sequence[Motion],
        num_envs: int,
        *,
        device: str | torch.device = "cpu",
        backend: PhysicsBackend | None = None,
        model: mujoco.MjModel | None = None,
    ) -> None:
        cfg.validate()
        _check_motions(cfg, motion)
        self.cfg = cfg  # pyright: ignore[reportIncompatibleVariableOverride]
        self.num_envs = num_envs
        self.device = torch.device(device)
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        self.step_dt = cfg.step_dt
        self.max_episode_length = math.ceil(cfg.episode_length_s / cfg.step_dt)
        self._attach_backend(
            backend or tracking_backend(cfg, num_envs, model=model, device=self.device)
        )
        be, dev, J = self.backend, self.device, self.num_actions
        robot = get_robot(cfg.robot)
        self.command = MotionCommand(cfg, motion, self.joint_names, robot.root_body, dev)
        self.num_frames = self.command.num_frames
        # Robot constants.
        self.default_joint_pos = self._tensor(be.default_joint_pos)
        self.action_scale = self._tensor(cfg.action_scale * be.effort_limit / be.kp)
        self.bases = BaseTargets(cfg, self.command, model, be, self.default_joint_pos, dev)
        rng_ = be.joint_range
        mid, half = rng_.mean(axis=1), 0.5 * (rng_[:, 1] - rng_[:, 0]) * cfg.soft_limit_factor
        self._bind_state(robot.root_body, self._tensor(np.stack([mid - half, mid + half], 1)))

        # Buffers (written in place: rsl_rl steps under torch.inference_mode()).
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=dev)
        self._gen = torch.Generator(device=dev).manual_seed(cfg.seed)
        self._lin_vel_gen = torch.Generator(device=dev).manual_seed(cfg.seed + 7919)
        self._rng = np.random.default_rng(cfg.seed)
        self.events = Events(cfg, be, self.command.start, (mid - half, mid + half), self._rng,
                             self._rand, dev)  # fmt: skip
        max_delay = int(cfg.dr.action_delay[1])
        self._cmd_hist = torch.zeros(num_envs, max_delay + 1, J, device=dev)
        self._delay = torch.zeros(num_envs, dtype=torch.long, device=dev)
        self._joint_offset = torch.zeros(num_envs, J, device=dev)
        self._params_dim = dr_mod.param_dim(be.num_bodies_total, J)
        self._params_e = torch.zeros(num_envs, self._params_dim, device=dev)
        self._rewards = torch.zeros(num_envs, device=dev)
        self._targets = self.default_joint_pos.repeat(num_envs, 1)
        self._terminated = torch.zeros(num_envs, dtype=torch.bool, device=dev)
        self._time_outs = torch.zeros(num_envs, dtype=torch.bool, device=dev)
        self._arange = torch.arange(num_envs, device=dev)
        self._gravity = torch.tensor([0.0, 0.0, -1.0], device=dev).expand(num_envs, 3)
        self._make_observation_buffers()
        self._make_term_rows()

        self._update_failure_stats()  # The initial sampling weights (no failures yet).
        self._reset_idx(self._arange)
        self._read_backend()
        self._update_reference()
        self._after_physics_fn, self._observe_fn = self._after_physics, self._observe
        if cfg.torch_compile:
            self._compile_math()
        self._compute_observations()

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32, device=self.device)

    def _attach_backend(self, be: PhysicsBackend) -> None:
        """Check the simulator and take its joints."""
        self.backend: PhysicsBackend = be
        # A backend on the env's device hands tensors over without a host round trip.
        self._tensor_backend: TensorBackend | None = None
        if isinstance(be, TensorBackend) and be.device == self.device:
            self._tensor_backend = be
        self._tensor_io = self._tensor_backend is not None
        if be.num_envs != self.num_envs:
            raise InputError(f"the backend has {be.num_envs} envs, the env {self.num_envs}")
        self.joint_names = be.joint_names
        self.num_actions = J = len(self.joint_names)
        if be.nq != 7 + J or be.nv != 6 + J:
            raise InputError(
                f"the robot must be a free-floating base plus its {J} actuated joints "
                f"(nq = {be.nq}, nv = {be.nv})"
            )

    def _bind_state(self, root_body: str, soft: torch.Tensor) -> None:
        """The state, its fields views of two buffers: the reference's (one gather of the
        packed table fills it, :meth:`_update_reference`) and the simulator's (one float64 ->
        float32 copy per read)."""
        cfg, be, n, dev, J = self.cfg, self.backend, self.num_envs, self.device, self.num_actions
        self.state = st = TrackingState.zeros(
            num_envs=n,
            body_names=cfg.body_names,
            anchor_body=cfg.anchor_body,
            root_body=root_body,
            num_joints=J,
            num_contact_bodies=len(be.contact_body_names),
            num_feet=len(be.foot_body_names),
            num_frames=self.num_frames,
            device=dev,
        )
        st.default_joint_pos.copy_(self.default_joint_pos)
        st.soft_joint_limits.copy_(soft)
        Bs = len(cfg.body_names)
        self._ref_buf = torch.zeros(n, self.command.packed.shape[1], device=dev)
        jp, jv, bp, bq, bl, ba = self._ref_buf.split(self.command.split, dim=1)
        st.ref_joint_pos, st.ref_joint_vel = jp, jv
        st.ref_body_pos_w, st.ref_body_quat_w = bp.view(-1, Bs, 3), bq.view(-1, Bs, 4)
        st.ref_body_lin_vel_w, st.ref_body_ang_vel_w = bl.view(-1, Bs, 3), ba.view(-1, Bs, 3)
        st.ref_body_quat_w[..., 0] = 1.0
        nb, C, F = len(be.body_names), len(be.contact_body_names), len(be.foot_body_names)
        self._read_split = [J, J, 3 * nb, 4 * nb, 3 * nb, 3 * nb, C, F]
        self._read_np = np.zeros((n, sum(self._read_split)))
        self._read_np_t = torch.from_numpy(self._read_np)  # A view: the copy is a tensor op.
        self._read_buf = torch.zeros(n, sum(self._read_split), device=dev)
        jp, jv, bp, bq, bl, ba, cf, ff = self._read_buf.split(self._read_split, dim=1)
        st.joint_pos, st.joint_vel, st.contact_found, st.foot_force = jp, jv, cf, ff
        st.body_pos_w, st.body_quat_w = bp.view(-1, nb, 3), bq.view(-1, nb, 4)
        st.body_lin_vel_w, st.body_ang_vel_w = bl.view(-1, nb, 3), ba.view(-1, nb, 3)

    def _make_observation_buffers(self) -> None:
        """The groups' buffers, their sizes from the terms (:mod:`.observations`)."""
        n, dev = self.num_envs, self.device
        dims = obs.ObsDims(
            joints=self.num_actions,
            bodies=len(self.cfg.body_names),
            feet=len(self.backend.foot_body_names),
            params=self._params_dim,
        )
        self._policy_dim = obs.group_size(obs.POLICY_TERMS, dims)
        self._critic_dim = self._policy_dim + obs.group_size(obs.CRITIC_EXTRA_TERMS, dims)
        self._lin_vel_at = self._policy_dim + obs.offset(
            obs.CRITIC_EXTRA_TERMS, "base_lin_vel", dims
        )
        self._policy = torch.zeros(n, self._policy_dim, device=dev)
        self._critic = torch.zeros(n, self._critic_dim, device=dev)
        self._base_lin_vel = torch.zeros(n, 3, device=dev)
        self._history = torch.zeros(n, self.cfg.history_length, self._policy_dim, device=dev)
        self._fresh = torch.ones(n, dtype=torch.bool, device=dev)
        scale = obs.noise_scale(obs.POLICY_TERMS, self.cfg.dr.obs_noise, dims)
        self._noise_scale = None if scale is None else scale.to(dev)

    def _make_term_rows(self) -> None:
        """One buffer row per reward and per termination term, and the logged names."""
        cfg, n, dev = self.cfg, self.num_envs, self.device
        scale = self.step_dt if cfg.reward_dt_scale else 1.0
        self._rew_weights = torch.tensor(
            [tc.weight * scale for tc in cfg.rewards.values()], device=dev
        ).unsqueeze(1)
        self._rew_buf = torch.zeros(len(cfg.rewards), n, device=dev)
        self._term_buf = torch.zeros(len(cfg.terminations), n, dtype=torch.bool, device=dev)
        is_timeout = [tc.time_out for tc in cfg.terminations.values()]
        self._timeout_rows = torch.tensor(
            [k for k, t in enumerate(is_timeout) if t], dtype=torch.long, device=dev
        )
        self._terminal_rows = torch.tensor(
            [k for k, t in enumerate(is_timeout) if not t], dtype=torch.long, device=dev
        )
        self._log_keys = [f"term_{k}" for k in cfg.terminations] + [f"rew_{k}" for k in cfg.rewards]
        self._log_keys.append("sampling_entropy")

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
        self._cmd_hist[:, 0] = self.bases.at(s.frame) + self.action_scale * a
        self.bases.queue_command(self._cmd_hist[:, 0], s.frame)
        targets = self._cmd_hist[self._arange, self._delay] + self._joint_offset
        self._targets = targets
        if self._tensor_backend is not None:
            self._tensor_backend.set_ctrl_tensor(targets)
        else:
            self.backend.set_ctrl(targets.detach().cpu().double().numpy())
        self.backend.step(cfg.decimation)

        ep = self.episode_length_buf  # rsl_rl may have replaced it: read it fresh.
        ep += 1
        torch.minimum(s.frame + 1, s.last_frame, out=s.frame)  # A clip's last frame holds.
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
                None
                if self.events.replay is None
                else (self._terminated & ~self._time_outs)[done_ids]
            )
            self._reset_idx(done_ids, failed)
        pushed = self.events.push(self.step_dt)
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
        return self.command.joint_pos

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
        return self.command.weights

    def action_for_targets(self, targets: torch.Tensor) -> torch.Tensor:
        """The action whose PD targets are ``targets`` at every env's current frame (before
        DR's joint offsets and delay): ``(targets - base) / scale``. Shape: (num_envs, J)."""
        return (targets - self.bases.at(self.state.frame)) / self.action_scale

    def base_targets(self, base: str) -> torch.Tensor:
        """The PD targets of the action base ``base`` (:mod:`.actions`) at every env's current
        frame for a zero action: the env's own base or another one of the same motion (a
        student that acts around a different base than its teacher learns the teacher's
        actions moved by the difference, :mod:`.distill`). Shape: (num_envs, J).

        Raises:
            InputError: A base the motion cannot give (:func:`.actions.base_table`). Another
                env's ``feedback`` base is designed for no command latency.
        """
        return self.bases.other(base, self.state.frame)

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
        return torch.cat([logged, self.command.sampling_entropy().view(1)])

    def _update_reference(self) -> None:
        """The reference at each env's frame: one gather into the buffer the state's
        reference fields view (the relative reference is :meth:`_compute_terms`'s)."""
        self.command.gather(self.state.frame, self._ref_buf)

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
        written = (self.command.bin_failed, self.command.weights, self._fresh, self._history)
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

    def _update_failure_stats(self) -> None:
        """Fold this step's failures (terminations that are not time-outs) into the failure
        rate of each bin and recompute the sampling weights (no host sync: a scatter, not a
        test for failures)."""
        failed = (self._terminated & ~self._time_outs).float()
        self.command.fold_failures(self.state.frame, failed)

    def _reset_idx(self, ids: torch.Tensor, failed: torch.Tensor | None = None) -> None:
        """Reset some envs in the backend and in the env's buffers. The caller reads the
        backend's new state (:meth:`_read_backend`, :meth:`_update_reference`) afterwards.

        Args:
            failed: Which of ``ids`` ended by failing (their draws are kept for the replay,
                :attr:`~humimic.tracking.config.AdaptiveSampling.dr_replay`). Shape: (len(ids),), bool.
        """
        s, n, dev = self.state, int(ids.numel()), self.device
        frames = self.command.sample_frames(n, self._gen)
        s.frame[ids] = frames
        s.last_frame[ids] = self.command.last[frames]
        ids_np = ids.cpu().numpy()
        smp, e = self.events.draw_physics(ids_np, failed)
        self._joint_offset[ids] = torch.as_tensor(smp.joint_offset, dtype=torch.float32, device=dev)
        self._delay[ids] = torch.as_tensor(smp.action_delay, dtype=torch.long, device=dev)
        self._params_e[ids] = torch.as_tensor(e, dtype=torch.float32, device=dev)
        # Reference state initialization with noise, in float64 for the backend: a few envs
        # per step, where numpy's small-array calls cost a fraction of torch's.
        qpos, qvel = self.events.reset_state(frames.cpu().numpy())
        self.backend.reset_to(ids_np, qpos, qvel)
        s.action[ids] = 0.0
        s.last_action[ids] = 0.0
        # Before the first command, the drives hold the start frame's base.
        self._cmd_hist[ids] = self.bases.start_commands(ids, frames, self._cmd_hist.shape[1])
        self.episode_length_buf[ids] = 0
        self._fresh[ids] = True
        self.events.restart_push_timers(ids)

    def _observation_math(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The noise-free ``policy`` and ``critic`` observations (pure tensor math)."""
        return obs.observe(obs.ObsFrames(self.state, self._params_e, self._gravity))

    def _compute_observations(self) -> None:
        with torch.inference_mode():
            noise = None
            if self._noise_scale is not None:
                noise = torch.rand(self._policy.shape, generator=self._gen, device=self.device)
            self._observe_fn(noise)
            # The base's linear velocity (a student's group): the critic's, noised from its
            # own generator (the other draws stay as they were before the group existed).
            start = self._lin_vel_at
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


__all__ = ["TrackingEnv", "tracking_backend", "tracking_model"]
