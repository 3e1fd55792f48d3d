"""Quality of kinematic retargeting on every real clip in ../shared/data. Prints one JSON object.

For each clip: the report of `humimic retarget` (speed, key-point error, foot skating, ground
penetration, feet on the floor, joint-limit violations, self-collision, jerk).

Usage: .venv/bin/python benchmarks/retarget_quality.py [--robot g1] [--data PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

from humimic.configs import retarget_default
from humimic.datasets import load_clip
from humimic.retarget import Retargeter

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def clips(root: Path) -> list[Path]:
    return sorted((root / "cmu").glob("*.bvh")) + sorted((root / "holosoma_climb").glob("*/*.npy"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robot", default="g1")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    paths = clips(args.data)
    if not paths:
        raise SystemExit(f"no clips under {args.data} (expected cmu/*.bvh, holosoma_climb/*/*.npy)")
    retargeters: dict[str, Retargeter] = {}
    out: dict = {
        "benchmark": "retarget_quality",
        "robot": args.robot,
        "machine": {"cpu": platform.machine(), "cores": os.cpu_count()},
        "clips": {},
    }
    for p in paths:
        clip = load_clip(p)
        if clip.skeleton == "cmu":
            clip = clip.slice(1)  # Frame 0 is a T-pose added by the BVH converter.
        if clip.skeleton not in retargeters:
            retargeters[clip.skeleton] = Retargeter(args.robot, clip.skeleton, retarget_default())
        report = retargeters[clip.skeleton].run(clip).report
        report["input"] = p.name
        out["clips"][p.name] = report
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
