"""Training variants on one motion: nominal, DR-range and unseen physics (issue 6's table).

Trains each variant (``humimic train --variant``) for the same wall-time budget (or, with
``--iterations``, to the same number of PPO iterations, resuming runs that exist), distills the
teacher into a student (``humimic distill``), then evaluates every policy on the same episodes
under three kinds of physics: the nominal robot (DR ``none``), robots drawn from the training
ranges (DR ``default``, with observation noise and pushes), and robots training never sampled
(the shipped physics files, ``--unseen``). The open-loop baseline (the reference's joint
targets, no policy) runs on the same episodes. Runs that exist in ``--out`` are reused, so an
interrupted comparison continues.

Note: the teacher's privileged input ``e`` holds the DR parameters of each env; on a physics
file with DR ``none`` it is the nominal value, not the file's: a teacher cannot see an unseen
robot's physics either.

Usage: .venv/bin/python benchmarks/variant_comparison.py --motion walk.npz --out runs/compare
    [--minutes 7 | --iterations 1000] [--num-envs 128] [--variants robust asymmetric teacher beyondmimic]
    [--distill-minutes 4] [--episodes 16] [--unseen backpack worn_knees]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from humimic.cli.main import main as humimic
from humimic.configs.jobs import EvalSettings
from humimic.tracking.evaluate import evaluate

_KEYS = ("success_rate", "mean_steps", "mpjpe_global_mm", "joint_error_rad")


def _train(args: argparse.Namespace, variant: str) -> Path:
    """Train a variant for ``--minutes`` (a new run only), or to ``--iterations`` PPO
    iterations (new or resumed: the same number of updates for every variant, whatever else
    the machine does meanwhile)."""
    run = args.out / variant
    exists = (run / "config.yaml").exists()
    if args.iterations is not None:
        budget = ["--max-iterations", str(args.iterations)] + (["--resume"] if exists else [])
    elif not exists:
        budget = ["--max-iterations", "1000000", "--max-minutes", str(args.minutes)]
    else:
        return run
    code = humimic(["train", "--motion", str(args.motion), "--out", str(run),
                    "--variant", variant, "--num-envs", str(args.num_envs), *budget,
                    "--checkpoint-every", "100", "--seed", str(args.seed), "--quiet"])  # fmt: skip
    if code != 0:
        raise SystemExit(f"training {variant} failed ({code})")
    return run


def _checkpoint(args: argparse.Namespace, run: Path) -> Path | None:
    """With ``--iterations``, the checkpoint at that many iterations (a run that went further
    is compared at the same point); else the newest."""
    if args.iterations is None or run.name == "student":
        return None
    path = run / "checkpoints" / f"model_{args.iterations:06d}.pt"
    if not path.is_file():
        raise SystemExit(f"{run}: no checkpoint at {args.iterations} iterations ({path})")
    return path


def _distill(args: argparse.Namespace, teacher: Path) -> Path:
    run = args.out / "student"
    if not (run / "config.yaml").exists():
        code = humimic(["distill", "--teacher", str(teacher), "--out", str(run),
                        "--student", args.student, "--num-envs", str(args.num_envs),
                        "--max-iterations", "1000000", "--max-minutes", str(args.distill_minutes),
                        "--checkpoint-every", "100", "--seed", str(args.seed), "--quiet"])  # fmt: skip
        if code != 0:
            raise SystemExit(f"distillation failed ({code})")
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--motion", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=7.0)
    parser.add_argument("--iterations", type=int, default=None,
                        help="train (or resume) every variant to this many PPO iterations "
                        "instead of --minutes")  # fmt: skip
    parser.add_argument("--num-envs", type=int, default=128)
    parser.add_argument("--variants", nargs="+",
                        default=["robust", "asymmetric", "teacher", "beyondmimic"])  # fmt: skip
    parser.add_argument("--student", default="mlp-history")
    parser.add_argument("--distill-minutes", type=float, default=4.0)
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--unseen", nargs="+", default=["backpack", "worn_knees"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    t0 = time.perf_counter()
    policies = {v: _train(args, v) for v in args.variants}
    if "teacher" in policies and args.student:
        policies["student"] = _distill(args, policies["teacher"])
    conditions: list[tuple[str, str, str | None]] = [("nominal", "none", None),
                                                     ("dr", "default", None)]  # fmt: skip
    conditions += [(f"unseen:{u}", "none", u) for u in args.unseen]
    rows = []
    for name, run in policies.items():
        for cond, dr, physics in conditions:
            r = evaluate(EvalSettings(run=run, episodes=args.episodes, dr=dr, physics=physics,
                                      seed=args.seed + 1, checkpoint=_checkpoint(args, run)))  # fmt: skip
            rows.append({"policy": name, "physics": cond, "iterations": r["iterations"],
                         **{k: r["policy"][k] for k in _KEYS}})  # fmt: skip
            if name == next(iter(policies)):
                rows.append({"policy": "open loop", "physics": cond,
                             **{k: r["open_loop"][k] for k in _KEYS}})  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    out = {
        "benchmark": "variant_comparison",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "motion": str(args.motion),
        "minutes_per_variant": None if args.iterations is not None else args.minutes,
        "iterations_per_variant": args.iterations,
        "distill_minutes": args.distill_minutes,
        "num_envs": args.num_envs,
        "episodes": args.episodes,
        "rows": rows,
        "seconds": time.perf_counter() - t0,
    }
    (args.out / "comparison.json").write_text(json.dumps(out, indent=2) + "\n")
    lines = ["Cells: mean steps survived / success / global MPJPE mm / joint error rad", "",
             "| policy | iterations | " + " | ".join(c for c, _, _ in conditions) + " |",
             "|---|---|" + "---|" * len(conditions)]  # fmt: skip
    for name in [*policies, "open loop"]:
        cells = []
        its = ""
        for cond, _, _ in conditions:
            row = next(r for r in rows if r["policy"] == name and r["physics"] == cond)
            its = str(row.get("iterations", "-"))
            cells.append(f"{row['mean_steps']:.1f} / {100 * row['success_rate']:.0f}% / "
                         f"{row['mpjpe_global_mm']:.0f} / {row['joint_error_rad']:.3f}")  # fmt: skip
        lines.append(f"| {name} | {its} | " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n"
    (args.out / "comparison.md").write_text(table)
    print(table)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
