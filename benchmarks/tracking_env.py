"""Tracking environment throughput on the CPU: env-steps per second of ``TrackingEnv.step``
(policy steps at 50 Hz, 4 physics steps each) and of the backend alone, for both stepping
methods (``mujoco.rollout`` vs a Python thread pool over ``mj_step``) and both DR profiles, plus
the time of one PPO iteration (rollout + update). Prints JSON.

Usage: .venv/bin/python benchmarks/tracking_env.py [--num-envs 64 256] [--steps 50]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace

import numpy as np
import torch

from humimic.motion import motion_from_qpos
from humimic.tracking.config import g1_tracking
from humimic.tracking.env import TrackingEnv, tracking_model
from humimic.tracking.rsl import make_runner, tracking_ppo, train_cfg


def _motion(model):
    fps, T = 50.0, 250
    q = np.tile(model.key_qpos[0], (T, 1))
    adr = model.jnt_qposadr[model.joint("left_shoulder_pitch_joint").id]
    q[:, adr] += 0.3 * np.sin(2 * np.pi * np.arange(T) / fps)
    return motion_from_qpos(model, q, fps, "g1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    out = {"benchmark": "tracking_env", "machine": {"cpu": platform.processor() or
           platform.machine(), "cores": os.cpu_count()}, "torch_threads": torch.get_num_threads(),
           "results": []}  # fmt: skip
    model = tracking_model(g1_tracking("none"))
    motion = _motion(model)
    for n in args.num_envs:
        for dr in ("none", "default"):
            for method in ("rollout", "threads"):
                cfg = replace(g1_tracking(dr), step_method=method, episode_length_s=1e3)
                env = TrackingEnv(cfg, motion, n, model=model)
                gen = torch.Generator().manual_seed(0)
                actions = [0.2 * torch.randn(n, env.num_actions, generator=gen)
                           for _ in range(args.steps)]  # fmt: skip
                with torch.inference_mode():
                    env.step(actions[0])
                    t0 = time.perf_counter()
                    for a in actions:
                        env.step(a)
                    env_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    env.backend.step(cfg.decimation)
                backend_s = time.perf_counter() - t0
                env.close()
                row = {"num_envs": n, "dr": dr, "method": method,
                       "env_steps_per_s": n * args.steps / env_s,
                       "backend_env_steps_per_s": n * args.steps / backend_s}  # fmt: skip
                out["results"].append(row)
                print(json.dumps(row), flush=True)
        cfg = g1_tracking("default")
        env = TrackingEnv(cfg, motion, n, model=model)
        runner = make_runner(env, train_cfg(tracking_ppo()), log_dir=None, device="cpu")
        t0 = time.perf_counter()
        runner.learn(2)
        it_s = (time.perf_counter() - t0) / 2
        env.close()
        row = {"num_envs": n, "ppo_iteration_s": it_s,
               "transitions_per_iteration": n * tracking_ppo().num_steps_per_env}  # fmt: skip
        out["results"].append(row)
        print(json.dumps(row), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
