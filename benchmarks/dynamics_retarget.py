"""Sampling-based dynamics retargeting on the real CMU clips: open-loop replays and compute.

For each clip (default: the CMU walk 35_01 and run 09_01 in ``../shared/data/cmu``, their
first ``--seconds`` after the T-pose frame), retargets kinematically to the G1 at 50 fps,
then refines with ``humimic.retarget.dynamics.refine`` and reports, from the same initial
state, the open-loop replay of the kinematic reference and of the result (time until fall,
MPJPE against the reference, foot skating, effort), the result's replays on perturbed physics,
whether the stored controls reproduce the stored states, and CPU seconds per second of motion.
The report's ``reference_flight`` says how ballistic the kinematic reference's flight is
(``humimic.retarget.dynamics.reference_flight``).

Usage: .venv/bin/python benchmarks/dynamics_retarget.py [--clips 35_01 09_01] [--seconds 3]
    [--samples 128] [--iterations 8] [--noise 0.15] [--threads N] [--robustness 8]
    [--ensemble E] [--seed S] [--set FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

from humimic.configs import DynamicsConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.errors import InputError
from humimic.retarget import Retargeter
from humimic.retarget.dynamics import check_replay, refine

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu"


def _overrides(parser: argparse.ArgumentParser, pairs: list[str]) -> dict[str, Any]:
    """``FIELD=VALUE`` pairs as DynamicsConfig keyword arguments, typed by the fields."""
    types = {f.name: f.type for f in dataclasses.fields(DynamicsConfig)}
    out: dict[str, Any] = {}
    for pair in pairs:
        name, _, value = pair.partition("=")
        if name not in types or not value:
            parser.error(f"--set {pair}: expected FIELD=VALUE with FIELD in {sorted(types)}")
        kind = {"int": int, "float": float}.get(str(types[name]), str)
        try:
            out[name] = kind(value)
        except ValueError:
            parser.error(f"--set {pair}: {name} takes a number")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clips", nargs="+", default=["35_01", "09_01"])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--samples", type=int, default=DynamicsConfig.samples)
    parser.add_argument("--iterations", type=int, default=DynamicsConfig.iterations)
    parser.add_argument("--noise", type=float, default=DynamicsConfig.noise)
    parser.add_argument("--ensemble", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--robustness", type=int, default=8)
    parser.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE",
                        help="other DynamicsConfig fields, e.g. joint_weight=0.3")  # fmt: skip
    args = parser.parse_args()
    cfg = DynamicsConfig(samples=args.samples, iterations=args.iterations, noise=args.noise,
                         ensemble=args.ensemble, seed=args.seed)  # fmt: skip
    cfg = dataclasses.replace(cfg, **_overrides(parser, args.set))  # --set wins over the flags.
    try:
        cfg.validate()
    except InputError as e:
        parser.error(str(e))
    rt = Retargeter("g1", "cmu", RetargetConfig(fps=50.0))
    rows = []
    t0 = time.perf_counter()
    for name in args.clips:
        path = CMU / f"{name}.bvh"
        if not path.is_file():
            raise SystemExit(f"{path}: not found (the CMU clips live in ../shared/data/cmu)")
        clip = load_clip(path)
        clip = clip.slice(1, min(clip.num_frames, 1 + int(args.seconds * clip.fps)))
        motion = rt.run(clip).motion
        refined, report = refine(motion, cfg, robustness=args.robustness, nthread=args.threads)
        row = {"clip": name, **report, "replay_check": check_replay(refined)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {
        "benchmark": "dynamics_retarget",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "config": cfg.__dict__,
        "clips": rows,
        "seconds": time.perf_counter() - t0,
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
