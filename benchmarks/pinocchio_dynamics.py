"""Pinocchio against MuJoCo on humimic's jobs: inverse dynamics of a retargeted reference,
payload identification from a gantry log, and (where CasADi is installed) a ballistic fix of
a reference's flight solved by CasADi and by a linear solve.

1. ``inverse_dynamics``: the G1 on the CMU walk (35_01, after the T-pose frame, retargeted at
   50 fps), finite-difference velocities and accelerations as
   ``retarget.dynamics.inverse_dynamics_torques`` takes them; ``mj_inverse`` (constraints
   off) against Pinocchio's RNEA (``humimic.real2sim.pinocchio``): largest difference, and time
   per frame, interleaved repeats (the ratio is MuJoCo's time over Pinocchio's).
2. ``payload``: ``humimic sysid simulate`` logs (written to MCAP and read back) with an
   undeclared payload; ``identify_payload`` on the fit part of the log (its first 70%, as the
   diagnosis fits) against ``humimic sysid diagnose`` on the whole log.
3. ``ballistic``: the CMU run (09_01): the base shift of least norm (and smooth) that makes
   the centre of mass fall at g in every flight frame, by a KKT solve in numpy and by CasADi;
   with ``--refine-seeds``, ``humimic refine`` of the run and of its fix.

Usage: .venv/bin/python benchmarks/pinocchio_dynamics.py [--repeats 5] [--seed 7]
    [--duration 40] [--no-diagnose] [--refine-seeds 0 1 2] [--only SECTION ...]
"""

from __future__ import annotations

import argparse
import copy
import importlib
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.configs import DynamicsConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.motion import Motion, motion_from_qpos
from humimic.real2sim import LogSettings, simulate_log, write_robot_log
from humimic.real2sim.pinocchio import PinocchioRobot, accelerations, identify_payload, pin
from humimic.real2sim.report import load_fixed_base_log, run_diagnosis
from humimic.retarget import Retargeter
from humimic.retarget.dynamics import FLIGHT_CLEARANCE, reference_flight, refine
from humimic.retarget.dynamics.inverse import com_and_feet
from humimic.robots import get_robot
from humimic.robots.model import nominal_model, robot_xml_path
from humimic.sim.effects import parse_injection

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu"
FIT_END = 0.7

LOGS = {
    "wrist 0.8 kg": "payload_mass:right_wrist_yaw_link=0.8",
    "torso 3.0 kg": "payload_mass:torso_link=3.0",
    "clean": None,
}
"""The simulated logs: name -> the undeclared effect."""

FITS = [
    ("wrist 0.8 kg", "right_wrist_yaw_link", 0.8),
    ("torso 3.0 kg", "torso_link", 3.0),
    ("clean", "right_wrist_yaw_link", 0.0),
    ("clean", "torso_link", 0.0),
]
"""Payload fits: log, body, true added mass [kg]."""


def _retarget(clip: str) -> Motion:
    path = CMU / f"{clip}.bvh"
    if not path.is_file():
        raise SystemExit(f"{path}: not found (the CMU clips live in ../shared/data/cmu)")
    c = load_clip(path)
    return Retargeter("g1", "cmu", RetargetConfig(fps=50.0)).run(c.slice(1, c.num_frames)).motion


def _spread(x: list[float]) -> dict[str, float]:
    return {"median": float(np.median(x)), "min": float(np.min(x)), "max": float(np.max(x))}


