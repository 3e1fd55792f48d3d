"""`humimic sysid diagnose` on logs whose effects are made by their own code, not by the
vocabulary's implementations (:mod:`humimic.sim.effects`): a gantry log and a deployment log
(the G1 standing on the floor, swaying under its balance controller) for each case.

Every effect here is written in this file, against the MuJoCo model spec or the log itself:

- bus latency: the log's command stamps moved 25 ms earlier (every command acts 25 ms after
  its stamp); the vocabulary's delay is an actuator ring buffer;
- weak proportional gain: every leg actuator's kp at 70 %, kd unchanged (``gainprm[0]`` and
  ``biasprm[1]`` edited); the vocabulary's gain mismatch scales kp and kd together;
- backpack: a new 3 kg box body welded to the torso, 15 cm above its frame (mass, centre of
  mass and inertia all change); the vocabulary's payload adds mass at the body's own centre
  of mass. (Placed 5 or 10 cm behind, the standing robot falls within 2.5 s of a 40 s log:
  its balance controller is designed on the nominal robot);
- cable spring: a cubic spring on the left knee (outside the vocabulary), 10 N m/rad^3 about
  0.8 rad (the standing robot falls with 20 or more);
- low floor friction: the floor's sliding friction at 0.3 (outside the vocabulary; the
  deployment log only).

Prints one JSON line per case and log, then a summary object.

Usage: .venv/bin/python benchmarks/sysid_independent.py [--duration 40] [--seed 11]
       [--only NAME] [--base fixed|floating] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim import LogSettings, RobotLog, simulate_log, write_robot_log
from humimic.real2sim.report import run_diagnosis
from humimic.robots import get_robot
from sysid_diagnose import diagnosis_summary

LEGS = [f"{side}_{j}_joint" for side in ("left", "right")
        for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")]  # fmt: skip


def _weak_kp(spec: mujoco.MjSpec) -> None:
    """Leg drives at 70 % of their proportional gain; the derivative gain unchanged. A
    position actuator's force is gain * ctrl + bias1 * q + bias2 * qdot: kp sits in
    ``gainprm[0]`` and ``-biasprm[1]``, kd in ``-biasprm[2]``."""
    for a in spec.actuators:
        if a.target in LEGS:
            a.gainprm[0] *= 0.7
            a.biasprm[1] *= 0.7


def _backpack(spec: mujoco.MjSpec) -> None:
    """A 3 kg box (0.12 x 0.30 x 0.25 m) welded to the torso, above its frame."""
    torso = spec.body("torso_link")
    box = torso.add_body(name="backpack_box", pos=[0.0, 0.0, 0.15])
    m = 3.0
    box.mass = m
    box.ipos[:] = 0.0
    sx, sy, sz = 0.12, 0.30, 0.25  # Full extents along x, y, z.
    box.inertia[:] = [m / 12 * (sy**2 + sz**2), m / 12 * (sx**2 + sz**2), m / 12 * (sx**2 + sy**2)]
    box.explicitinertial = True


def _cable(spec: mujoco.MjSpec) -> None:
    """A cable pulling the left knee: a cubic spring about 0.8 rad."""
    j = spec.joint("left_knee_joint")
    j.stiffness = np.array([0.0, 0.0, 10.0])
    j.springref = 0.8


def _slippery(spec: mujoco.MjSpec) -> None:
    """The floor's sliding friction at 0.3 (the robot's feet keep theirs; MuJoCo takes the
    larger of two geoms' frictions by default, so the feet's is lowered too)."""
    for g in spec.geoms:
        g.friction = [0.3, g.friction[1], g.friction[2]]


def _bus_latency(log: RobotLog) -> RobotLog:
    return replace(log, t_cmd=log.t_cmd - 0.025)


Case = tuple[Callable[[mujoco.MjSpec], None] | None, Callable[[RobotLog], RobotLog] | None, str]
CASES: dict[str, Case] = {
    "clean": (None, None, "nothing"),
    "bus latency 25 ms": (None, _bus_latency, "delay 0.025 s on every joint"),
    "leg kp at 70 %, kd kept": (_weak_kp, None, "kp x 0.7 on the 12 leg drives"),
    "backpack 3 kg, offset": (_backpack, None, "3 kg on torso_link, 15 cm above its frame"),
    "cable spring on the left knee": (_cable, None, "outside the vocabulary"),
    "floor friction 0.3": (_slippery, None, "outside the vocabulary"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--only", default=None, help="run one case (its name)")
    parser.add_argument("--base", choices=["fixed", "floating"], default=None)
    parser.add_argument(
        "--keep", type=Path, default=None, help="keep each case's log and report in this folder"
    )
    args = parser.parse_args()
    robot = get_robot("g1")
    out = {"benchmark": "sysid_independent", "machine": {"cpu": platform.processor() or
           platform.machine(), "cores": os.cpu_count()}, "duration_s": args.duration,
           "seed": args.seed, "cases": []}  # fmt: skip
    bases = [args.base] if args.base else ["fixed", "floating"]
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.keep or Path(scratch)
        tmp.mkdir(parents=True, exist_ok=True)
        for name, (edit, retime, truth) in CASES.items():
            if args.only and name != args.only:
                continue
            for base in bases:
                if base == "fixed" and edit is _slippery:
                    continue  # A gantry has no floor.
                settings = LogSettings(duration=args.duration, seed=args.seed, base=base)
                t0 = time.perf_counter()
                try:
                    log = simulate_log(robot, [], settings, edit=edit)
                except InputError as e:  # The robot fell: the log cannot be made.
                    print(json.dumps({"case": name, "base": base, "error": str(e)}), flush=True)
                    continue
                if retime is not None:
                    log = retime(log)
                sim_s = time.perf_counter() - t0
                case_dir = Path(tmp) / f"{base}_{name.replace(' ', '_')}"
                path = write_robot_log(log, Path(tmp) / f"{case_dir.name}.mcap")
                r = run_diagnosis(path, case_dir).report
                case = {
                    "case": name, "base": base, "truth": truth,
                    **diagnosis_summary(r),
                    "simulate_s": sim_s, "diagnose_s": r["seconds"],
                }  # fmt: skip
                out["cases"].append(case)
                print(json.dumps(case), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
