"""Deployment logs (a G1 standing on the floor, swaying under its balance controller): the
nominal model's k-step prediction error, with the base state rebuilt from the log
(humimic.real2sim.floating.estimate_base) with and without motion capture, at the step
``humimic sysid diagnose`` predicts at (``prediction_step``), on a clean log and on logs with undeclared effects;
with ``--diagnose``, the diagnosis search (the Python API ``humimic sysid diagnose`` runs) on
each. Prints one JSON line per case and a summary object.

Usage: .venv/bin/python benchmarks/sysid_deployment.py [--duration 12] [--seed 1] [--diagnose]
       [--only knee]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from humimic.real2sim import LogSettings, diagnose_log, simulate_log
from humimic.real2sim.correction import Correction
from humimic.real2sim.floating import prediction_step
from humimic.real2sim.residual import Predictor
from humimic.robots import get_robot
from humimic.sim.effects import parse_injection
from humimic.sim.models import floating_prediction_spec

CASES = {
    "clean": [],
    "payload 5 kg on the torso": ["payload_mass:torso_link=5.0"],
    "knee drives at 70 % gain": ["gain_mismatch:left_knee_joint,right_knee_joint=0.7"],
    "left ankle pitch friction 3 N m": ["coulomb_friction:left_ankle_pitch_joint=3.0"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--only", default="", help="run the cases whose name contains this")
    args = ap.parse_args()
    robot = get_robot("g1")
    model = floating_prediction_spec(robot).compile()
    rows = []
    for name, texts in CASES.items():
        if args.only not in name:
            continue
        injections = [parse_injection(t) for t in texts]
        for mocap in (True, False):
            t0 = time.perf_counter()
            settings = LogSettings(duration=args.duration, base="floating", mocap=mocap,
                                   seed=args.seed)  # fmt: skip
            log = simulate_log(robot, injections, settings)
            model.opt.timestep = prediction_step(log)  # As `humimic sysid diagnose` steps.
            t1 = time.perf_counter()
            p = Predictor(model, log, horizon=0.5)
            err = p.error(Correction.of(model))
            t2 = time.perf_counter()
            worst = np.argsort(-err.per_joint)[:3]
            row = {
                "case": name, "truth": texts, "mocap": mocap,
                "base_estimate": p.base.source if p.base else None,
                "kstep_rmse_mrad": round(err.kstep_rmse_rad * 1e3, 3),
                "worst_joints_mrad": {log.joint_names[j]: round(float(err.per_joint[j]) * 1e3, 2)
                                      for j in worst},
                "simulate_s": round(t1 - t0, 2), "predict_s": round(t2 - t1, 2),
            }  # fmt: skip
            if args.diagnose and mocap:
                d = diagnose_log(model, log)
                held = Predictor(model, log, horizon=0.5, span=(0.7, 1.0))
                assert d.correction is not None
                row["diagnose_s"] = round(time.perf_counter() - t2, 1)
                row["claimed"] = [
                    f"{f.effect} {f.target} {f.value:.4g} ({f.confidence:.2f})"
                    for f in d.findings if f.confidence >= 0.5
                ]  # fmt: skip
                row["best_unclaimed"] = [
                    f"{f.effect} {f.target} {f.value:.4g} ({f.confidence:.2f})"
                    for f in d.findings if f.confidence < 0.5
                ][:2]  # fmt: skip
                row["held_out_mrad"] = [
                    round(held.error(c).kstep_rmse_rad * 1e3, 3)
                    for c in (Correction.of(model), d.correction)
                ]
            print(json.dumps(row), flush=True)
            rows.append(row)
    print(json.dumps({
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.python_version()}",
        "duration_s": args.duration, "seed": args.seed, "cases": len(rows),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