def model_parity() -> dict[str, Any]:
    """How the adapter's model and Pinocchio's own MJCF parser match MuJoCo's."""
    cfg = get_robot("g1")
    mj = nominal_model(cfg)
    t0 = time.perf_counter()
    robot = PinocchioRobot.from_mujoco(mj)
    t1 = time.perf_counter()
    parsed = pin.buildModelFromMJCF(str(robot_xml_path(cfg).with_name("g1.xml")))
    t2 = time.perf_counter()
    mi = copy.copy(mj)
    mi.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    data, pdata = mujoco.MjData(mi), parsed.createData()
    rng = np.random.default_rng(0)
    ours, theirs = 0.0, 0.0
    for _ in range(50):
        q = mi.qpos0.copy()
        q[:3] = rng.normal(size=3)
        q[3:7] = rng.normal(size=4)
        q[3:7] /= np.linalg.norm(q[3:7])
        q[7:] = rng.uniform(mi.jnt_range[1:, 0], mi.jnt_range[1:, 1])
        v, a = rng.normal(size=mi.nv), 5.0 * rng.normal(size=mi.nv)
        data.qpos[:], data.qvel[:], data.qacc[:] = q, v, a
        mujoco.mj_inverse(mi, data)
        mine = robot.inverse_dynamics(q[None], v[None], a[None])[0]
        ours = max(ours, float(np.abs(mine - data.qfrc_inverse).max()))
        pq, pv, pa = robot.to_pinocchio(q, v, a)
        tau = pin.rnea(parsed, pdata, pq, pv, pa).copy()
        tau[:3] = pin.Quaternion(*map(float, q[3:7])).matrix() @ tau[:3]
        theirs = max(theirs, float(np.abs(tau - data.qfrc_inverse).max()))
    return {
        "build_s": {"from_mujoco": t1 - t0, "buildModelFromMJCF": t2 - t1},
        "max_abs_generalized_force_diff_vs_mj_inverse": {
            "from_mujoco": ours,
            "buildModelFromMJCF": theirs,
        },
        "buildModelFromMJCF_armature_max_diff": float(
            np.abs(parsed.armature - robot.model.armature).max()
        ),
        "total_mass_kg": {
            "mujoco": float(mj.body_mass.sum()),
            "pinocchio": float(pin.computeTotalMass(robot.model)),
        },
    }


