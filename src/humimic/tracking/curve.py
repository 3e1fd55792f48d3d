"""The learning curve of a run: its training progress and its checkpoints evaluated after the
fact, against wall time (an evaluation inside training would take from its budget)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from humimic.errors import InputError


def progress_rows(run: Path) -> list[dict[str, float]]:
    """The rows of a run's progress.csv as numbers (empty cells: NaN)."""
    path = run / "progress.csv"
    if not path.is_file():
        raise InputError(f"{run}: the run has no progress.csv")
    with open(path, newline="") as f:
        return [
            {k: float(v) if v not in ("", None) else math.nan for k, v in row.items()}
            for row in csv.DictReader(f)
        ]


def evaluation_curve(
    run: Path,
    *,
    episodes: int = 8,
    dr: str = "default",
    points: int = 12,
    device: str = "cpu",
    seed: int = 1,
) -> list[dict[str, float]]:
    """Evaluate up to ``points`` of a run's checkpoints, spread evenly over its iterations
    (the newest always), each on ``episodes`` episodes from the first frame (``humimic eval``
    under ``dr``; the open loop is not rerun).

    Returns:
        One row per checkpoint: ``iteration``, ``seconds`` (the run's wall time when it was
        written, from progress.csv), ``success_rate``, ``mean_steps``, ``mpjpe_global_mm``,
        ``mpjpe_root_mm``.
    """
    from humimic.configs.jobs import EvalSettings
    from humimic.tracking.evaluate import run_evaluation
    from humimic.tracking.runs import checkpoint_files

    files = checkpoint_files(run)
    if not files:
        raise InputError(f"{run}: the run has no checkpoint yet")
    step = max(1, math.ceil(len(files) / points))
    chosen = files[::-1][::step][::-1]
    seconds = {int(r["iteration"]): r["seconds"] for r in progress_rows(run)}
    out = []
    for path in chosen:
        s = EvalSettings(run=run, episodes=episodes, dr=dr, checkpoint=path, device=device,
                         seed=seed)  # fmt: skip
        policy = run_evaluation(s, open_loop=False, protocols=False).results["policy"]
        it = int(path.stem.split("_")[1])
        out.append({"iteration": float(it), "seconds": seconds.get(it, math.nan),
                    **{k: float(policy[k]) for k in ("success_rate", "mean_steps",
                                                     "mpjpe_global_mm", "mpjpe_root_mm")}})  # fmt: skip
    return out


def plot_learning_curve(
    progress: list[dict[str, float]], evals: list[dict[str, float]], path: Path, title: str
) -> None:
    """A PNG of the training episode length and reward, and of the evaluations' success rate
    and global MPJPE, against wall time [min]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    minutes = [r["seconds"] / 60.0 for r in progress]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    a, b, c = axes
    a.plot(minutes, [r["mean_episode_length"] for r in progress])
    a.set_ylabel("training episode length [steps]")
    b.plot(minutes, [r["mean_reward"] for r in progress])
    b.set_ylabel("training episode reward")
    em = [r["seconds"] / 60.0 for r in evals]
    c.plot(em, [r["mpjpe_global_mm"] for r in evals], "o-", label="global MPJPE [mm]")
    c.plot(em, [r["mpjpe_root_mm"] for r in evals], "s-", label="root-relative MPJPE [mm]")
    c.set_ylabel("evaluation MPJPE [mm]")
    c2 = c.twinx()
    c2.plot(em, [100.0 * r["success_rate"] for r in evals], "k^--", label="success [%]")
    c2.set_ylabel("evaluation success [%]")
    c2.set_ylim(-5, 105)
    c.legend(loc="upper left", fontsize=8)
    c2.legend(loc="upper right", fontsize=8)
    for ax in axes:
        ax.set_xlabel("wall time [min]")
    fig.suptitle(title)
    fig.tight_layout()
    from humimic.io import atomic_write

    with atomic_write(path) as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)


def plot_failures(
    clips: dict[str, tuple[int, list[int], int]], step_dt: float, path: Path, title: str
) -> None:
    """A PNG of where in each clip the policy's episodes fail: per clip (name -> its frames,
    the steps each failed episode lived, its episodes), the share of episodes still tracking
    against the time into the clip [s], a tick at each failure, the clip's end marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.2))
    for name, (frames, fails, episodes) in clips.items():
        end = (frames - 1) * step_dt
        times = [0.0] + [s * step_dt for s in fails] + [end]
        alive = [100.0] + [100.0 * (1 - (i + 1) / episodes) for i in range(len(fails))]
        alive.append(alive[-1])
        (line,) = ax.step(times, alive, where="post",
                          label=f"{name}: {len(fails)} of {episodes} fail")  # fmt: skip
        ax.plot([s * step_dt for s in fails], [-3.0] * len(fails), "|",
                color=line.get_color(), markersize=8)  # fmt: skip
        ax.plot([end], [alive[-1]], "o", color=line.get_color())
    ax.set_xlabel("time into the clip [s] (dot: the clip's end)")
    ax.set_ylabel("episodes still tracking [%]")
    ax.set_ylim(-6, 103)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title(title)
    fig.tight_layout()
    from humimic.io import atomic_write

    with atomic_write(path) as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)


def curve_summary(
    evals: list[dict[str, float]], progress: list[dict[str, float]]
) -> dict[str, Any]:
    """When the evaluated checkpoints first completed the clip: on some episode
    (``first_full_clip``) and on every one (``first_all_full_clip``), each as its iteration
    and wall time (None if none did); and the last row."""

    def first(ok: Any) -> dict[str, float] | None:
        row = next((r for r in evals if ok(r["success_rate"])), None)
        return None if row is None else {"iteration": row["iteration"], "seconds": row["seconds"]}

    return {
        "first_full_clip": first(lambda s: s > 0.0),
        "first_all_full_clip": first(lambda s: s >= 1.0),
        "last": evals[-1] if evals else None,
        "iterations": progress[-1]["iteration"] if progress else 0,
    }


__all__ = [
    "curve_summary",
    "evaluation_curve",
    "plot_failures",
    "plot_learning_curve",
    "progress_rows",
]
