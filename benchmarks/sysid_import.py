"""`humimic sysid import` on a 40 s deployment log written as a Unitree low-state .npz (35
motor slots) and as a ROS 2 bag (JointState, Imu, PoseStamped, JointState targets), by the
import tests' own writers; the whole command's seconds, against the same command on a missing
file (start-up and the model's compilation), and reading the written log back.

Usage: .venv/bin/python benchmarks/sysid_import.py [--duration 40] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from humimic.real2sim import LogSettings, simulate_log
from humimic.real2sim.report import load_robot_log
from humimic.robots import get_robot

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_real2sim_import as writers

HUMIMIC = str(Path(sys.executable).with_name("humimic"))


def _seconds(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([HUMIMIC, "sysid", "import", *args], capture_output=True, check=False)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    log = simulate_log(get_robot("g1"), [],
                       LogSettings(duration=args.duration, base="floating", mocap=True, seed=4))  # fmt: skip
    out: dict = {"benchmark": "sysid_import", "machine": {"cpu": platform.processor() or
                 platform.machine(), "cores": os.cpu_count()}, "duration_s": args.duration,
                 "states": int(log.t.size), "commands": int(log.t_cmd.size)}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        writers._savez(d / "low.npz", writers._unitree_arrays(log))
        writers._ros_bag(d / "bag", log, names_order=np.arange(len(log.joint_names)),
                         extra_joint=False)  # fmt: skip
        (d / "gains.yaml").write_text(writers._gains_yaml(log))
        (d / "slots.yaml").write_text("ignore: [29, 30, 31, 32, 33, 34]\n")
        runs = {
            "npz": [str(d / "low.npz"), "--map", str(d / "slots.yaml")],
            "ros2_bag": [str(d / "bag"), "--map", str(d / "gains.yaml"), "--base-pose-topic",
                         "/mocap"],
            "missing_file": [str(d / "missing.npz")],
        }  # fmt: skip
        for name, flags in runs.items():
            out[f"{name}_s"] = [_seconds(*flags, "--out", str(d / f"{name}.mcap"))
                                for _ in range(args.repeats)]  # fmt: skip
        t0 = time.perf_counter()
        load_robot_log(d / "npz.mcap")
        out["read_back_s"] = time.perf_counter() - t0
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
