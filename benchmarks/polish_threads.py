"""The iLQR polish of dynamics retargeting with its linearization on one thread against every
core, in the same run: refine the same clip alternately both ways, report the wall times, their
ratio and whether the refined motions are identical (they must be: the threads split the
control steps, not the arithmetic).

Usage: .venv/bin/python benchmarks/polish_threads.py [--clip 35_01] [--seconds 3] [--repeats 2]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from humimic.configs import DynamicsConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.retarget import Retargeter
from humimic.retarget.dynamics import ilqr as ilqr_module
from humimic.retarget.dynamics import refine
from humimic.retarget.dynamics import sampler as sampler_module

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clip", default="35_01")
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    path = CMU / f"{args.clip}.bvh"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (the shared CMU data, ../shared/data/cmu)")
    clip = load_clip(path)
    clip = clip.slice(1, min(clip.num_frames, 1 + int(args.seconds * clip.fps)))
    motion = Retargeter("g1", "cmu", RetargetConfig(fps=50.0)).run(clip).motion
    serial = functools.partial(ilqr_module.ilqr, threads=1)
    times: dict[str, list[float]] = {"one_thread": [], "all_cores": []}
    outputs: dict[str, np.ndarray] = {}
    for _ in range(args.repeats):
        for name, fn in (("one_thread", serial), ("all_cores", ilqr_module.ilqr)):
            sampler_module.ilqr = fn  # The polish's linearization threads; all else the same.
            t0 = time.perf_counter()
            refined, _ = refine(motion, DynamicsConfig(), robustness=0)
            times[name].append(time.perf_counter() - t0)
            outputs[name] = refined.qpos
    sampler_module.ilqr = ilqr_module.ilqr
    best = {k: min(v) for k, v in times.items()}
    print(json.dumps({
        "benchmark": "polish_threads", "clip": args.clip, "seconds_of_motion": args.seconds,
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "refine_wall_s": times, "best_s": best,
        "speedup": best["one_thread"] / best["all_cores"],
        "identical": bool(np.array_equal(outputs["one_thread"], outputs["all_cores"])),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
