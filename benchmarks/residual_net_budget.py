"""The residual actuator network's training budget against its held-out accuracy.

A gantry log with an effect outside the vocabulary (the cable test's cubic spring on the
left knee, 16 s, seed 4), the nominal model corrected by nothing; the network trained on the
first 70 % with each number of Adam steps (``NetConfig.steps``), scored on the last 30 % as
``humimic sysid diagnose`` scores it (closed loop, k-step windows). Prints one JSON object.

Usage: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/residual_net_budget.py
    [--steps 1500 750 500] [--duration 16] [--seed 4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import mujoco
import numpy as np

from humimic.real2sim import LogSettings, simulate_log
from humimic.real2sim.actuator_net import NetConfig, fit_residual_net
from humimic.real2sim.fitting import FIT_END
from humimic.real2sim.residual import Correction, Predictor
from humimic.robots import get_robot
from humimic.sim.models import prediction_spec


def _cable(spec: mujoco.MjSpec) -> None:
    """Outside the vocabulary: a cable pulling the left knee (cubic spring about 0.8 rad)."""
    j = spec.joint("left_knee_joint")
    j.stiffness = np.array([0.0, 0.0, 300.0])
    j.springref = 0.8


def main() -> None:
    parser = argparse.ArgumentParser(description="Residual network budget")
    parser.add_argument("--steps", nargs="+", type=int, default=[1500, 750, 500])
    parser.add_argument("--duration", type=float, default=16.0)
    parser.add_argument("--seed", type=int, default=4)
    args = parser.parse_args()
    g1 = get_robot("g1")
    log = simulate_log(g1, [], LogSettings(duration=args.duration, seed=args.seed), edit=_cable)
    model = prediction_spec(g1, log.base_pose).compile()
    c = Correction.of(model)
    held = Predictor(model, log, span=(FIT_END, 1.0))
    out: dict = {"benchmark": "residual_net_budget", "machine": {"cpu": platform.processor()
                 or platform.machine(), "cores": os.cpu_count()},
                 "torch_threads": os.environ.get("OMP_NUM_THREADS"),
                 "nominal_heldout_mrad": 1e3 * held.error(c).kstep_rmse_rad, "rows": []}  # fmt: skip
    for steps in args.steps:
        t = time.perf_counter()
        net, info = fit_residual_net(c, log, (0.0, FIT_END), NetConfig(steps=steps))
        seconds = time.perf_counter() - t
        err = held.report(held.run_with_torque(c, net.torque, net.config.history))
        out["rows"].append({"steps": steps, "train_s": seconds,
                            "heldout_mrad": 1e3 * err.kstep_rmse_rad,
                            "torque_variance_explained": info["torque_variance_explained"]})  # fmt: skip
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
