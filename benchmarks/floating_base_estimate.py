"""How well the floating base's state is rebuilt at each prediction window's start, and what it
costs the nominal model's k-step error (humimic.real2sim.floating.estimate_base).

1. Standing logs (``humimic sysid simulate --base floating``, clean, with sensor noise): the
   nominal model's k-step error without motion capture, the lowest collider placed on the
   floor (rest depth 0) or at the model's rest depth (``humimic_rest_depth``), and with
   motion capture and the accelerometer.
2. With ``--run RUN``: a tracking policy's deployment (episodes from the training's reset
   noise on the nominal robot, logged as ``humimic loop`` logs them), where the simulator's
   true base state is known: the k-step error from the estimate with each combination of
   streams (motion capture, accelerometer, both with noise added, neither) and from the
   truth, the estimate's height and velocity errors, and how deep the true lowest collider
   lies and how fast it moves.

Prints one JSON object.

Usage: .venv/bin/python benchmarks/floating_base_estimate.py [--seeds 5 8] [--run RUN]
    [--episodes 4] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np

from humimic.real2sim import LogSettings, simulate_log
from humimic.real2sim.residual import Correction, Predictor, kstep_error
from humimic.robots import get_robot
from humimic.sim.models import (
    REST_DEPTH,
    floating_prediction_spec,
    floor_and_colliders,
    lowest_point,
)

HORIZONS = (0.02, 0.1, 0.5)


def _model(depth: float | None) -> mujoco.MjModel:
    """The floating prediction model, its rest depth replaced by ``depth`` (``None``: kept)."""
    spec = floating_prediction_spec(get_robot("g1"))
    if depth is not None:
        spec.numeric(REST_DEPTH).data = [depth]
    return spec.compile()


def _standing(seeds: list[int]) -> list[dict]:
    out = []
    for seed in seeds:
        log = simulate_log(get_robot("g1"), [], LogSettings(duration=8.0, base="floating",
                                                             seed=seed))  # fmt: skip
        row: dict = {"seed": seed}
        # Without motion capture the height comes from the contact, so the rest depth counts.
        for label, depth, lg in (("no_mocap_on_the_floor", 0.0, replace(log, mocap=None)),
                                 ("no_mocap_rest_depth", None, replace(log, mocap=None)),
                                 ("mocap_and_accelerometer", None, log)):  # fmt: skip
            m = _model(depth)
            row[label] = {f"kstep_mrad_{h}s": 1e3 * kstep_error(m, lg, horizon=h).kstep_rmse_rad
                          for h in HORIZONS}  # fmt: skip
        out.append(row)
    return out


def _deployment(run: Path, episodes: int, seed: int) -> dict:
    from humimic.configs.jobs import EvalSettings
    from humimic.real2sim.robotlog import join_logs
    from humimic.sim.physics import Physics, write_physics
    from humimic.tracking.evaluate import run_evaluation

    with tempfile.TemporaryDirectory() as tmp:  # The nominal robot as a "real" one.
        nominal = Path(tmp) / "nominal.yaml"
        write_physics(Physics(name="nominal"), nominal)
        ev = run_evaluation(EvalSettings(run=run, episodes=episodes, physics=str(nominal),
                                         seed=seed, start_noise=True),
                            open_loop=False, traces=episodes)  # fmt: skip
    from humimic.pipeline.loop import _robot_logs

    lived = [t for t in ev.policy_traces if len(t.qpos) >= 2]
    log = join_logs(_robot_logs(run, ev.joint_names, ev.step_dt, lived))
    qpos = np.concatenate([np.stack(t.qpos) for t in lived])
    qvel = np.concatenate([np.stack(t.qvel) for t in lived])
    m = _model(None)
    c = Correction.of(m)
    out: dict = {"run": str(run), "episodes": episodes, "seconds_logged": log.duration,
                 "state_rate_hz": 1.0 / float(np.median(np.diff(log.t)))}  # fmt: skip
    rng = np.random.default_rng(seed)
    assert log.imu is not None and log.imu.acc_b is not None and log.mocap is not None
    noisy = replace(
        log,
        imu=replace(log.imu, acc_b=log.imu.acc_b + rng.normal(0, 0.05, log.imu.acc_b.shape)),
        mocap=replace(log.mocap, pos_w=log.mocap.pos_w + rng.normal(0, 0.001,
                                                                    log.mocap.pos_w.shape)),
    )  # fmt: skip
    variants = {
        "mocap_and_accelerometer": log,
        "mocap_1mm_and_accelerometer_0.05": noisy,
        "mocap_only": replace(log, imu=replace(log.imu, acc_b=None)),
        "accelerometer_no_mocap": replace(log, mocap=None),
        "neither": replace(log, mocap=None, imu=replace(log.imu, acc_b=None)),
    }
    for h in HORIZONS:
        row: dict = {}
        p = base = None
        for name, lg in variants.items():
            p = Predictor(m, lg, horizon=h, stride=0.02)
            base = p.base
            assert base is not None  # A floating-base model.
            row[name] = {"kstep_mrad": 1e3 * p.error(c).kstep_rmse_rad}
            if h == HORIZONS[0]:
                row[name]["height_error_mm_median"] = 1e3 * float(
                    np.median(np.abs(base.qpos[:, 2] - qpos[p.starts, 2])))  # fmt: skip
                row[name]["velocity_error_mm_s_median_xyz"] = (1e3 * np.median(
                    np.abs(base.qvel[:, :3] - qvel[p.starts, :3]), axis=0)).tolist()  # fmt: skip
                row[name]["source"] = base.source
        assert p is not None and base is not None  # The last variant's predictor.
        p.base = replace(base, qpos=qpos[p.starts, :7].copy(), qvel=qvel[p.starts, :6].copy())
        row["true_base"] = {"kstep_mrad": 1e3 * p.error(c).kstep_rmse_rad}
        out[f"horizon_{h}s"] = row
    d = mujoco.MjData(m)
    f, cols = floor_and_colliders(m)
    depth, speed = [], []
    jac = np.zeros((3, m.nv))
    for k in range(len(qpos)):
        d.qpos[:], d.qvel[:] = qpos[k], qvel[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        dist, point, body = lowest_point(m, d, f, cols)
        mujoco.mj_jac(m, d, jac, None, point, body)
        depth.append(-dist)
        speed.append(float(np.linalg.norm(jac @ d.qvel)))
    out["true_lowest_depth_mm_p10_p50_p90"] = (1e3 * np.percentile(depth, [10, 50, 90])).tolist()
    out["true_lowest_speed_mm_s_p10_p50_p90"] = (1e3 * np.percentile(speed, [10, 50, 90])).tolist()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description="The floating base's estimate")
    parser.add_argument("--seeds", nargs="+", type=int, default=[5, 8])
    parser.add_argument("--run", type=Path, default=None)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    out: dict = {"benchmark": "floating_base_estimate", "machine": {"cpu": platform.processor()
                 or platform.machine(), "cores": os.cpu_count()},
                 "rest_depth_mm": 1e3 * float(_model(None).numeric(REST_DEPTH).data[0]),
                 "standing": _standing(args.seeds)}  # fmt: skip
    if args.run is not None:
        out["deployment"] = _deployment(args.run, args.episodes, args.seed)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
