"""Tracking recipes side by side at equal wall time: each trains with ``humimic train`` on the
same kinematic motion for the same minutes, then its checkpoints are evaluated (the learning
curve) and its last one on 32 episodes under nominal physics, DR ``default`` and the shipped
unseen robots. Prints JSON (one object per recipe, then a summary).

Usage (the runs take ``--minutes`` each, one after the other: nothing else should load the
machine meanwhile):
  .venv/bin/humimic retarget ../shared/data/cmu/35_01.bvh --out runs/walk.npz
  .venv/bin/python benchmarks/tracking_recipes.py --motion runs/walk.npz --out runs/recipes \\
      --minutes 30 --recipes default beyondmimic reference feedforward-std1
  # The default's run distilled into a student without the LQR (another 30 minutes):
  .venv/bin/python benchmarks/tracking_recipes.py --motion runs/walk.npz --out runs/recipes \\
      --minutes 30 --recipes dagger-ff
  # PPO under DR from that student (another 30 minutes):
  .venv/bin/python benchmarks/tracking_recipes.py --motion runs/walk.npz --out runs/recipes \\
      --minutes 30 --recipes dagger-ff-ppo
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

MJLAB_ANCHOR = ["--task.reward-stds", "anchor_pos", "0.3", "--task.reward-weights", "anchor_pos",
                "0.5"]  # fmt: skip
"""mjlab's anchor-position reward (humimic's default holds the world position tighter)."""

BEYONDMIMIC_PPO = ["--ppo.actor-hidden-dims", "512", "256", "128", "--ppo.critic-hidden-dims",
                   "512", "256", "128", "--ppo.num-learning-epochs", "5"]  # fmt: skip
"""BeyondMimic's networks and epochs (humimic's default halves the widths, 3 epochs)."""

RECIPES: dict[str, list[str]] = {
    "default": [],
    "beyondmimic": ["--task.action-base", "default", "--ppo.init-std", "1.0",
                    "--ppo.actor-output-gain", "1.0", *MJLAB_ANCHOR, *BEYONDMIMIC_PPO],
    "feedback-root10": ["--task.feedback-root-cost", "10", *MJLAB_ANCHOR],
    "wide-dr": ["--dr", "wide"],
    "kl0.1": ["--ppo.desired-kl", "0.1"],
    # A third of the default's noise; the desired KL scaled by (0.3/0.1)^2 so that the
    # adaptive rate lets the mean move as far per update as the default's does.
    "low-noise": ["--ppo.init-std", "0.1", "--ppo.desired-kl", "0.09"],
    # A third of the default's noise that stays low: no entropy bonus pushing the std up.
    "std0.1-ent0": ["--ppo.init-std", "0.1", "--ppo.entropy-coef", "0"],
    "delay1": ["--task.feedback-delay", "1"],
    # DR `wide` (0-2 steps of delay, friction from 0.2, a heavier torso) with the LQR base
    # designed for the middle of its delays: a 40 ms delay defeats the undelayed design
    # whatever the residual learns (2026-12-02), and the design for one step held 40 and
    # 60 ms alone.
    "wide-delay1": ["--dr", "wide", "--task.feedback-delay", "1"],
    # The actor also reads its proprioceptive history: under DR `default` the policy fell
    # mostly on draws with one step of action delay and low friction, which the history
    # may reveal and the current observation does not.
    "asymmetric": ["--variant", "asymmetric"],
    # A quarter of the resets replay the physics draw of a recently failed episode (the
    # failures concentrate on low friction with a delayed command).
    "dr-replay": ["--task.dr-replay", "0.25"],
    # The default before 2026-12-03: BeyondMimic's networks and epochs (the update took ~40 %
    # of an iteration on the CPU).
    "wide-ppo": BEYONDMIMIC_PPO,
    "reference": ["--task.action-base", "reference"],
    "feedforward": ["--task.action-base", "feedforward"],
    "feedforward-std1": ["--task.action-base", "feedforward", "--ppo.init-std", "1.0",
                         "--ppo.actor-output-gain", "1.0"],
    "feedforward-64envs": ["--task.action-base", "feedforward", "--num-envs", "64"],
    "feedforward-256envs": ["--task.action-base", "feedforward", "--num-envs", "256"],
    # Not a candidate: a feasibility check. Trained on the shipped `backpack` robot itself,
    # nothing drawn around it (no DR): can the recipe perform the clip on that robot at all
    # in the budget?
    "oracle-backpack": ["--physics", "backpack", "--dr", "none"],
}  # fmt: skip
"""Recipe name -> the flags it adds to ``humimic train --motion M --out RUN --max-minutes X``
(``default``: none, the command a user runs)."""

DISTILLS: dict[str, tuple[str, list[str]]] = {
    "dagger-ff": ("default", ["--student-base", "feedforward"]),
    "dagger-ff-kl0.1": ("kl0.1", ["--student-base", "feedforward"]),
}
"""Recipe name -> (the recipe whose run teaches it, the flags it adds to ``humimic distill
--teacher OUT/TEACHER --out RUN --max-minutes X``): a student that acts around the stored
targets without the LQR. Its teacher's run must be in ``--out`` (listed before it, or there
from an earlier invocation); the minutes are the student's own."""

