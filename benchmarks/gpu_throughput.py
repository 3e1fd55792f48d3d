"""G1 tracking env throughput on a GPU (the MuJoCo Warp backend), against raw MJWarp stepping
of the same model in the same run. Prints JSON.

For each env count:

* ``raw``: the backend alone (``MujocoWarpBackend.step``, the env step's 4 physics steps
  replayed as one CUDA graph) with fixed PD targets: MJWarp's own throughput for this model,
  the ceiling of the env.
* ``env``: the whole :class:`~humimic.tracking.env.TrackingEnv` (DR, resets, rewards,
  observations, terminations) with random actions, as PPO collects rollouts.

Steps/s count env (policy, 50 Hz) steps over all envs; ``physics_steps_per_s`` multiplies by
the decimation (4). Every timing is bracketed by ``torch.cuda.synchronize()``.

Usage (a GPU machine with ``humimic[gpu]``):
  python benchmarks/gpu_throughput.py [--num-envs 1024 4096 8192] [--steps 200]
      [--motion walk.npz] [--dr default]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import replace
from pathlib import Path

import torch

from env_throughput import arm_swing  # The CPU benchmark's reference (no data files needed).
from humimic.sim.warp_backend import MujocoWarpBackend
from humimic.tracking.actions import has_stored_controls
from humimic.tracking.config import g1_tracking
from humimic.tracking.env import TrackingEnv, tracking_backend, tracking_model
from humimic.tracking.task import load_reference, resolve_dr


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn, steps: int) -> float:
    _sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    _sync()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024, 4096, 8192])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--motion", type=Path, default=None)
    parser.add_argument("--dr", default="default")
    parser.add_argument("--device", default="cuda")
    parser.add_argument(
        "--compile", action="store_true", help="also the env with its math compiled (torch.compile)"
    )
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("no CUDA device (--device cpu runs MJWarp on the CPU: a smoke test only)")
    cuda = args.device.startswith("cuda")
    cfg = replace(g1_tracking("none"), dr=resolve_dr(args.dr), backend="warp")
    model = tracking_model(cfg)
    motion = (
        arm_swing(model)
        if args.motion is None
        else load_reference(args.motion, "g1", 1.0 / cfg.step_dt)
    )
    if not has_stored_controls(motion):  # The LQR base needs a refined motion.
        cfg = replace(cfg, action_base="default")
    dec = cfg.decimation
    out: dict = {
        "benchmark": "gpu_throughput",
        "machine": {
            "gpu": torch.cuda.get_device_name(0) if cuda else None,
            "cpu": platform.processor() or platform.machine(),
            "torch": torch.__version__,
        },
        "motion": str(args.motion or "arm swing, 5 s"),
        "dr": args.dr,
        "decimation": dec,
        "steps": args.steps,
        "results": [],
    }
    for n in args.num_envs:
        row: dict = {"num_envs": n}
        t0 = time.perf_counter()
        be = tracking_backend(cfg, n, model=model, device=args.device)
        assert isinstance(be, MujocoWarpBackend)
        row["backend_build_s"] = time.perf_counter() - t0
        ctrl = torch.as_tensor(be.default_joint_pos, dtype=torch.float32, device=be.device)
        be.set_ctrl_tensor(ctrl.expand(n, -1))
        _timed(lambda be=be: be.step(dec), args.warmup)
        sec = _timed(lambda be=be: be.step(dec), args.steps)
        row["raw_env_steps_per_s"] = n * args.steps / sec
        row["raw_physics_steps_per_s"] = n * args.steps * dec / sec
        be.close()
        del be
        if cuda:
            torch.cuda.empty_cache()

        for name, compiled in (("env", False), ("compiled_env", True))[: 1 + args.compile]:
            t0 = time.perf_counter()
            ecfg = replace(cfg, torch_compile=compiled)
            env = TrackingEnv(ecfg, motion, n, device=args.device, model=model)
            row[f"{name}_build_s"] = time.perf_counter() - t0
            gen = torch.Generator(device=env.device).manual_seed(0)

            def step(env=env, gen=gen, n=n) -> None:
                a = torch.randn(n, env.num_actions, generator=gen, device=env.device)
                with torch.inference_mode():
                    env.step(a)

            _timed(step, args.warmup)
            if cuda:
                torch.cuda.reset_peak_memory_stats()
            sec = _timed(step, args.steps)
            row[f"{name}_steps_per_s"] = n * args.steps / sec
            row[f"{name}_physics_steps_per_s"] = n * args.steps * dec / sec
            row[f"{name}_over_raw"] = row[f"{name}_steps_per_s"] / row["raw_env_steps_per_s"]
            if cuda:
                row[f"{name}_torch_peak_mem_gib"] = torch.cuda.max_memory_allocated() / 2**30
            env.close()
            del env
            if cuda:
                torch.cuda.empty_cache()
        out["results"].append(row)
        print(json.dumps(row), flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
