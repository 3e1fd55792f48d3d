"""`humimic sysid diagnose` on 40 s G1 logs with undeclared effects, end to end (log file in,
model, report and plots out, residual network when unexplained). Prints one JSON line per case
and a summary object: the truth, what was claimed, held-out k-step error before/after, time.

Usage: .venv/bin/python benchmarks/sysid_diagnose.py [--duration 40] [--seed 7] [--only NAME]
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

from humimic.real2sim import LogSettings, RobotLog, simulate_log, write_robot_log
from humimic.real2sim.report import run_diagnosis
from humimic.robots import get_robot
from humimic.sim.effects import parse_injection


def _cable(spec: mujoco.MjSpec) -> None:
    """Outside the vocabulary: a cable pulling the left knee (cubic spring about 0.8 rad)."""
    j = spec.joint("left_knee_joint")
    j.stiffness = np.array([0.0, 0.0, 300.0])
    j.springref = 0.8


def _bus_latency(log: RobotLog) -> RobotLog:
    """Outside the effect code: every command acts 25 ms after the log's stamp says it was
    sent (the command stamps moved earlier), a latency of the whole bus."""
    return replace(log, t_cmd=log.t_cmd - 0.025)


LEGS = ",".join(f"{side}_{j}_joint" for side in ("left", "right")
                for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll"))  # fmt: skip

CASES: dict[str, tuple[list[str], object]] = {
    "clean": ([], None),
    "coulomb_friction": (["coulomb_friction:right_knee_joint=2.5"], None),
    "viscous_damping": (["viscous_damping:left_hip_pitch_joint=1.5"], None),
    "armature": (["armature:left_elbow_joint=0.05"], None),
    "gain_mismatch": (["gain_mismatch:left_knee_joint=0.75"], None),
    "delay": (["delay:left_knee_joint=0.0213"], None),
    "lag": (["lag:right_hip_pitch_joint=0.025"], None),
    "torque_limit": (["torque_limit:left_knee_joint=3.5"], None),
    "encoder_offset": (["encoder_offset:right_hip_roll_joint=0.05"], None),
    "payload_mass": (["payload_mass:right_wrist_yaw_link=0.8"], None),
    "backlash": (["backlash:left_knee_joint=0.04"], None),
    "friction+damping (one joint)": (
        ["coulomb_friction:left_knee_joint=2.0", "viscous_damping:left_knee_joint=1.5"], None),
    "delay+payload": (["delay:right_knee_joint=0.0187", "payload_mass:left_wrist_yaw_link=0.8"], None),
    "encoder_offset, wrist yaw (not identifiable)": (["encoder_offset:left_wrist_yaw_joint=0.05"], None),
    "cable spring (outside the vocabulary)": ([], _cable),
    "leg latency 30 ms (12 drives)": ([f"delay:{LEGS}=0.03"], None),
    "bus latency 25 ms (command stamps moved)": ([], _bus_latency),
}  # fmt: skip


def diagnosis_summary(r: dict) -> dict:
    """What a diagnosis report claimed and how much of the held-out error it removed."""
    net = r["residual_model"]
    return {
        "claimed": [{"effect": e["effect"],
                     "target": e.get("group") or e.get("body") or e["joints"][0],
                     "joints": len(e.get("joints", [])),
                     "value": e["params"]["value"], "confidence": round(e["confidence"], 2),
                     "stands_out": e.get("stands_out")}
                    for e in r["effects"] if e["confidence"] >= 0.5],
        "not_identifiable": [{"effect": s["effect"], "joints": len(s["joints"])}
                             for s in r["not_identifiable"]],
        "unexplained": r["unexplained"],
        "unexplained_joints": len(r["unexplained_joints"]),
        "heldout_kstep_rmse_mrad_before": r["error_before"]["kstep_rmse_rad"] * 1e3,
        "heldout_kstep_rmse_mrad_after": r["error_after"]["kstep_rmse_rad"] * 1e3,
        "heldout_kstep_rmse_mrad_residual_net": None if net is None
        else net["error_after"]["kstep_rmse_rad"] * 1e3,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--only", default=None, help="run one case (its name)")
    args = parser.parse_args()
    robot = get_robot("g1")
    out = {"benchmark": "sysid_diagnose", "machine": {"cpu": platform.processor() or
           platform.machine(), "cores": os.cpu_count()}, "duration_s": args.duration,
           "cases": []}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for name, (texts, edit) in CASES.items():
            if args.only and name != args.only:
                continue
            injections = [parse_injection(x) for x in texts]
            retime = edit is _bus_latency
            log = simulate_log(robot, injections, LogSettings(duration=args.duration,
                               seed=args.seed), edit=None if retime else edit)  # type: ignore[arg-type]  # fmt: skip
            if retime:
                log = _bus_latency(log)
            path = write_robot_log(log, Path(tmp) / "log.mcap")
            r = run_diagnosis(path, Path(tmp) / name.replace(" ", "_")).report
            case = {
                "case": name,
                "injected": [{"effect": i.effect, "target": ",".join(i.targets), "value": i.value}
                             for i in injections] + ([{"effect": "cable spring (hidden)",
                                                      "target": "left_knee_joint"}] if edit is _cable else [])
                            + ([{"effect": "bus latency (stamps)", "target": "all joints",
                                 "value": 0.025}] if retime else []),
                **diagnosis_summary(r),
                "seconds": r["seconds"],
            }  # fmt: skip
            out["cases"].append(case)
            print(json.dumps(case), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
