"""The action base of a tracking env at every step: the table of :mod:`.actions` indexed by
each env's frame, and, for the ``feedback`` base, its LQR correction from the simulated state.
A library's tables hold its clips one after the other (as :class:`.command.MotionCommand`'s).
"""

from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np
import torch

from humimic.sim.backend import PhysicsBackend
from humimic.sim.setup import build_model
from humimic.tracking.actions import base_table, stored_states
from humimic.tracking.command import MotionCommand
from humimic.tracking.config import TrackingConfig
from humimic.tracking.math import quat_conj_mul, quat_log

Feedback = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""A ``feedback`` base's LQR gains (Shape: (T, J, n)) and the trajectory's qpos and qvel."""


class BaseTargets:
    """The action base of a tracking env at every env's current frame: its own
    (``cfg.action_base``) and, when asked, another base of the same motion.

    Args:
        cfg: The task.
        command: The reference clips (their joints, and each frame's clip).
        model: A prebuilt nominal training model (the ``feedback`` base's design), or None.
        backend: The simulator (the ``feedback`` base reads its state).
        default_joint_pos: The default pose. Shape: (J,).
        device: Torch device.
    """

    def __init__(
        self,
        cfg: TrackingConfig,
        command: MotionCommand,
        model: mujoco.MjModel | None,
        backend: PhysicsBackend,
        default_joint_pos: torch.Tensor,
        device: torch.device,
    ) -> None:
        self.cfg, self.backend, self.device = cfg, backend, device
        self.num_envs = backend.num_envs
        self.default_joint_pos = default_joint_pos
        self.command, self._model = command, model
        table = self._table(cfg.action_base)
        self.table = None if table is None else self._tensor(table)
        """What actions are added to, indexed by the step's frame (None: the default pose)."""
        self.feedback: Feedback | None = None
        if cfg.action_base == "feedback":
            assert self.table is not None  # base_table gave the stored targets.
            self.feedback = self._feedback_setup(self.table, cfg.feedback_delay)
            J = self.feedback[0].shape[1]
            self.queue = torch.zeros(self.num_envs, cfg.feedback_delay, J, device=device)
        # Other bases of the same motion, built when first asked for (other).
        self.others: dict[str, tuple[torch.Tensor, Feedback | None]] = {}

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=self.device)

    def _table(self, base: str) -> np.ndarray | None:
        """The base of every frame of every clip (:func:`base_table`), or None (the default
        pose)."""
        cfg, c = self.cfg, self.command
        tables = [base_table(base, m, c.joint_index, cfg.sim_dt, cfg.decimation) for m in c.clips]
        if tables[0] is None:
            return None
        return tables[0] if len(tables) == 1 else np.concatenate(tables)  # type: ignore[arg-type]

    def _ahead(self, frame: torch.Tensor, d: int) -> torch.Tensor:
        """``d`` frames after ``frame``, held at its clip's last frame."""
        return torch.minimum(frame + d, self.command.last[frame])

    def at(self, frame: torch.Tensor) -> torch.Tensor:
        """The env's own base at ``frame``. Shape: (num_envs, J)."""
        if self.table is None:
            return self.default_joint_pos.expand(self.num_envs, -1)
        if self.feedback is None:
            return self.table[frame]
        d = self.cfg.feedback_delay
        ff = self.table[self._ahead(frame, d)]
        # The commands in flight, oldest first (tvlqr_gains' delayed state).
        queue = self.queue.reshape(self.num_envs, -1) if d else None
        return ff + self.correction(frame, *self.feedback, queue)

    def other(self, base: str, frame: torch.Tensor) -> torch.Tensor:
        """The base ``base`` at ``frame`` (another env's ``feedback`` base is designed for no
        command latency). Shape: (num_envs, J).

        Raises:
            InputError: A base the motion cannot give (:func:`base_table`).
        """
        if base == self.cfg.action_base:
            return self.at(frame)
        if base == "default":
            return self.default_joint_pos.expand(self.num_envs, -1)
        if base not in self.others:
            table = self._tensor(self._table(base))  # type: ignore[arg-type]
            fb = self._feedback_setup(table, 0) if base == "feedback" else None
            self.others[base] = (table, fb)
        table, fb = self.others[base]
        return table[frame] if fb is None else table[frame] + self.correction(frame, *fb)

    def correction(
        self,
        f: torch.Tensor,
        gains: torch.Tensor,
        ref_qpos: torch.Tensor,
        ref_qvel: torch.Tensor,
        queue: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The LQR correction ``K_f (x - x_f)`` at frames ``f``, clipped to the task's
        ``feedback_limit``; ``queue``: the commands in flight of a delay design."""
        dx = self.state_deviation(ref_qpos[f], ref_qvel[f])
        if queue is not None:
            dx = torch.cat([dx, queue], dim=1)
        fb = torch.einsum("nij,nj->ni", gains[f], dx)
        lim = self.cfg.feedback_limit
        return fb.clamp(-lim, lim)

    def state_deviation(self, ref_q: torch.Tensor, ref_v: torch.Tensor) -> torch.Tensor:
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

    def queue_command(self, command: torch.Tensor, frame: torch.Tensor) -> None:
        """Remember a command the delay-aware LQR issued, as its deviation from the stored
        target of the step it will act on."""
        d = self.cfg.feedback_delay
        if self.feedback is None or not d:
            return
        assert self.table is not None
        f = self._ahead(frame, d)
        self.queue[:, :-1] = self.queue[:, 1:].clone()
        self.queue[:, -1] = command - self.table[f]

    def start_commands(self, ids: torch.Tensor, frames: torch.Tensor, depth: int) -> torch.Tensor:
        """The commands in the drives' history when the envs ``ids`` start at ``frames``:
        the start frame's base, or, for a delay-aware ``feedback`` base, the stored targets
        a controller designed for that delay issued (the one issued ``i + 1`` steps ago acts
        ``d - i - 1`` steps from now; its queue starts on the plan). Shape: (n, depth, J)."""
        n = int(frames.numel())
        start = self.default_joint_pos.expand(n, -1) if self.table is None else self.table[frames]
        out = start.unsqueeze(1).expand(-1, depth, -1)
        d = self.cfg.feedback_delay
        if self.feedback is not None and d:
            assert self.table is not None
            self.queue[ids] = 0.0
            age = torch.arange(depth, device=self.device)
            frames = frames.to(self.device)
            c = self.command
            lo, hi = c.first[frames][:, None], c.last[frames][:, None]
            out = self.table[torch.minimum(torch.maximum(frames[:, None] + d - 1 - age, lo), hi)]
        return out

    def _feedback_setup(self, table: torch.Tensor, delay: int) -> Feedback:
        """The ``feedback`` base's time-varying LQR gains around each clip's refined
        trajectory (with ``table`` its stored targets, designed for ``delay`` steps of
        latency), on the robot's nominal model (the one ``humimic refine`` plans on): neither
        DR nor a physics file changes the controller, so a policy meets an unseen robot with
        the base it trained with. A clip's last frame has no control step: no gain."""
        from humimic.sim.lqr import tvlqr_gains

        cfg, c = self.cfg, self.command
        nominal = cfg.physics is None
        m = (
            self._model
            if self._model is not None and nominal
            else build_model(replace(cfg, physics=None).sim_setup())
        )
        gains, qpos, qvel = [], [], []
        for motion, start, n in zip(c.clips, c.clip_start, c.clip_length, strict=True):
            states = stored_states(motion, cfg.decimation)
            assert states is not None  # base_table checked it.
            q, v = states
            ctrl = table[int(start) : int(start + n) - 1].double().cpu().numpy()
            K = tvlqr_gains(m, q, v, ctrl, cfg.decimation, cfg.feedback, delay=delay)
            gains.append(np.concatenate([K, np.zeros_like(K[-1:])]))
            qpos.append(q)
            qvel.append(v)
        if len(gains) == 1:
            return self._tensor(gains[0]), self._tensor(qpos[0]), self._tensor(qvel[0])
        return (self._tensor(np.concatenate(gains)), self._tensor(np.concatenate(qpos)),
                self._tensor(np.concatenate(qvel)))  # fmt: skip


__all__ = ["BaseTargets", "Feedback"]
