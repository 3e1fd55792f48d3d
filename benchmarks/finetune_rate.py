"""Fine-tuning a converged tracking policy: which PPO settings keep or improve it. Each recipe
fine-tunes RUN from its weights for a fixed number of iterations in PHYSICS (e.g. the "real"
robot's true physics: an oracle with no sysid between), under the run's DR and other PPO
settings, then evaluates 32 deterministic episodes on PHYSICS and on the nominal robot.
Iteration-fixed: other load changes the seconds, not the result. Prints one JSON line per
recipe and a summary object.

Usage: .venv/bin/python benchmarks/finetune_rate.py --run RUN --physics worn_knees --out DIR
       [--recipe NAME:LR:ENVS:ITERATIONS ...]  (default: the five recipes of BENCHMARKS.md)
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from humimic.configs.jobs import EvalSettings
from humimic.configs.runs import TrainSettings
from humimic.tracking.evaluate import run_evaluation
from humimic.tracking.runs import run_config
from humimic.tracking.train import train

DEFAULT = ["1e-3-adaptive:1e-3:128:100", "1e-4:1e-4:128:100", "3e-5:3e-5:128:100",
           "3e-5-x3:3e-5:128:300", "3e-5-512:3e-5:512:25"]  # fmt: skip
_METRICS = ("success_rate", "mpjpe_global_mm", "mpjpe_root_mm")


def _evaluate(run: Path, physics: str | None, seed: int) -> dict:
    ev = run_evaluation(EvalSettings(run=run, episodes=32, physics=physics, seed=seed))
    return {k: ev.results["policy"][k] for k in _METRICS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--physics", required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--recipe", nargs="*", default=DEFAULT)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    _, run = run_config(args.run)
    out = {"benchmark": "finetune_rate", "run": str(args.run), "physics": args.physics,
           "before": {args.physics: _evaluate(args.run, args.physics, args.seed),
                      "nominal": _evaluate(args.run, None, args.seed)},
           "recipes": []}  # fmt: skip
    print(json.dumps(out["before"]), flush=True)
    for text in args.recipe:
        name, lr, envs, iterations = text.split(":")
        schedule = "adaptive" if name.endswith("adaptive") else "fixed"
        folder = args.out / name
        t0 = time.perf_counter()
        train(TrainSettings(
            motion=run.motion, out=folder, robot=run.robot, num_envs=int(envs),
            max_iterations=int(iterations), device="cpu", dr=run.dr, physics=args.physics,
            init_from=args.run, variant=run.variant, seed=args.seed,
            checkpoint_every=int(iterations), num_steps_per_env=run.num_steps_per_env,
            quiet=True, task=run.task,
            ppo=replace(run.ppo, learning_rate=float(lr), schedule=schedule)))  # fmt: skip
        r = {"recipe": name, "learning_rate": float(lr), "schedule": schedule,
             "num_envs": int(envs), "iterations": int(iterations),
             "train_s": time.perf_counter() - t0,
             args.physics: _evaluate(folder, args.physics, args.seed),
             "nominal": _evaluate(folder, None, args.seed)}  # fmt: skip
        out["recipes"].append(r)
        print(json.dumps(r), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