def inverse_dynamics(motion: Motion, repeats: int) -> dict[str, Any]:
    mj = nominal_model(get_robot(motion.robot))
    mi = copy.copy(mj)
    mi.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    T, fps = motion.num_frames, motion.fps
    qv = np.zeros((T, mi.nv))
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(mi, qv[t], (b - a) / fps, motion.qpos[a], motion.qpos[b])
    qa = np.asarray(np.gradient(qv, 1.0 / fps, axis=0))
    robot = PinocchioRobot.from_mujoco(mj)
    data = mujoco.MjData(mi)
    pq = [robot.to_pinocchio(motion.qpos[t], qv[t], qa[t]) for t in range(T)]

    def run_mujoco() -> np.ndarray:
        out = np.zeros((T, mi.nv))
        for t in range(T):
            data.qpos[:], data.qvel[:], data.qacc[:] = motion.qpos[t], qv[t], qa[t]
            mujoco.mj_inverse(mi, data)
            out[t] = data.qfrc_inverse
        return out

    def run_rnea() -> None:
        for q, v, a in pq:
            pin.rnea(robot.model, robot.data, q, v, a)

    f_mj = run_mujoco()
    f_pin = robot.inverse_dynamics(motion.qpos, qv, qa)
    inner = max(1, 2000 // T)  # About 2,000 frames per timing.
    times: dict[str, list[float]] = {"mj_inverse": [], "adapter": [], "rnea": []}
    for _ in range(repeats):
        for name, fn in (
            ("mj_inverse", run_mujoco),
            ("adapter", lambda: robot.inverse_dynamics(motion.qpos, qv, qa)),
            ("rnea", run_rnea),
        ):
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            times[name].append(1e6 * (time.perf_counter() - t0) / (inner * T))
    return {
        "frames": T,
        "max_abs_diff": {
            "all_rows": float(np.abs(f_pin - f_mj).max()),
            "joint_rows_n_m": float(np.abs(f_pin[:, 6:] - f_mj[:, 6:]).max()),
        },
        "largest_generalized_force": float(np.abs(f_mj).max()),
        "us_per_frame": {k: _spread(v) for k, v in times.items()},
        "ratio_mj_over_adapter": _spread(
            [m / p for m, p in zip(times["mj_inverse"], times["adapter"], strict=True)]
        ),
        "ratio_mj_over_rnea": _spread(
            [m / p for m, p in zip(times["mj_inverse"], times["rnea"], strict=True)]
        ),
    }


def _fits(log: Any, body: str) -> dict[str, Any]:
    """``identify_payload`` on the fit part of a log, several ways; seconds include the
    model build and the accelerations."""
    out = {}
    for name, effort, fit_com, instrument in (
        ("effort, mass", True, False, True),
        ("pd law, mass", False, False, True),
        ("effort, mass + com", True, True, True),
        ("effort, mass, plain least squares", True, False, False),
    ):
        t0 = time.perf_counter()
        pr = PinocchioRobot.from_mujoco(
            nominal_model(get_robot(log.robot)), base_pose=log.base_pose
        )
        qdd, valid = accelerations(log.t, log.qd, log.t_cmd)
        fit = valid & (log.t < log.t[0] + FIT_END * (log.t[-1] - log.t[0]))
        if effort:
            tau = log.effort
        else:  # The drives' PD law from the held commands.
            i = log.command_index(log.t)
            tau = log.kp[i] * (log.cmd_q[i] - log.q) + log.kd[i] * (log.cmd_qd[i] - log.qd)
            tau = tau + log.cmd_tau[i]
        f = identify_payload(
            pr, log.q, log.qd, qdd, tau, body, samples=fit, fit_com=fit_com, instrument=instrument
        )
        out[name] = {
            "kg": f.mass,
            "std_kg": f.mass_std,
            "com_m": [float(x) for x in f.com],
            "rows": f.rows,
            "residual_rms_n_m": f.residual_rms,
            "seconds": time.perf_counter() - t0,
        }
    return out


def payload(seed: int, duration: float, diagnose: bool) -> list[dict[str, Any]]:
    robot = get_robot("g1")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        diagnosed: dict[str, Any] = {}
        logs = {}
        for name, text in LOGS.items():
            inj = [parse_injection(text)] if text else []
            sim = simulate_log(robot, inj, LogSettings(duration=duration, seed=seed))
            path = write_robot_log(sim, Path(tmp) / f"{name.split()[0]}.mcap")
            logs[name] = load_fixed_base_log(path)[2]  # Read back: what the diagnosis reads.
            if diagnose:
                r = run_diagnosis(path, Path(tmp) / name.split()[0]).report
                diagnosed[name] = {
                    "claimed": [
                        {
                            "effect": e["effect"],
                            "target": e.get("body") or e["joints"][0],
                            "value": e["params"]["value"],
                        }
                        for e in r["effects"]
                        if e["confidence"] >= 0.5
                    ],
                    "heldout_mrad_before": 1e3 * r["error_before"]["kstep_rmse_rad"],
                    "heldout_mrad_after": 1e3 * r["error_after"]["kstep_rmse_rad"],
                    "seconds": r["seconds"],
                }
        for name, body, kg in FITS:
            row = {
                "log": name,
                "body": body,
                "true_kg": kg,
                "regressor": _fits(logs[name], body),
                "diagnose": diagnosed.get(name),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def ballistic(motion: Motion, refine_seeds: list[int], smooth: float = 1.0) -> dict[str, Any]:
    """The base shift ``dp`` (T, 3) of least ``|dp|^2 + smooth |D2 dp|^2`` with the centre of
    mass's second difference ``g dt^2`` in every flight frame (both feet
    ``FLIGHT_CLEARANCE`` above their lowest): an equality-constrained least squares, solved
    by its KKT system and by CasADi's QP and NLP solvers. With ``refine_seeds``, both
    references are refined (``humimic refine`` defaults) with each seed."""
    cfg = get_robot(motion.robot)
    mj = nominal_model(cfg)
    T, dt = motion.num_frames, 1.0 / motion.fps
    com, foot_z = com_and_feet(mj, motion)
    air = (foot_z > foot_z.min(axis=0) + FLIGHT_CLEARANCE).all(axis=1)
    flight = [t for t in range(1, T - 1) if air[t]]
    D2 = np.zeros((T - 2, T))
    for i in range(T - 2):
        D2[i, i : i + 3] = [1.0, -2.0, 1.0]
    C = D2[[t - 1 for t in flight]]
    rhs = np.asarray(mj.opt.gravity) * dt**2 - C @ com  # (F, 3)

    def kkt() -> np.ndarray:
        H = np.eye(T) + smooth * D2.T @ D2
        K = np.block([[H, C.T], [C, np.zeros((len(flight), len(flight)))]])
        return np.linalg.solve(K, np.vstack([np.zeros((T, 3)), rhs]))[:T]

    out: dict[str, Any] = {"frames": T, "flight_frames": len(flight)}
    t0 = time.perf_counter()
    dp = kkt()
    out["seconds"] = {"numpy_kkt": time.perf_counter() - t0}
    try:  # Not a dependency of humimic (BENCHMARKS.md says why): measured where installed.
        ca: Any = importlib.import_module("casadi")
    except ImportError:
        out["casadi"] = "not installed"
    else:
        for solver in ("qpoases", "osqp", "ipopt"):
            t0 = time.perf_counter()
            opti = ca.Opti() if solver == "ipopt" else ca.Opti("conic")
            x = opti.variable(T, 3)
            opti.minimize(ca.sumsqr(x) + smooth * ca.sumsqr(ca.DM(D2) @ x))
            opti.subject_to(ca.DM(C) @ x == ca.DM(rhs))
            opts: dict[str, Any] = {"print_time": False}
            opts.update(
                {"ipopt.print_level": 0, "ipopt.sb": "yes"}
                if solver == "ipopt"
                else {"printLevel": "none"}
                if solver == "qpoases"
                else {"osqp.verbose": False}
            )
            opti.solver(solver, opts)
            x_opt = np.asarray(opti.solve().value(x))
            out["seconds"][f"casadi_{solver}"] = time.perf_counter() - t0
            out[f"casadi_{solver}_max_diff_m"] = float(np.abs(x_opt - dp).max())
    qpos = motion.qpos.copy()
    qpos[:, :3] += dp
    fixed = motion_from_qpos(mj, qpos, motion.fps, motion.robot)
    out["before"] = reference_flight(motion, mj)
    out["after"] = reference_flight(fixed, mj)
    out["base_shift_mm"] = {
        "max": 1e3 * float(np.linalg.norm(dp, axis=1).max()),
        "rms": 1e3 * float(np.sqrt((dp**2).sum(axis=1).mean())),
    }
    out["body_shift_mm_mean"] = _body_error_mm(fixed, motion)
    out["refined"] = []
    for seed in refine_seeds:  # Does the fix help the sampler + iLQR downstream?
        for name, ref in (("original", motion), ("ballistic", fixed)):
            refined, report = refine(ref, DynamicsConfig(seed=seed))
            rep = report["dynamics_replay"]
            out["refined"].append({
                "reference": name, "seed": seed, "fell": rep["fell"],
                "mpjpe_mm_own_reference": rep["mpjpe_mm"],
                "body_error_mm_vs_original": _body_error_mm(refined, motion),
                "foot_skating_mm_per_s": rep["foot_skating_mm_per_s"],
                "cpu_seconds_per_motion_second": report["cpu_seconds_per_motion_second"],
            })  # fmt: skip
            print(json.dumps(out["refined"][-1]), flush=True)
    return out


def _body_error_mm(a: Motion, b: Motion) -> float:
    """Mean distance of every body between two motions of the same robot [mm]."""
    return 1e3 * float(np.linalg.norm(a.body_pos_w - b.body_pos_w, axis=-1).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=7, help="seed of the simulated logs")
    parser.add_argument("--duration", type=float, default=40.0, help="log length [s]")
    parser.add_argument("--no-diagnose", action="store_true", help="skip humimic sysid diagnose")
    parser.add_argument(
        "--only", nargs="+", choices=["model", "inverse_dynamics", "ballistic", "payload"]
    )
    parser.add_argument(
        "--refine-seeds", type=int, nargs="*", default=[],
        help="refine the run and its ballistic fix with these seeds (about 1 min each)",
    )  # fmt: skip
    args = parser.parse_args()
    t0 = time.perf_counter()
    out: dict[str, Any] = {
        "benchmark": "pinocchio_dynamics",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "versions": {"pinocchio": pin.__version__, "mujoco": mujoco.__version__},
    }
    sections = {
        "model": model_parity,
        "inverse_dynamics": lambda: inverse_dynamics(_retarget("35_01"), args.repeats),
        "ballistic": lambda: ballistic(_retarget("09_01"), args.refine_seeds),
        "payload": lambda: payload(args.seed, args.duration, not args.no_diagnose),
    }
    for name in args.only or list(sections):
        out[name] = sections[name]()
    out["seconds"] = time.perf_counter() - t0
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