FINETUNES: dict[str, tuple[str, list[str]]] = {
    "dagger-ff-ppo": ("dagger-ff", ["--variant", "asymmetric", "--task.action-base",
                                    "feedforward", "--ppo.critic-warmup-iterations", "20",
                                    "--ppo.init-std", "0.3", "--ppo.learning-rate", "1e-4"]),
}  # fmt: skip
"""Recipe name -> (the student recipe it starts from, the flags it adds to ``humimic train
--motion STUDENT'S MOTION --init-from OUT/STUDENT --out RUN --max-minutes X``): PPO under DR
from a distilled student (its actor; a fresh critic trained alone for the first iterations).
The student's run must be in ``--out``; the minutes are the fine-tuning's own."""

UNSEEN = Path(__file__).parent / "physics"
"""Unseen robots of the same kind as the shipped ones, outside DR ``default`` (issue 25)."""

PHYSICS = {"nominal": ["--dr", "none"], "dr_default": ["--dr", "default"],
           "backpack": ["--dr", "none", "--physics", "backpack"],
           "worn_knees": ["--dr", "none", "--physics", "worn_knees"],
           **{p.stem: ["--dr", "none", "--physics", str(p)]
              for p in sorted(UNSEEN.glob("*.yaml"))}}  # fmt: skip
"""Evaluation physics -> ``humimic eval`` flags."""

METRICS = ("success_rate", "mean_steps", "mpjpe_global_mm", "mpjpe_root_mm", "joint_error_rad")


def _humimic(*args: str) -> None:
    cmd = [sys.executable, "-m", "humimic.cli.main", *args]
    done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout[-3000:]}")


def _trained_on(run: Path, progress: list[dict]) -> str:
    """Where and how long a run trained, from its own files (a reused run may come from a GPU
    machine)."""
    from humimic.tracking.runs import read_run_settings

    s = read_run_settings(run)
    where = (f"{s.device}, {s.backend} backend, {s.num_envs} envs" if s.device != "cpu"
             else f"{os.cpu_count()} CPU cores")  # fmt: skip
    return f"{progress[-1]['seconds'] / 60:.1f} min on {where}"


