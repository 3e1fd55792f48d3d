"""Does a dynamically refined reference make tracking easier? Two PPO runs of equal budget
(same envs, iterations, rollout length, DR, seed) on the kinematic reference and on its
``humimic refine`` result; both policies evaluated on their own reference and on the kinematic
one (what the human did), against the open-loop replay of each reference. Prints JSON; writes
both learning curves into one PNG.

Usage:
  .venv/bin/humimic retarget ../shared/data/cmu/35_01.bvh --out walk.npz
  .venv/bin/humimic refine walk.npz --out walk_dyn.npz
  .venv/bin/python benchmarks/refined_tracking.py --kinematic walk.npz --refined walk_dyn.npz \\
      --out runs/refined_vs_kinematic --iterations 600 --num-envs 128 \\
      --plot docs/refined_tracking_curve.png [--compile]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import time
from pathlib import Path

from humimic.configs.jobs import EvalSettings
from humimic.configs.runs import TrainSettings
from humimic.motion import load_motion
from humimic.tracking.evaluate import evaluate
from humimic.tracking.train import train

METRICS = ("success_rate", "mean_steps", "mpjpe_global_mm", "mpjpe_root_mm", "joint_error_rad")


def _curve(run: Path) -> list[dict[str, float]]:
    with open(run / "progress.csv") as f:
        return [
            {k: float(r[k]) for k in ("iteration", "seconds", "mean_reward", "mean_episode_length")}
            for r in csv.DictReader(f)
        ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--kinematic", type=Path, required=True)
    parser.add_argument("--refined", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--num-envs", type=int, default=128)
    parser.add_argument("--dr", default="default")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--compile", action="store_true", help="torch.compile the env's math")
    parser.add_argument("--plot", type=Path, default=None)
    args = parser.parse_args()
    for path in (args.kinematic, args.refined):
        if not path.is_file():
            parser.error(f"{path}: no such file")
    if load_motion(args.refined).dynamics is None:
        parser.error(f"--refined {args.refined}: no dynamic section (run humimic refine)")

    result: dict = {
        "benchmark": "refined_tracking",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "num_envs": args.num_envs, "iterations": args.iterations, "dr": args.dr,
        "seed": args.seed, "runs": {},
    }  # fmt: skip
    references = {"kinematic": args.kinematic, "refined": args.refined}
    for name, motion in references.items():
        run = args.out / name
        t0 = time.perf_counter()
        train(
            TrainSettings(
                motion=motion,
                out=run,
                num_envs=args.num_envs,
                max_iterations=args.iterations,
                dr=args.dr,
                seed=args.seed,
                checkpoint_every=100,
                quiet=True,
                compile=args.compile,
                resume=(run / "config.yaml").exists(),
            )
        )
        entry: dict = {"train_seconds": time.perf_counter() - t0, "curve": _curve(run)}
        for ref_name, ref in references.items():  # Each policy on both references.
            ev = evaluate(EvalSettings(run=run, episodes=args.episodes, motion=ref, dr="none"))
            entry[f"eval_on_{ref_name}"] = {
                k: {m: ev[k][m] for m in METRICS} for k in ("policy", "open_loop")
            }
        result["runs"][name] = entry
        print(json.dumps({name: {k: v for k, v in entry.items() if k != "curve"}}), flush=True)
    if args.plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
        for name, entry in result["runs"].items():
            it = [r["iteration"] for r in entry["curve"]]
            a.plot(it, [r["mean_episode_length"] for r in entry["curve"]], label=name)
            b.plot(it, [r["mean_reward"] for r in entry["curve"]], label=name)
        a.set_xlabel("PPO iteration")
        a.set_ylabel("mean episode length [policy steps]")
        b.set_xlabel("PPO iteration")
        b.set_ylabel("mean episode reward")
        a.legend()
        fig.suptitle(
            f"G1 tracking, kinematic vs refined reference: {args.num_envs} envs, "
            f"{args.iterations} iterations each, DR {args.dr}"
        )
        fig.savefig(args.plot, dpi=90, bbox_inches="tight")
        result["plot"] = str(args.plot)
    for entry in result["runs"].values():  # Thin the curves for the printout.
        entry["curve"] = entry["curve"][:: max(1, len(entry["curve"]) // 20)] + entry["curve"][-1:]
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
