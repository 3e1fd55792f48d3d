"""The motion command of the tracking task: the reference clips as tensors, the states episodes
start from, and BeyondMimic's adaptive sampling of start frames.

:class:`MotionCommand` holds what every step reads of the reference (one packed table, one
gather per step) and the failure statistics that choose where episodes start. A library of
clips is one table, the clips one after the other; every frame knows its clip's first and
last frame, so an episode ends at its own clip's end. Each clip is cut into bins, each bin's
failure rate is an exponential average of the episodes that failed there, smoothed forward
within its clip by a kernel (a failure is often caused a little earlier), and start bins are
drawn in proportion over the whole library, so a clip that fails more is started more often
(Liao et al., "BeyondMimic", 2025); every bin keeps a floor (``uniform_ratio``). A library's
clip weights (``{file: a.npz, weight: 2}``) multiply its bins' and frames' probabilities.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from humimic import transforms as tf
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.tracking.actions import STORED_BASES, stored_states
from humimic.tracking.config import TrackingConfig


def as_clips(motion: Motion | Sequence[Motion]) -> tuple[Motion, ...]:
    """One clip or a library of clips, as a tuple.

    Raises:
        InputError: An empty library.
    """
    clips = (motion,) if isinstance(motion, Motion) else tuple(motion)
    if not clips:
        raise InputError("the motion library has no clip")
    return clips


class MotionCommand:
    """The reference motions of a tracking task, in the env's joint and tracked-body order.

    Args:
        cfg: The task (its tracked bodies, action base, adaptive sampling, start frame).
        motion: The reference clip, or a library of clips, at the policy rate.
        joint_names: The env's joints (the backend's order).
        root_body: The robot's root body.
        device: Torch device of the tables.

    Raises:
        InputError: If the motion lacks a joint or tracked body of the task.
    """

    def __init__(
        self,
        cfg: TrackingConfig,
        motion: Motion | Sequence[Motion],
        joint_names: Sequence[str],
        root_body: str,
        device: torch.device,
    ) -> None:
        self.clips = clips = as_clips(motion)
        try:
            jidx = [clips[0].joint_names.index(j) for j in joint_names]
            bidx = [clips[0].body_names.index(b) for b in cfg.body_names]
            root_m = clips[0].body_names.index(root_body)
        except ValueError as e:
            raise InputError(f"the motion lacks a joint or body of the task: {e}") from None
        for c in clips[1:]:
            if c.joint_names != clips[0].joint_names or c.body_names != clips[0].body_names:
                raise InputError(
                    f"{c.source or 'a clip'}: its joints or bodies differ from the first "
                    "clip's: a library's clips are of one robot, written alike"
                )
        self.cfg, self.device, self.joint_index = cfg, device, jidx
        lengths = np.array([c.num_frames for c in clips])
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        self.num_frames = T = int(lengths.sum())
        self.clip_start, self.clip_length = starts, lengths
        """Each clip's first frame in the library's table, and its frames. Shape: (C,)."""
        self._start_t = torch.as_tensor(starts, device=device)
        self._length_t = torch.as_tensor(lengths, device=device)
        clip_of = np.repeat(np.arange(len(clips)), lengths)
        self.clip_of = torch.as_tensor(clip_of, device=device)
        """The clip of every frame. Shape: (T,), long."""
        self.first = torch.as_tensor(starts[clip_of], device=device)
        self.last = torch.as_tensor((starts + lengths - 1)[clip_of], device=device)
        """The first and last frame of every frame's clip. Shape: (T,), long."""

        def cat(f: Callable[[Motion], np.ndarray]) -> np.ndarray:
            return np.concatenate([f(c) for c in clips])

        fields = [
            cat(lambda m: m.joint_pos[:, jidx]), cat(lambda m: m.joint_vel[:, jidx]),
            cat(lambda m: m.body_pos_w[:, bidx]), cat(lambda m: m.body_quat_w[:, bidx]),
            cat(lambda m: m.body_lin_vel_w[:, bidx]), cat(lambda m: m.body_ang_vel_w[:, bidx]),
        ]  # fmt: skip
        tables = [self._tensor(f) for f in fields]
        self.joint_pos = tables[0]
        """The reference's joint positions. Shape: (T, J)."""
        # One packed table of what every step reads: one gather per step instead of six.
        self.packed = torch.cat([x.reshape(T, -1) for x in tables], dim=1)
        self.split = [x.reshape(T, -1).shape[1] for x in tables]
        """The widths of the fields in :attr:`packed`: joint positions and velocities, tracked
        bodies' positions, orientations, linear and angular velocities (world frame)."""
        self._root_m = root_m
        weights = np.array([float((c.info or {}).get("library_weight", 1.0)) for c in clips])
        self.clip_weight = weights
        """Each clip's sampling weight (a library's, :func:`~humimic.tracking.task.
        library_entries`): its frames are that much more likely to start an episode."""
        self._weighted = bool(np.any(weights != 1.0))
        self._make_bins()
        # Start frames without adaptive sampling: any frame but a clip's last.
        startable = np.flatnonzero(np.arange(T) != (starts + lengths - 1)[clip_of])
        self._startable = torch.as_tensor(startable, device=device)
        self._startable_w = torch.as_tensor(weights[clip_of[startable]], device=device)
        self._clip_w = torch.as_tensor(weights, device=device)

    def _make_bins(self) -> None:
        """Adaptive sampling's bins: each clip cut into bins of ``bin_s``; every frame's bin,
        and where the kernel's forward smoothing reads (never past its clip's last bin)."""
        cfg, dev, ad = self.cfg, self.device, self.cfg.adaptive
        per_bin = max(ad.bin_s / cfg.step_dt, 1.0)
        counts = np.array([int(n // per_bin) + 1 for n in self.clip_length])
        first_bin = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.bin_count = int(counts.sum())
        self.bin_failed = torch.zeros(self.bin_count, device=dev)
        self._clip_bins = torch.as_tensor(counts, device=dev)
        self._bin_clip = torch.as_tensor(np.repeat(np.arange(len(counts)), counts), device=dev)
        self._first_bin = torch.as_tensor(first_bin, device=dev)
        frame_bin = [
            b0 + np.clip((np.arange(n) * c) // n, 0, c - 1)
            for b0, c, n in zip(first_bin, counts, self.clip_length, strict=True)
        ]
        self._frame_bin = torch.as_tensor(np.concatenate(frame_bin), device=dev)
        self._bin_weight = torch.as_tensor(
            np.repeat(self.clip_weight, counts), dtype=torch.float32, device=dev
        )
        # Each clip's bins followed by kernel_size - 1 copies of its last: one convolution
        # smooths every clip within itself.
        k = ad.kernel_size
        pad = [np.concatenate([b0 + np.arange(c), np.full(k - 1, b0 + c - 1)])
               for b0, c in zip(first_bin, counts, strict=True)]  # fmt: skip
        self._padded = torch.as_tensor(np.concatenate(pad), device=dev)
        self._smoothed = torch.as_tensor(
            np.concatenate([i * (k - 1) + b0 + np.arange(c)
                            for i, (b0, c) in enumerate(zip(first_bin, counts, strict=True))]),
            device=dev,
        )  # fmt: skip
        kernel = torch.tensor([ad.kernel_lambda**i for i in range(k)], device=dev)
        self._kernel = (kernel / kernel.sum()).view(1, 1, -1)
        self.weights = torch.zeros(self.bin_count, device=dev)
        """Start-bin sampling probabilities. Shape: (bins,)."""

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32, device=self.device)

    def gather(self, frame: torch.Tensor, out: torch.Tensor) -> None:
        """The packed reference at each env's ``frame`` into ``out`` (one gather)."""
        torch.index_select(self.packed, 0, frame, out=out)

    @functools.cached_property
    def start(self) -> dict[str, np.ndarray]:
        """The reference states episodes start from (float64), every clip's frames one after
        the other: the motion's frames and their finite-difference velocities, or, with a
        stored base (``feedforward``, ``feedback``), the simulated states the stored controls
        continue from (:func:`~humimic.tracking.actions.stored_states`). Read after the action
        base is built (:class:`~humimic.tracking.bases.BaseTargets`), which checks the
        motions' dynamic sections."""
        per_clip = [self._start_of(c) for c in self.clips]
        if len(per_clip) == 1:
            return per_clip[0]
        return {k: np.concatenate([p[k] for p in per_clip]) for k in per_clip[0]}

    def _start_of(self, motion: Motion) -> dict[str, np.ndarray]:
        jidx, root_m = self.joint_index, self._root_m
        if self.cfg.action_base in STORED_BASES:
            states = stored_states(motion, self.cfg.decimation)
            assert states is not None  # BaseTargets' base_table has checked the section.
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

    # ------------------------------------------------------------------ adaptive sampling

    def sample_frames(self, n: int, gen: torch.Generator) -> torch.Tensor:
        """``n`` start frames: the task's fixed start frame (of a clip drawn by the clips'
        weights, in a library), or drawn by the sampling weights (without adaptive sampling,
        over the frames that are not a clip's last, each by its clip's weight)."""
        dev = self.device
        if self.cfg.start_frame is not None:
            f = torch.full((n,), self.cfg.start_frame, device=dev)
            if len(self.clips) == 1:
                return f.clamp(max=self.num_frames - 2)
            if self._weighted:
                c = torch.multinomial(self._clip_w, n, replacement=True, generator=gen)
            else:
                c = torch.randint(0, len(self.clips), (n,), generator=gen, device=dev)
            return self._start_t[c] + torch.minimum(f, self._length_t[c] - 2)
        if self.cfg.adaptive.enabled:
            bins = torch.multinomial(self.weights, n, replacement=True, generator=gen)
            u = torch.rand(n, generator=gen, device=dev)
            clip = self._bin_clip[bins]
            local = bins - self._first_bin[clip]
            length = self._length_t[clip]
            frames = ((local.float() + u) / self._clip_bins[clip] * (length - 1)).long()
            frames = torch.minimum(frames.clamp(min=0), length - 2)
            return frames + self._start_t[clip]
        if self._weighted:
            i = torch.multinomial(self._startable_w, n, replacement=True, generator=gen)
        else:
            i = torch.randint(0, len(self._startable), (n,), generator=gen, device=dev)
        return self._startable[i]

    def fold_failures(self, frame: torch.Tensor, failed: torch.Tensor) -> None:
        """Fold one step's failures (``failed``: 1.0 per env whose episode failed at its
        ``frame``) into the failure rate of each bin and recompute the sampling weights (no
        host sync: a scatter, not a test for failures)."""
        now = torch.zeros_like(self.bin_failed).scatter_add_(0, self._frame_bin[frame], failed)
        a = self.cfg.adaptive.alpha
        self.bin_failed.mul_(1.0 - a).add_(a * now)
        self.weights.copy_(self._compute_weights())

    def _compute_weights(self) -> torch.Tensor:
        ad = self.cfg.adaptive
        n = self.bin_count
        if not ad.enabled:
            return torch.full((n,), 1.0 / n, device=self.device)
        p = self.bin_failed + ad.uniform_ratio / n
        padded = p[self._padded]
        out = torch.nn.functional.conv1d(padded.view(1, 1, -1), self._kernel).view(-1)
        out = out[self._smoothed]
        if self._weighted:
            out = out * self._bin_weight
        return out / out.sum()

    def sampling_entropy(self) -> torch.Tensor:
        """The sampling weights' entropy over its maximum (1: uniform)."""
        p = self.weights
        h = -(p * (p + 1e-12).log()).sum()
        return h / math.log(self.bin_count) if self.bin_count > 1 else h * 0 + 1


__all__ = ["MotionCommand", "as_clips"]
