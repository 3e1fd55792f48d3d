"""The field's evaluation protocols, so that ``humimic eval`` figures compare with papers.

Both protocols play every clip once from its first frame with the deterministic policy, no
start noise and no domain randomization (on the nominal robot or the physics file the
evaluation names), and with none of the task's own terminations: the rollout runs to the
clip's end and each protocol judges it by its own rule, computed here from the recorded
poses (numpy, not the env's termination code).

1. **BeyondMimic** (Liao et al., 2025; mjlab's ``tracking_env_cfg.py``): a clip fails at the
   first step where the anchor body's height differs from the reference's by more than
   0.25 m, or the z component of its projected gravity ``R^T [0, 0, -1]`` differs from the
   reference's by more than 0.8 (BeyondMimic's orientation rule: a difference of cosines of
   tilt, not an angle in radians). Reported: the failed clips and the mean normalized return
   (the return up to the failure over the return of a full clip at the maximum reward of
   every step).
2. **PHC / ProtoMotions** (Luo et al., 2023): a clip fails at the first step where the mean
   over tracked bodies of the global position error exceeds 0.5 m. Reported: the success
   rate, global and root-relative MPJPE [mm], and the velocity and acceleration errors of the
   body positions (finite differences, [mm/frame] and [mm/frame^2] at the policy rate, as
   PHC computes them at its rate), each over all clips and over the successful clips (null
   when none succeeded); a failed clip's errors cover its steps up to the failure.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from humimic.errors import InputError

BEYONDMIMIC_HEIGHT_M = 0.25
BEYONDMIMIC_GRAVITY_Z = 0.8
PHC_MEAN_BODY_M = 0.5

BEYONDMIMIC_RULE = (
    f"one deterministic play of each clip from its first frame, no noise or randomization; "
    f"a clip fails when the anchor's height error exceeds {BEYONDMIMIC_HEIGHT_M} m or its "
    f"projected-gravity z error exceeds {BEYONDMIMIC_GRAVITY_Z}"
)
PHC_RULE = (
    f"one deterministic play of each clip from its first frame, no noise or randomization; "
    f"a clip fails when the mean global body position error exceeds {PHC_MEAN_BODY_M} m"
)


@dataclass(frozen=True)
class ClipTrace:
    """One deterministic play of a clip, step by step (``T`` policy steps).

    Attributes:
        anchor_pos: The robot's anchor body position. Shape: (T, 3).
        ref_anchor_pos: The reference's. Shape: (T, 3).
        anchor_quat: The robot's anchor orientation (w, x, y, z). Shape: (T, 4).
        ref_anchor_quat: The reference's. Shape: (T, 4).
        body_pos: Tracked bodies' world positions. Shape: (T, B, 3).
        ref_body_pos: The reference's. Shape: (T, B, 3).
        root: Index of the robot's root among the tracked bodies.
        reward: Each step's reward. Shape: (T,).
        reward_max: The largest reward one step can earn (the positive terms' weights).
    """

    anchor_pos: np.ndarray
    ref_anchor_pos: np.ndarray
    anchor_quat: np.ndarray
    ref_anchor_quat: np.ndarray
    body_pos: np.ndarray
    ref_body_pos: np.ndarray
    root: int
    reward: np.ndarray
    reward_max: float

    @property
    def steps(self) -> int:
        """The clip's steps."""
        return len(self.reward)


def _gravity_z(q: np.ndarray) -> np.ndarray:
    """z of the projected gravity ``R^T [0, 0, -1]``, i.e. ``-R[2, 2]`` (rotation matrix)."""
    from humimic import transforms as tf

    return -tf.quat_to_matrix(q / np.linalg.norm(q, axis=-1, keepdims=True))[..., 2, 2]


def _first(bad: np.ndarray) -> int | None:
    idx = np.flatnonzero(bad)
    return int(idx[0]) if len(idx) else None


def beyondmimic(tr: ClipTrace) -> dict[str, Any]:
    """Protocol 1 on one clip: ``failed``, ``fail_step`` (``None`` if it did not fail) and
    ``normalized_return`` (the reward up to and including the failing step over
    ``steps * reward_max``)."""
    height = np.abs(tr.anchor_pos[:, 2] - tr.ref_anchor_pos[:, 2])
    tilt = np.abs(_gravity_z(tr.anchor_quat) - _gravity_z(tr.ref_anchor_quat))
    fail = _first((height > BEYONDMIMIC_HEIGHT_M) | (tilt > BEYONDMIMIC_GRAVITY_Z))
    end = tr.steps if fail is None else fail + 1
    denom = tr.steps * tr.reward_max
    return {
        "failed": fail is not None,
        "fail_step": fail,
        "normalized_return": float(tr.reward[:end].sum() / denom) if denom > 0 else None,
    }


def phc(tr: ClipTrace) -> dict[str, Any]:
    """Protocol 2 on one clip: ``failed``, ``fail_step``, and the errors over the steps up to
    the failure (all of them if none): MPJPE global and root-relative [mm], velocity
    [mm/frame] and acceleration [mm/frame^2] errors (``None`` where the steps are too few)."""
    err = np.linalg.norm(tr.body_pos - tr.ref_body_pos, axis=-1)  # (T, B)
    fail = _first(err.mean(axis=1) > PHC_MEAN_BODY_M)
    end = tr.steps if fail is None else fail + 1
    p, q = tr.body_pos[:end], tr.ref_body_pos[:end]
    r = tr.root
    rel = (p - p[:, r : r + 1]) - (q - q[:, r : r + 1])
    vel = np.diff(p, axis=0) - np.diff(q, axis=0)
    acc = np.diff(p, 2, axis=0) - np.diff(q, 2, axis=0)

    def mean_mm(x: np.ndarray) -> float | None:
        return float(np.linalg.norm(x, axis=-1).mean() * 1e3) if x.size else None

    return {
        "failed": fail is not None,
        "fail_step": fail,
        "mpjpe_global_mm": mean_mm(p - q),
        "mpjpe_root_mm": mean_mm(rel),
        "vel_error_mm_per_frame": mean_mm(vel),
        "acc_error_mm_per_frame2": mean_mm(acc),
    }


def judge(tr: ClipTrace) -> dict[str, dict[str, Any]]:
    """Both protocols on one clip: ``{"beyondmimic": ..., "phc": ...}``."""
    return {"beyondmimic": beyondmimic(tr), "phc": phc(tr)}


PHC_ERRORS = ("mpjpe_global_mm", "mpjpe_root_mm", "vel_error_mm_per_frame",
              "acc_error_mm_per_frame2")  # fmt: skip


def _mean(rows: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rows if r[key] is not None]
    return float(np.mean(vals)) if vals else None


def summarize(per_clip: Mapping[str, Mapping[str, dict[str, Any]]]) -> dict[str, Any]:
    """Both protocols over a set of clips (name -> ``{"beyondmimic": ..., "phc": ...}``, as
    :func:`beyondmimic` and :func:`phc` return): each protocol's rule, totals and the table
    per clip. A mean over no clip is ``None``."""
    names = list(per_clip)
    bm = [per_clip[n]["beyondmimic"] for n in names]
    ph = [per_clip[n]["phc"] for n in names]
    ok = [r for r in ph if not r["failed"]]
    return {
        "beyondmimic": {
            "rule": BEYONDMIMIC_RULE,
            "clips": len(bm),
            "failed_clips": sum(r["failed"] for r in bm),
            "mean_normalized_return": _mean(bm, "normalized_return"),
            "per_clip": dict(zip(names, bm, strict=True)),
        },
        "phc": {
            "rule": PHC_RULE,
            "clips": len(ph),
            "success_rate": (len(ok) / len(ph)) if ph else None,
            "all": {k: _mean(ph, k) for k in PHC_ERRORS},
            "successful": {k: _mean(ok, k) for k in PHC_ERRORS} if ok else None,
            "per_clip": dict(zip(names, ph, strict=True)),
        },
    }


def play_clip(env: Any, act: Any) -> ClipTrace:
    """Play env 0 of ``env`` (a tracking env of the evaluation task, started on the clip's
    first frame, the task's failure terminations removed) with ``act`` until its episode ends
    at the clip's last frame; record what the protocols judge."""
    from humimic.tracking.rsl import torch_threads

    s, cfg = env.state, env.cfg
    scale = env.step_dt if cfg.reward_dt_scale else 1.0
    reward_max = scale * sum(max(tc.weight, 0.0) for tc in cfg.rewards.values())
    rows: dict[str, list[np.ndarray]] = {k: [] for k in (
        "anchor_pos", "ref_anchor_pos", "anchor_quat", "ref_anchor_quat", "body_pos",
        "ref_body_pos", "reward")}  # fmt: skip
    obs = env.get_observations()
    threads = 1 if env.device.type == "cpu" else torch.get_num_threads()
    with torch.inference_mode(), torch_threads(threads):
        while True:
            obs, rew, dones, _ = env.step(act(obs))
            if bool(dones[0]):  # Reset inside step: the state is a new episode's.
                break
            for k, x in (("anchor_pos", s.anchor_pos_w), ("ref_anchor_pos", s.ref_anchor_pos_w),
                         ("anchor_quat", s.anchor_quat_w), ("ref_anchor_quat", s.ref_anchor_quat_w),
                         ("body_pos", s.body_pos_w), ("ref_body_pos", s.ref_body_pos_w),
                         ("reward", rew)):  # fmt: skip
                rows[k].append(x[0].double().cpu().numpy())
    if not rows["reward"]:
        raise InputError("the clip is too short to play: it ends on its first step")
    arr = {k: np.array(v) for k, v in rows.items()}
    return ClipTrace(**arr, root=s.root_index, reward_max=reward_max)


__all__ = ["ClipTrace", "beyondmimic", "judge", "phc", "play_clip", "summarize"]
