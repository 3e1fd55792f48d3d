"""`humimic sysid diagnose` on 40 s G1 logs with one injected (undeclared) effect each.
Prints one JSON object: per case, the truth, what was found, held-out error before/after, time.

Usage: .venv/bin/python benchmarks/sysid_diagnose.py [--duration 40] [--seed 7]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

from humimic.real2sim import (
    LogSettings,
    fixed_base_spec,
    kstep_error,
    parse_injection,
    simulate_log,
)
from humimic.real2sim.diagnose import FIT_END, diagnose_log
from humimic.robots import get_robot

CASES = [
    "",
    "coulomb_friction:right_knee_joint=2.5",
    "viscous_damping:left_hip_pitch_joint=1.5",
    "gain_mismatch:left_knee_joint=0.75",
    "armature:right_hip_roll_joint=0.08",
    "coulomb_friction:left_hip_roll_joint=2.0;viscous_damping:right_knee_joint=1.5",
    "delay:left_knee_joint=0.02",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    robot = get_robot("g1")
    out = {"benchmark": "sysid_diagnose", "machine": {"cpu": platform.machine(),
           "cores": os.cpu_count()}, "duration_s": args.duration, "cases": []}  # fmt: skip
    for case in CASES:
        injections = [parse_injection(x) for x in case.split(";") if x]
        log = simulate_log(robot, injections, LogSettings(duration=args.duration, seed=args.seed))
        model = fixed_base_spec(robot, log.base_pose).compile()
        t0 = time.perf_counter()
        before = kstep_error(model, log, span=(FIT_END, 1.0)).kstep_rmse_rad
        d = diagnose_log(model, log)
        after = kstep_error(model, log, span=(FIT_END, 1.0), gain_scale=d.gain_scale).kstep_rmse_rad
        out["cases"].append({
            "injected": [{"effect": i.effect, "joint": i.targets[0], "value": i.value}
                         for i in injections],
            "claimed": [{"effect": f.effect, "joint": f.joint, "value": f.value,
                         "confidence": f.confidence} for f in d.claimed],
            "heldout_kstep_rmse_mrad_before": before * 1e3,
            "heldout_kstep_rmse_mrad_after": after * 1e3,
            "seconds": time.perf_counter() - t0,
        })  # fmt: skip
        print(json.dumps(out["cases"][-1]), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
