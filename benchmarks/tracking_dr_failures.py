"""Which randomized physics make a tracking policy fall: ``humimic eval``'s episodes under a
DR profile, each with the draw it ran under, and the failure rate by quantity.

For every quantity of the DR draw (:func:`humimic.sim.randomization.param_layout`) the
episodes are split at the median of that quantity's normalized value (its mean over joints or
bodies for the per-joint and per-body ones): the failure rates of the low and the high half,
and the standardized difference of the quantity between failed and completed episodes. The
integer action delay is split by value, and friction also by quarter. Prints JSON.

Usage (1-2 minutes for 256 episodes of a short clip on 2 cores):
    .venv/bin/python benchmarks/tracking_dr_failures.py RUN --episodes 256 [--dr default]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from humimic.configs.jobs import EvalSettings
from humimic.errors import HumimicError


def _rate(failed: np.ndarray) -> dict[str, float | int | None]:
    """Failure rate of a group of episodes (null for an empty group)."""
    n = int(failed.size)
    return {"episodes": n, "failure_rate": float(failed.mean()) if n else None}


def analyze(e: np.ndarray, failed: np.ndarray, layout: dict[str, slice]) -> dict:
    """The failure rates by quantity (see the module docstring)."""
    out: dict[str, dict] = {}
    for name, sl in layout.items():
        v = e[:, sl].mean(axis=1)
        row: dict = {}
        if name == "action_delay" or np.unique(v).size <= 4:
            row["by_value"] = {f"{x:+.2f}": _rate(failed[v == x]) for x in np.unique(v)}
        else:
            mid = float(np.median(v))
            row["low_half"], row["high_half"] = _rate(failed[v <= mid]), _rate(failed[v > mid])
        if name == "friction":
            q = np.quantile(v, [0.25, 0.5, 0.75])
            bins = np.digitize(v, q)
            row["by_quarter"] = [_rate(failed[bins == b]) for b in range(4)]
        sd = float(v.std())
        both = failed.any() and (~failed).any()
        row["difference_in_sd"] = (
            float((v[failed].mean() - v[~failed].mean()) / sd) if both and sd > 0 else None
        )
        out[name] = row
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--dr", default="default")
    parser.add_argument("--seed", type=int, default=1)  # humimic eval's default
    args = parser.parse_args()
    from humimic.tracking.evaluate import run_evaluation

    try:
        ev = run_evaluation(
            EvalSettings(run=args.run, episodes=args.episodes, dr=args.dr, seed=args.seed),
            open_loop=False,
        )
    except HumimicError as err:
        print(f"tracking_dr_failures: error: {err}", file=sys.stderr)
        return 2
    e, failed = ev.episodes["physics_e"], ev.episodes["failed"]
    policy = ev.results["policy"]
    print(json.dumps({
        "benchmark": "tracking_dr_failures", "run": str(args.run), "dr": args.dr,
        "episodes": int(failed.size), "failures": int(failed.sum()),
        "success_rate": policy["success_rate"],
        "by_quantity": analyze(e, failed, ev.param_layout) if failed.size else None,
    }, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
