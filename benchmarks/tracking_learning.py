"""A tracking policy learns a real clip on this machine: train for a wall-time budget, evaluate
against the open-loop baseline on the same episodes, plot the learning curve. Prints JSON.

Usage:
  .venv/bin/humimic retarget ../shared/data/cmu/35_01.bvh --out walk.npz
  .venv/bin/python benchmarks/tracking_learning.py --motion walk.npz --out runs/walk \\
      --minutes 45 --num-envs 128 --plot docs/tracking_walk_curve.png
On a GPU (MuJoCo Warp, humimic[gpu]):
  python benchmarks/tracking_learning.py --motion walk.npz --out runs/walk_gpu --minutes 6 \\
      --num-envs 4096 --device cuda --backend warp
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
from pathlib import Path

import torch

from humimic.configs.jobs import EvalSettings
from humimic.configs.runs import TrainSettings
from humimic.tracking.evaluate import evaluate
from humimic.tracking.train import train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--motion", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=45.0)
    parser.add_argument("--num-envs", type=int, default=128)
    parser.add_argument("--dr", default="default")
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", choices=("cpu", "warp"), default="cpu")
    args = parser.parse_args()
    settings = TrainSettings(motion=args.motion, out=args.out, num_envs=args.num_envs,
                             max_iterations=100_000, dr=args.dr, max_minutes=args.minutes,
                             checkpoint_every=25, quiet=True, device=args.device,
                             backend=args.backend,
                             resume=(args.out / "config.yaml").exists())  # fmt: skip
    train(settings)
    with open(args.out / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    result = {"benchmark": "tracking_learning", "machine": {"cpu": platform.processor() or
              platform.machine(), "cores": os.cpu_count(), "gpu": torch.cuda.get_device_name(0)
              if torch.cuda.is_available() else None}, "motion": str(args.motion),
              "num_envs": args.num_envs, "dr": args.dr, "minutes": args.minutes,
              "device": args.device, "backend": args.backend,
              "iterations": int(rows[-1]["iteration"]), "env_steps": int(float(rows[-1]["env_steps"])),
              "curve": [{k: float(r[k]) for k in ("iteration", "seconds", "mean_reward",
                                                   "mean_episode_length")}
                        for r in rows[:: max(1, len(rows) // 20)] + rows[-1:]]}  # fmt: skip
    for dr in ("none", args.dr):
        ev = evaluate(EvalSettings(run=args.out, episodes=args.episodes, dr=dr))
        result[f"eval_{dr}"] = {k: {m: ev[k][m] for m in ("success_rate", "mean_steps",
                                "mpjpe_global_mm", "mpjpe_root_mm", "joint_error_rad")}
                                for k in ("policy", "open_loop")}  # fmt: skip
        result["frames"] = ev["frames"]
    if args.plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        it = [float(r["iteration"]) for r in rows]
        fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
        a.plot(it, [float(r["mean_episode_length"]) for r in rows])
        a.set_xlabel("PPO iteration")
        a.set_ylabel("mean episode length [policy steps]")
        b.plot(it, [float(r["mean_reward"]) for r in rows])
        b.set_xlabel("PPO iteration")
        b.set_ylabel("mean episode reward")
        fig.suptitle(f"G1 tracking {args.motion.name}: {args.num_envs} envs, DR {args.dr}, "
                     f"{args.minutes:g} min on {os.cpu_count()} CPU cores")  # fmt: skip
        fig.savefig(args.plot, dpi=90, bbox_inches="tight")
        result["plot"] = str(args.plot)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
