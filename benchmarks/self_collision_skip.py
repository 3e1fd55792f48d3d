"""Does skipping self-collision pairs that cannot have come within reach pay for itself?
Prints one JSON object.

For each robot and CMU clip: the configurations at which the kinematic IK evaluated its
self-collision limit (rows for a QP, or the frame's closing repair check) are recorded during
one default run, then replayed on two fresh limits in the same process, alternately,
``--repeats`` times each (best time kept): the limit as built (a pair is computed again only
when its geoms can have come within reach since it was last computed), and a baseline whose
distances are one plain ``mj_geomDistance`` call per candidate pair, as before that bound. Both
must give the same rows, bounds and repair figures. ``ratio`` < 1: the skipping is faster.
``ik_share`` is the replayed baseline's time as a fraction of the IK run's, for scale.

Usage: .venv/bin/python benchmarks/self_collision_skip.py [--robots g1 op3] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import types
from pathlib import Path

import mink
import mujoco
import numpy as np

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.retarget import Retargeter
from humimic.retarget.limits import SelfCollisionLimit
from humimic.robots.collision import self_collision_floors

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu"
CLIPS = ("35_01", "69_32", "87_03")


def plain_distances(
    self: SelfCollisionLimit, data: mujoco.MjData, idx: np.ndarray, distmax: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: every candidate pair computed, capped at its own distance."""
    cap = np.broadcast_to(np.asarray(distmax, dtype=float), idx.shape)
    dists, ends = np.empty(idx.size), np.zeros((idx.size, 6))
    fromto = np.zeros(6)
    for k, p in enumerate(idx.tolist()):
        g1, g2 = self._given[p]
        dists[k] = mujoco.mj_geomDistance(self.model, data, g1, g2, float(cap[k]), fromto)
        if dists[k] < cap[k]:
            ends[k] = fromto
    return dists, ends


def replay(limit: SelfCollisionLimit, conf: mink.Configuration, calls: list, margin: float):
    out = []
    for kind, q in calls:
        conf.update(q)
        if kind == "rows":
            c = limit.compute_qp_inequalities(conf, 1.0)
            out.append((c.G, c.h))
        else:
            out.append((limit.repair_slack(conf, margin), limit.counted_depth))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", nargs="+", default=["g1", "op3"])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats: at least 1")
    missing = [c for c in CLIPS if not (DATA / f"{c}.bvh").is_file()]
    if missing:
        raise SystemExit(f"clips not found in {DATA}: {missing}")
    cfg = retarget_default()
    result: dict = {
        "benchmark": "self_collision_skip",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "rows": [],
    }
    for robot in args.robots:
        rt = Retargeter(robot, "cmu", cfg)
        ik = rt.ik
        limit = ik.self_collision
        assert limit is not None
        for name in CLIPS:
            clip = load_clip(DATA / f"{name}.bvh").slice(1)
            calls: list = []
            rows, check = limit.compute_qp_inequalities, limit.repair_slack

            def record_rows(conf, dt, rows=rows, calls=calls):
                calls.append(("rows", conf.q.copy()))
                return rows(conf, dt)

            def record_check(conf, margin, check=check, calls=calls):
                calls.append(("check", conf.q.copy()))
                return check(conf, margin)

            limit.compute_qp_inequalities = record_rows  # type: ignore[method-assign]
            limit.repair_slack = record_check  # type: ignore[method-assign]
            ik_seconds = ik.run(clip).solve_seconds
            del limit.compute_qp_inequalities, limit.repair_slack
            pairs = np.array(limit._given)
            floors = self_collision_floors(ik.model, pairs, cfg.collision_margin)
            conf = mink.Configuration(ik.model)
            best = {"skipping": np.inf, "baseline": np.inf}
            for _ in range(args.repeats):
                answers = {}
                for label in best:
                    fresh = SelfCollisionLimit(
                        ik.model, pairs, floors, gain=cfg.collision_gain,
                        collision_detection_distance=cfg.collision_detection,
                    )  # fmt: skip
                    if label == "baseline":
                        fresh._distances = types.MethodType(plain_distances, fresh)  # type: ignore[method-assign]
                    t0 = time.perf_counter()
                    answers[label] = replay(fresh, conf, calls, cfg.collision_margin)
                    best[label] = min(best[label], time.perf_counter() - t0)
                for (a1, a2), (b1, b2) in zip(
                    answers["skipping"], answers["baseline"], strict=True
                ):
                    if not (np.array_equal(a1, b1) and np.array_equal(a2, b2)):
                        raise SystemExit(f"{robot} {name}: the two limits disagree")
            result["rows"].append({
                "robot": robot, "clip": name, "evaluations": len(calls),
                "skipping_s": best["skipping"], "baseline_s": best["baseline"],
                "ratio": best["skipping"] / best["baseline"],
                "ik_share": best["baseline"] / ik_seconds,
            })  # fmt: skip
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
