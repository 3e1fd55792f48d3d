"""Retargeting speed on the CMU walk, with the quality it reaches. Prints one JSON object.

Baseline in the same run: the same targets solved the textbook mink way (one
``mink.FrameTask`` per key point and frame, ``mink.solve_ik`` through qpsolvers/daqp, mink's
configuration and collision limits), with the same number of QP iterations per frame as
humimic used. The ratio isolates the cost of one IK iteration.

Where the time goes, in the same run: the IK's frames/s (best of ``--repeats``) at 50 fps output
with each limit switched off in turn (``ablation``), as ratios to the default.

Usage: .venv/bin/python benchmarks/retarget_speed.py [--clip PATH] [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import mink
import numpy as np

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.retarget import Retargeter
from humimic.retarget.kinematic import KEYPOINT_SITE_PREFIX
from humimic.retarget.limits import FloorLimit

DEFAULT_CLIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu" / "35_01.bvh"


def mink_baseline(rt: Retargeter, clip, iters_per_frame: int) -> float:
    """Frames per second of the plain-mink formulation of the same IK problem."""
    ik = rt.ik
    model = ik.model
    targets = ik.targets(clip)
    conf = mink.Configuration(model)
    kp_tasks = [
        mink.FrameTask(KEYPOINT_SITE_PREFIX + n, "site", position_cost=1.0, orientation_cost=0.0)
        for n in rt.map.keypoints
    ]
    bodies = [f.body for f in rt.map.frames.values()] + [f.body for f in rt.map.feet.values()]
    ori_tasks = [mink.FrameTask(b, "body", position_cost=0.0, orientation_cost=1.0) for b in bodies]
    posture = mink.PostureTask(model, cost=rt.map.posture_weight)
    posture.set_target(model.qpos0)
    limits = [
        mink.ConfigurationLimit(model),
        FloorLimit(model, [f.body for f in rt.map.feet.values()]),
        mink.CollisionAvoidanceLimit(
            model,
            [([int(a)], [int(b)]) for a, b in ik.self_collision_pairs],  # type: ignore[arg-type]
            minimum_distance_from_collisions=rt.cfg.collision_margin,
            collision_detection_distance=rt.cfg.collision_detection,
        ),
    ]
    q = model.qpos0.copy()
    q[:3] = targets.positions[0, 0]
    conf.update(q)
    T = targets.positions.shape[0]
    eye = mink.SO3.identity()
    zero = np.zeros(3)
    rots = np.concatenate([targets.frame_rots, targets.foot_rots], axis=1)
    t0 = time.perf_counter()
    for t in range(T):
        for k, task in enumerate(kp_tasks):
            task.set_target(mink.SE3.from_rotation_and_translation(eye, targets.positions[t, k]))
            task.set_position_cost(targets.position_weights[t, k])
        for b, task in enumerate(ori_tasks):
            task.set_target(
                mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(rots[t, b]), zero)
            )
        for _ in range(iters_per_frame):
            v = mink.solve_ik(
                conf, [*kp_tasks, *ori_tasks, posture], 1.0, "daqp", 1e-3, limits=limits
            )
            conf.integrate_inplace(v, 1.0)
    return T / (time.perf_counter() - t0)


def measure(rt: Retargeter, clip, repeats: int) -> dict:
    best = None
    for _ in range(repeats):
        out = rt.run(clip)
        if best is None or out.report["seconds"] < best.report["seconds"]:
            best = out
    assert best is not None
    r = best.report
    keys = (
        "frames", "fps", "source_frames", "seconds", "ik_seconds", "frames_per_second",
        "source_frames_per_second", "qp_iterations_per_frame", "keypoint_error_mm_mean",
        "keypoint_error_mm_p95", "foot_skating_mm_per_s", "max_ground_penetration_mm",
        "median_lowest_foot_mm", "joint_limit_violations", "self_collision_frames",
        "max_self_penetration_mm", "mean_joint_jerk",
    )  # fmt: skip
    return {k: r[k] for k in keys}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clip", type=Path, default=DEFAULT_CLIP)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if not args.clip.is_file():
        raise SystemExit(f"clip not found: {args.clip} (the CMU walk lives in ../shared/data/cmu)")
    clip = load_clip(args.clip)
    if clip.skeleton == "cmu":
        clip = clip.slice(1)
    result: dict = {
        "benchmark": "retarget_speed",
        "clip": args.clip.name,
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
        },
    }
    for fps in (50.0, 120.0):
        cfg = replace(retarget_default(), fps=fps)
        t0 = time.perf_counter()
        rt = Retargeter("g1", clip.skeleton, cfg)
        setup = time.perf_counter() - t0
        ours = measure(rt, clip, args.repeats)
        iters = round(ours["qp_iterations_per_frame"])
        base_fps = max(mink_baseline(rt, clip, iters) for _ in range(args.repeats))
        ik_fps = ours["frames"] / ours["ik_seconds"]
        result[f"output_{fps:g}fps"] = {
            **ours,
            "setup_seconds": setup,
            "ik_frames_per_second": ik_fps,
            "baseline_mink_frame_tasks_ik_frames_per_second": base_fps,
            "ik_speedup_vs_baseline": ik_fps / base_fps,
        }
    result["ablation"] = ablation(clip, args.repeats)
    print(json.dumps(result, indent=2))


def ablation(clip, repeats: int) -> dict:
    """IK frames/s with each limit off in turn (not a recommended setting: a cost split)."""
    variants = {
        "default": {},
        "no_self_collision": {"self_collision": False},
        "no_planted_feet": {"hold_planted_feet": False},
        "no_floor": {"floor_limit": False},
    }
    out: dict = {}
    for name, change in variants.items():
        rt = Retargeter("g1", clip.skeleton, replace(retarget_default(), **change))
        best = min(rt.run(clip).report["ik_seconds"] for _ in range(repeats))
        frames = rt.run(clip).report["frames"]
        out[name] = {"ik_frames_per_second": frames / best}
    base = out["default"]["ik_frames_per_second"]
    for row in out.values():
        row["ratio_to_default"] = row["ik_frames_per_second"] / base
    return out


if __name__ == "__main__":
    main()
