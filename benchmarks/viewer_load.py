"""Time from `humimic view` to a served 3,000-frame clip (issue 3: under 5 s), and the MCAP
round trip of that motion. Prints JSON.

Makes a 3,011-frame G1 motion (climbing clip 2 at 120 fps), then starts the viewer as a user
would, with the human and the scene, and measures the wall time until it prints its URL
(Python start, imports, model compile, forward kinematics of every frame, scene upload).

Usage: .venv/bin/python benchmarks/viewer_load.py [--data PATH] [--repeats N]
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
from dataclasses import replace
from pathlib import Path

import numpy as np

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.formats.mcap import read_motion_mcap, write_motion_mcap
from humimic.motion import save_motion
from humimic.retarget import Retargeter
from humimic.viewer.browser import free_port

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def time_view(args: list[str]) -> float:
    port = free_port()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "humimic.cli.main", "view", *args, "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    try:
        for line in proc.stdout:
            if "humimic view: http" in line:
                return time.perf_counter() - t0
        raise RuntimeError("the viewer exited without serving")
    finally:
        proc.kill()
        proc.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    seq = args.data / "holosoma_climb" / "mocap_climb_seq_2"
    clip_path = next(seq.glob("*.npy"))
    clip = load_clip(clip_path)
    out = Retargeter("g1", clip.skeleton, replace(retarget_default(), fps=120.0)).run(clip)
    with tempfile.TemporaryDirectory() as tmp:
        motion = Path(tmp) / "climb_120fps.npz"
        save_motion(out.motion, motion)
        view_args = [str(motion), "--human", str(clip_path), "--scene", str(seq)]
        times = [time_view(view_args) for _ in range(args.repeats)]
        mcap = Path(tmp) / "climb_120fps.mcap"
        t0 = time.perf_counter()
        write_motion_mcap(out.motion, mcap)
        t1 = time.perf_counter()
        back = read_motion_mcap(mcap)
        t2 = time.perf_counter()
        lossless = all(
            np.array_equal(getattr(out.motion, k), getattr(back, k))
            for k in ("qpos", "joint_pos", "joint_vel", "body_pos_w", "body_quat_w",
                      "body_lin_vel_w", "body_ang_vel_w")
        )  # fmt: skip
        sizes = {"mcap_mb": mcap.stat().st_size / 1e6, "npz_mb": motion.stat().st_size / 1e6}
    print(
        json.dumps(
            {
                "benchmark": "viewer_load",
                "machine": {"cpu": platform.machine(), "cores": os.cpu_count()},
                "frames": out.motion.num_frames,
                "seconds_to_served_best": min(times),
                "seconds_to_served_all": times,
                "mcap_write_seconds": t1 - t0,
                "mcap_read_seconds": t2 - t1,
                "mcap_round_trip_lossless": lossless,
                **sizes,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
