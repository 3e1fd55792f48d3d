"""The model-based expert alone: the ``feedforward`` and ``feedback`` action bases with a zero
residual (no policy), evaluated as ``humimic eval`` evaluates a policy (whole clip from its
first frame, 32 episodes per physics). How often the stored controls and the time-varying
LQR around them survive DR draws and the unseen robots, per LQR cost setting.

Usage (a refined motion, e.g. ``humimic refine walk.npz --out walk_ref.npz``):
  .venv/bin/python benchmarks/tracking_expert.py --motion runs/walk_ref.npz \\
      --variants feedforward feedback root100
Prints JSON: one object per variant and physics.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

VARIANTS: dict[str, dict] = {
    "feedforward": {"action_base": "feedforward"},
    "feedback": {"action_base": "feedback"},
    "root10": {"action_base": "feedback", "feedback": {"base_position": 10.0}},
    "root100": {"action_base": "feedback", "feedback": {"base_position": 100.0}},
    "root1000": {"action_base": "feedback", "feedback": {"base_position": 1000.0}},
    # Around the root cost of 10 (the default until 2026-12-02), as BENCHMARKS.md reports them.
    **{name: {"action_base": "feedback", "feedback": {"base_position": 10.0, **costs}}
       for name, costs in (("control3", {"control": 3.0}), ("control30", {"control": 30.0}),
                           ("control100", {"control": 100.0}),
                           ("ori1000", {"base_orientation": 1000.0}),
                           ("joints10", {"joint_position": 10.0}),
                           ("vel10", {"base_velocity": 10.0}))},
    # The default costs, the LQR designed for 1 or 2 policy steps (20, 40 ms) of latency.
    "delay1": {"action_base": "feedback", "feedback_delay": 1},
    "delay2": {"action_base": "feedback", "feedback_delay": 2},
    "limit1": {"action_base": "feedback", "feedback_limit": 1.0,
               "feedback": {"base_position": 10.0}},
}  # fmt: skip
"""Variant name -> the task fields it sets (``feedback``: :class:`~humimic.sim.lqr.LqrWeights` fields)."""

UNSEEN = Path(__file__).parent / "physics"
"""Unseen robots of the same kind as the shipped ones, outside DR ``default`` (issue 25)."""

PHYSICS = {"nominal": ("none", None), "dr_default": ("default", None),
           "backpack": ("none", "backpack"), "worn_knees": ("none", "worn_knees"),
           **{p.stem: ("none", str(p)) for p in sorted(UNSEEN.glob("*.yaml"))}}  # fmt: skip
"""Evaluation physics -> (DR profile, physics file)."""


def evaluate_variant(motion_path: Path, robot: str, variant: dict, dr: str, physics: str | None,
                     episodes: int, seed: int, noise: float = 0.0) -> dict:  # fmt: skip
    """The zero-residual expert's episodes on one physics (``_episodes``'s metrics), with
    Gaussian action noise of standard deviation ``noise`` (what PPO's exploration adds)."""
    import torch

    from humimic.sim.lqr import LqrWeights
    from humimic.tracking.config import AdaptiveSampling, ResetNoise
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.evaluate import _episodes
    from humimic.tracking.task import load_reference, task_config

    base = task_config(robot, dr, seed, physics)
    fields = dict(variant)
    if "feedback" in fields:
        fields["feedback"] = LqrWeights(**fields["feedback"])
    motion = load_reference(motion_path, robot, 1.0 / base.step_dt)
    task = replace(
        base, **fields, start_frame=0,
        reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=((0.0, 0.0),) * 6,  # type: ignore[arg-type]
                         joint_pos=(0.0, 0.0)),
        adaptive=AdaptiveSampling(enabled=False),
        episode_length_s=motion.num_frames * base.step_dt + 1.0,
    )  # fmt: skip
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    env = TrackingEnv(task, motion, episodes)
    setup = time.perf_counter() - t0
    try:
        zero = torch.zeros(episodes, len(env.joint_names))
        out = _episodes(env, lambda obs: zero + noise * torch.randn_like(zero), episodes)
    finally:
        env.close()
    out.pop("per_body_mm")
    return {**out, "setup_s": setup, "frames": motion.num_frames}


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--motion", type=Path, required=True, help="a refined motion (.npz)")
    p.add_argument("--robot", default="g1")
    p.add_argument("--variants", nargs="+", default=["feedforward", "feedback"],
                   choices=sorted(VARIANTS))  # fmt: skip
    p.add_argument("--physics", nargs="+", default=list(PHYSICS)[:4], choices=list(PHYSICS),
                   help="default: nominal, DR default and the shipped unseen robots")  # fmt: skip
    p.add_argument("--episodes", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--noise",
        type=float,
        nargs="+",
        default=[0.0],
        help="action noise standard deviations (policy action units)",
    )
    a = p.parse_args()
    print(json.dumps({"machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
                      "motion": str(a.motion)}))  # fmt: skip
    for name in a.variants:
        for label in a.physics:
            dr, physics = PHYSICS[label]
            for noise in a.noise:
                r = evaluate_variant(a.motion, a.robot, VARIANTS[name], dr, physics, a.episodes,
                                     a.seed, noise)  # fmt: skip
                print(json.dumps({"variant": name, "physics": label, "noise": noise, **r}),
                      flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
