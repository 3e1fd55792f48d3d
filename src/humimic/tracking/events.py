"""The events of the tracking task: what a reset draws (domain randomization and its replay of
failed draws, the noisy reference state an episode starts from) and the pushes.

:class:`Events` owns the random streams of these draws; the env decides when they happen
(:meth:`humimic.tracking.env.TrackingEnv.step`) and writes what they return into its buffers.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from humimic import transforms as tf
from humimic.sim import randomization as dr_mod
from humimic.sim.backend import PhysicsBackend
from humimic.tracking.config import TrackingConfig


class Events:
    """Resets and pushes of ``num_envs`` envs.

    Args:
        cfg: The task (its reset ranges, DR, adaptive DR replay, seed).
        backend: The simulator (pushed here; reset by the env).
        start: The reference states episodes start from
            (:attr:`~humimic.tracking.command.MotionCommand.start`).
        soft_limits: The joints' soft limits, low and high. Shape: (J,) each.
        rng: The env's numpy stream (DR draws, reset noise, push velocities).
        rand: Uniform draws on the env's torch stream, ``rand(lo, hi, shape)`` (push timers).
        device: Torch device of the push timers.
    """

    def __init__(
        self,
        cfg: TrackingConfig,
        backend: PhysicsBackend,
        start: dict[str, np.ndarray],
        soft_limits: tuple[np.ndarray, np.ndarray],
        rng: np.random.Generator,
        rand: Callable[[float, float, tuple[int, ...]], torch.Tensor],
        device: torch.device,
    ) -> None:
        self.cfg, self.backend, self.start = cfg, backend, start
        self.soft_lo, self.soft_hi = soft_limits
        self.rng, self.rand = rng, rand
        J = len(self.soft_lo)
        rn = cfg.reset
        ranges = np.array([*rn.pose, *rn.velocity] + [rn.joint_pos] * J, dtype=np.float64)
        self.reset_lo, self.reset_hi = ranges[:, 0], ranges[:, 1]
        push = np.array([*cfg.dr.push_lin_vel, *cfg.dr.push_ang_vel], dtype=np.float64)
        self.push_lo, self.push_hi = push[:, 0], push[:, 1]
        self.pool = dr_mod.SamplePool(
            cfg.dr,
            num_bodies=backend.num_bodies_total,
            num_joints=J,
            rng=rng,
            com_column=backend.layout.com_column,
        )
        self.reset_noise = dr_mod.Blocks(self.draw_reset_noise)
        # Replay of failed episodes' draws: each env's current draw, kept to be recorded.
        self.replay: dr_mod.FailedDraws | None = None
        self._env_rows: list[np.ndarray] = []
        if cfg.adaptive.dr_replay > 0:
            self.replay = dr_mod.FailedDraws(
                cfg.adaptive.dr_replay,
                cfg.adaptive.dr_replay_size,
                np.random.default_rng([cfg.seed, 0x5EED]),
            )
        self.push_timer = torch.full((backend.num_envs,), torch.inf, device=device)

    def draw_physics(
        self, ids_np: np.ndarray, failed: torch.Tensor | None
    ) -> tuple[dr_mod.DrSample, np.ndarray]:
        """The DR draw of the envs ``ids_np`` (mixed with replayed draws of failed episodes),
        set on the backend where DR changes the model; ``failed``: which of them ended by
        failing (their draws are recorded for the replay). Returns the draw and its
        normalized parameters ``e``."""
        rows = self.pool.take_rows(len(ids_np))
        if self.replay is not None:
            if not self._env_rows:  # The first reset (every env): the arrays to keep.
                n = self.backend.num_envs
                self._env_rows = [np.zeros((n, *a.shape[1:]), a.dtype) for a in rows]
            elif failed is not None:
                lost = ids_np[failed.cpu().numpy()]
                self.replay.record(tuple(a[lost] for a in self._env_rows))
            rows = self.replay.mix(rows)
            for kept, a in zip(self._env_rows, rows, strict=True):
                kept[ids_np] = a
        smp, e = self.pool.as_sample(rows)
        if self.cfg.dr.randomizes_model:
            self.backend.set_params(ids_np, smp.physics)
        return smp, e

    def draw_reset_noise(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` draws of the reset noise: the uniform offsets (root pose, root velocity,
        joints; Shape: (n, 12 + J)), and the root orientation noise as a rotation matrix
        (Shape: (n, 3, 3)) and as the matrix of left quaternion multiplication (Shape:
        (n, 4, 4))."""
        u = self.rng.uniform(self.reset_lo, self.reset_hi, size=(n, len(self.reset_lo)))
        q = tf.quat_from_euler_xyz(u[:, 3:6])
        left = np.stack([tf.quat_mul(q, e) for e in np.eye(4)], axis=-1)
        return u, tf.quat_to_matrix(q), left

    def reset_state(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference's states at ``frames`` with the reset noise of the config (drawn in
        blocks: a reset step resets a few envs, where numpy's per-call cost dominates).

        Returns:
            qpos Shape: (n, nq), qvel Shape: (n, nv), float64.
        """
        r, n = self.start, len(frames)
        u, noise_rot, noise_left = self.reset_noise.take(n)
        root_quat = np.einsum("nij,nj->ni", noise_left, r["root_quat"][frames])
        root_rot = noise_rot @ r["root_rot"][frames]
        jp = np.clip(r["joint_pos"][frames] + u[:, 12:], self.soft_lo, self.soft_hi)
        qpos = np.concatenate([r["root_pos"][frames] + u[:, :3], root_quat, jp], axis=-1)
        ang_vel_b = np.einsum("nji,nj->ni", root_rot, r["root_ang_vel"][frames] + u[:, 9:12])
        lin_vel_w = r["root_lin_vel"][frames] + u[:, 6:9]
        return qpos, np.concatenate([lin_vel_w, ang_vel_b, r["joint_vel"][frames]], axis=-1)

    def restart_push_timers(self, ids: torch.Tensor) -> None:
        """Draw the time to the next push of the envs ``ids`` (after a reset)."""
        if self.cfg.dr.push_interval_s is not None:
            lo, hi = self.cfg.dr.push_interval_s
            self.push_timer[ids] = self.rand(lo, hi, (int(ids.numel()),))

    def push(self, step_dt: float) -> bool:
        """Count down the push timers by a step and push the envs whose timer ran out;
        returns whether any was pushed (the caller then reads the backend)."""
        dr = self.cfg.dr
        if dr.push_interval_s is None:
            return False
        self.push_timer -= step_dt
        ids = (self.push_timer <= 0).nonzero(as_tuple=False).flatten()
        if ids.numel() == 0:
            return False
        n = int(ids.numel())
        lo, hi = dr.push_interval_s
        self.push_timer[ids] = self.rand(lo, hi, (n,))
        dqvel = np.zeros((n, self.backend.nv))
        dqvel[:, :6] = self.rng.uniform(self.push_lo, self.push_hi, size=(n, 6))
        self.backend.push(ids.cpu().numpy(), dqvel)
        return True


__all__ = ["Events"]
