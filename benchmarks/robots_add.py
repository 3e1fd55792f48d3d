"""`humimic robots add` on the humanoid URDFs of example-robot-data (Talos, Romeo, iCub, the G1,
simple_humanoid), each then retargeting every CMU clip in ../shared/data with the report's figures
and the independent checks of benchmarks/retarget_quality.py. Prints one JSON object.

Needs `pip install example-robot-data==6.0.0` (about 130 MB; not a humimic dependency).

Usage: .venv/bin/python benchmarks/robots_add.py [--data PATH] [--robots talos romeo ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

URDFS = {
    "talos": "talos_data/robots/talos_reduced.urdf",
    "romeo": "romeo_description/urdf/romeo_small.urdf",
    "icub": "icub_description/robots/icub_reduced.urdf",
    "g1_urdf": "g1_description/urdf/g1_29dof_rev_1_0.urdf",
    "simple_humanoid": "simple_humanoid_description/urdf/simple_humanoid.urdf",
}
"""Robot name -> URDF under example-robot-data's robots folder."""


def erd_robots() -> Path:
    """example-robot-data's robots folder (the cmeel layout it installs)."""
    for site in map(Path, sys.path):
        cand = site / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if cand.is_dir():
            return cand
    raise SystemExit("example-robot-data is not installed: pip install example-robot-data==6.0.0")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", nargs="+", default=list(URDFS))
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[2] / "shared" / "data")  # fmt: skip
    args = parser.parse_args()
    root = erd_robots()
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["HUMIMIC_ROBOTS_DIR"] = str(Path(tmp) / "robots")
        from humimic.configs import retarget_default
        from humimic.datasets import load_clip
        from humimic.errors import HumimicError
        from humimic.retarget import Retargeter
        from humimic.robots import export_nominal, get_robot
        from humimic.robots.add import add_robot
        from retarget_quality import KEYS, independent_checks

        out: dict = {
            "benchmark": "robots_add",
            "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
            "robots": [],
        }
        clips = sorted((args.data / "cmu").glob("*.bvh"))
        for name in args.robots:
            entry: dict = {"robot": name, "urdf": URDFS[name]}
            t0 = time.perf_counter()
            try:
                r = add_robot(root / URDFS[name], name)
            except HumimicError as e:
                entry["refused"] = str(e).replace(str(root), "<example-robot-data>")
                out["robots"].append(entry)
                print(json.dumps(entry), file=sys.stderr, flush=True)
                continue
            s = r.structure
            entry |= {"add_seconds": time.perf_counter() - t0, "joints": r.joints,
                      "mass_kg": r.mass, "height_m": s.height, "not_found": s.missing(),
                      "notes": len(r.notes), "rows": []}  # fmt: skip
            xml = export_nominal(get_robot(name), Path(tmp) / f"{name}.xml")
            rt = Retargeter(name, "cmu", retarget_default())
            for p in clips:
                result = rt.run(load_clip(p).slice(1))
                row = {"clip": p.stem} | {k: result.report.get(k) for k in KEYS}
                row["independent"] = independent_checks(xml, result.motion.qpos)
                entry["rows"].append(row)
                print(json.dumps({"robot": name} | row), file=sys.stderr, flush=True)
            out["robots"].append(entry)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
