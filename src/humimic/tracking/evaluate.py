"""``humimic eval``: closed-loop evaluation of a tracking policy, and the open-loop baseline.

Every episode plays the whole clip from its first frame, without reset noise, under the
physics of the chosen DR profile (``none``: the nominal robot). An episode succeeds if no
tracking failure (a termination other than the clip's end) happens. Errors are averaged over
the steps each episode lived:

* global MPJPE: tracked bodies' world positions against the reference [mm];
* root-relative MPJPE: the same after subtracting each side's root position [mm];
* joint error: mean absolute joint position error [rad];
* per-body global errors [mm].

The open-loop baseline replays the reference's joint positions as PD targets (no policy): how
far the raw reference gets on this robot and these physics.
"""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import torch

from humimic.configs.runs import EvalSettings
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_writable, json_ready
from humimic.tracking.config import AdaptiveSampling, ResetNoise


def _episodes(env: Any, act: Any, episodes: int) -> dict:
    """Run one episode per env; returns the metrics."""
    s, dev = env.state, env.device
    n = env.num_envs
    alive = torch.ones(n, dtype=torch.bool, device=dev)
    failed = torch.zeros(n, dtype=torch.bool, device=dev)
    steps = torch.zeros(n, device=dev)
    glob = torch.zeros(n, device=dev)
    root = torch.zeros(n, device=dev)
    joint = torch.zeros(n, device=dev)
    per_body = torch.zeros(n, len(s.body_names), device=dev)
    obs = env.get_observations()
    with torch.inference_mode():
        while bool(alive.any()):
            obs, _, dones, extras = env.step(act(obs))
            live = alive & ~dones  # Done envs were reset inside step: their state is new.
            err = (s.body_pos_w - s.ref_body_pos_w).norm(dim=-1)  # (n, B)
            r = s.root_index
            rel = (s.body_pos_w - s.body_pos_w[:, r : r + 1]) - (
                s.ref_body_pos_w - s.ref_body_pos_w[:, r : r + 1]
            )
            w = live.float()
            steps += w
            glob += w * err.mean(dim=1)
            root += w * rel.norm(dim=-1).mean(dim=1)
            joint += w * (s.joint_pos - s.ref_joint_pos).abs().mean(dim=1)
            per_body += w[:, None] * err
            failed |= alive & dones & ~extras["time_outs"].to(dev)
            alive &= ~dones
    k = torch.arange(n, device=dev) < episodes
    st = steps.clamp(min=1)[k]
    return {
        "episodes": int(k.sum()),
        "success_rate": float((~failed[k]).float().mean()),
        "mean_steps": float(steps[k].mean()),
        "mpjpe_global_mm": float((glob[k] / st).mean() * 1e3),
        "mpjpe_root_mm": float((root[k] / st).mean() * 1e3),
        "joint_error_rad": float((joint[k] / st).mean()),
        "per_body_mm": {
            b: float((per_body[k, i] / st).mean() * 1e3) for i, b in enumerate(s.body_names)
        },
    }


def evaluate(settings: EvalSettings) -> dict:
    """Evaluate a run's policy and the open-loop baseline; write JSON if asked."""
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.rsl import make_runner
    from humimic.tracking.train import (
        load_reference,
        read_run_settings,
        resolve_checkpoint,
        task_config,
    )

    s = settings
    if s.episodes < 1:
        raise InputError(f"--episodes {s.episodes}: must be at least 1")
    if s.out is not None:
        check_writable(s.out)
    run = read_run_settings(s.run)
    path, blob = resolve_checkpoint(s.run, s.checkpoint)
    base = task_config(run.robot, s.dr, s.seed)
    motion = load_reference(run.motion, run.robot, 1.0 / base.step_dt)
    task = replace(
        base,
        start_frame=0,
        reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=((0.0, 0.0),) * 6,  # type: ignore[arg-type]
                         joint_pos=(0.0, 0.0)),
        adaptive=AdaptiveSampling(enabled=False),
        episode_length_s=motion.num_frames * base.step_dt + 1.0,
    )  # fmt: skip
    n = s.num_envs or s.episodes
    if n < s.episodes:
        raise InputError(f"--num-envs {n}: evaluate at least as many envs as --episodes")
    results: dict[str, Any] = {"run": str(s.run), "checkpoint": str(path),
                               "iterations": int(blob["iter"]), "dr": s.dr,
                               "motion": str(run.motion), "frames": motion.num_frames}  # fmt: skip

    torch.manual_seed(s.seed)
    env = TrackingEnv(task, motion, n, device=s.device)
    try:
        from humimic.tracking.rsl import train_cfg
        from humimic.tracking.train import ppo_for

        runner = make_runner(env, train_cfg(ppo_for(run)), log_dir=None, device=s.device)
        runner.load_checkpoint(blob)
        policy = runner.get_inference_policy(device=s.device)
        results["policy"] = _episodes(env, policy, s.episodes)
    finally:
        env.close()
    env = TrackingEnv(task, motion, n, device=s.device)
    try:
        st = env.state

        def open_loop(obs: Any) -> torch.Tensor:
            del obs
            nxt = (st.frame + 1).clamp(max=env.num_frames - 1)
            return (env.reference_joint_pos[nxt] - env.default_joint_pos) / env.action_scale

        results["open_loop"] = _episodes(env, open_loop, s.episodes)
    finally:
        env.close()
    if s.out is not None:
        atomic_write_text(s.out, json.dumps(json_ready(results), indent=2) + "\n")
    return results


__all__ = ["evaluate"]