def run_recipe(name: str, args: argparse.Namespace) -> dict:
    """Train one recipe for the budget, evaluate its curve and its last checkpoint."""
    from humimic.tracking.curve import (
        curve_summary,
        evaluation_curve,
        plot_learning_curve,
        progress_rows,
    )
    from humimic.tracking.runs import read_run_settings

    run = args.out / name
    t0 = time.perf_counter()
    reused = args.reuse and (run / "config.yaml").is_file()
    if not reused and name in DISTILLS:
        teacher, flags = DISTILLS[name]
        if not (args.out / teacher / "config.yaml").is_file():
            raise SystemExit(f"{name}: its teacher's run {args.out / teacher} is missing")
        _humimic("distill", "--teacher", str(args.out / teacher), "--out", str(run),
                 "--max-minutes", str(args.minutes), "--max-iterations", "1000000", "--seed",
                 str(args.seed), "--quiet", *flags)  # fmt: skip
    elif not reused and name in FINETUNES:
        student, flags = FINETUNES[name]
        if not (args.out / student / "config.yaml").is_file():
            raise SystemExit(f"{name}: its student's run {args.out / student} is missing")
        motion = str(read_run_settings(args.out / student).motion)
        _humimic("train", "--motion", motion, "--init-from", str(args.out / student), "--out",
                 str(run), "--max-minutes", str(args.minutes), "--seed", str(args.seed),
                 "--quiet", *flags)  # fmt: skip
    elif not reused:
        _humimic("train", "--motion", str(args.motion), "--out", str(run), "--max-minutes",
                 str(args.minutes), "--seed", str(args.seed), "--quiet", *args.train_flags,
                 *RECIPES[name])  # fmt: skip
    train_wall = time.perf_counter() - t0
    progress = progress_rows(run)
    if args.train_only:
        return {"recipe": name, "train_wall_s": train_wall, **progress[-1]}
    curve = evaluation_curve(run, episodes=args.curve_episodes, dr="default",
                             points=args.curve_points)  # fmt: skip
    plot_learning_curve(
        progress,
        curve,
        run / "learning_curve.png",
        f"{name}: {args.motion.name}, {_trained_on(run, progress)}",
    )
    flags = RECIPES[name] if name in RECIPES else {**DISTILLS, **FINETUNES}[name][1]
    result: dict = {"recipe": name, "flags": flags, "train_wall_s": train_wall,
                    "train_seconds": progress[-1]["seconds"], "env_steps": progress[-1]["env_steps"],
                    "curve": curve, **curve_summary(curve, progress)}  # fmt: skip
    for label in args.physics:
        flags = PHYSICS[label]
        out = run / f"eval_{label}.json"
        _humimic("eval", str(run), "--episodes", str(args.episodes), "--out", str(out), *flags)
        ev = json.loads(out.read_text())
        result[label] = {k: {m: ev[k][m] for m in METRICS} for k in ("policy", "open_loop")}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--motion", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--recipes", nargs="+", default=["default", "beyondmimic"],
                        choices=sorted([*RECIPES, *DISTILLS, *FINETUNES]))  # fmt: skip
    parser.add_argument("--physics", nargs="+", default=list(PHYSICS), choices=list(PHYSICS),
                        help="the physics to evaluate the last checkpoint on (default: all)")  # fmt: skip
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--curve-episodes", type=int, default=8)
    parser.add_argument("--curve-points", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-flags", type=shlex.split, default=[],
                        help="flags for every recipe's `humimic train`, one string: "
                             "--train-flags='--backend warp --device cuda'")  # fmt: skip
    parser.add_argument("--train-only", action="store_true",
                        help="train, evaluate nothing (on a GPU machine; evaluate here with --reuse)")  # fmt: skip
    parser.add_argument("--reuse", action="store_true",
                        help="evaluate a recipe's run folder that exists instead of training")  # fmt: skip
    args = parser.parse_args()
    machine = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()}
    rows = []
    for name in args.recipes:
        row = run_recipe(name, args)
        row["machine"] = machine
        print(json.dumps(row), flush=True)
        rows.append(row)
    if args.train_only:
        return
    summary = {
        r["recipe"]: {
            "dr_default": r["dr_default"]["policy"],
            "first_full_clip": r["first_full_clip"],
        }
        for r in rows
    }
    print(json.dumps({"benchmark": "tracking_recipes", "motion": str(args.motion),
                      "minutes": args.minutes, "machine": machine, "summary": summary}))  # fmt: skip


if __name__ == "__main__":
    main()
