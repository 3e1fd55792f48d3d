"""Robot-to-robot retargeting on every CMU clip in ../shared/data: each clip retargeted to the
source robot (default G1), then that motion to every other registered robot, with the report's
figures and the independent checks of benchmarks/retarget_quality.py. Prints one JSON object.

Usage: .venv/bin/python benchmarks/robot_to_robot.py [--source g1] [--robots t1 h1 ...]
    [--data PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.motion import save_motion
from humimic.pipeline.robot_clip import robot_motion_clip
from humimic.retarget import Retargeter
from humimic.robots import export_nominal, get_robot, robot_names
from retarget_quality import KEYS, independent_checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--source", default="g1")
    parser.add_argument("--robots", nargs="+", default=None)
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[2] / "shared" / "data")  # fmt: skip
    args = parser.parse_args()
    targets = args.robots or [r for r in robot_names() if r != args.source]
    clips = sorted((args.data / "cmu").glob("*.bvh"))
    out: dict = {
        "benchmark": "robot_to_robot",
        "source": args.source,
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "rows": [],
    }
    with tempfile.TemporaryDirectory() as tmp:
        src_rt = Retargeter(args.source, "cmu", retarget_default())
        sources = []
        for p in clips:
            motion = src_rt.run(load_clip(p).slice(1)).motion
            path = Path(tmp) / f"{p.stem}.npz"
            save_motion(motion, path)
            sources.append(path)
        for robot in targets:
            xml = export_nominal(get_robot(robot), Path(tmp) / f"{robot}.xml")
            try:
                rt = Retargeter(robot, "canonical", retarget_default())
                for path in sources:
                    result = rt.run(robot_motion_clip(path))
                    row = {"clip": path.stem, "robot": robot}
                    row |= {k: result.report.get(k) for k in KEYS}
                    row["independent"] = independent_checks(xml, result.motion.qpos)
                    out["rows"].append(row)
                    print(json.dumps(row), file=sys.stderr, flush=True)
            except Exception as e:
                out["rows"].append({"robot": robot, "refused": str(e)})
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
