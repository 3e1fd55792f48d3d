"""Interaction-mesh retargeting against the kinematic method on the real climbing clips.

For each clip of ``../shared/data/holosoma_climb`` (or ``--clips``), retargets to the G1 at
30 fps (holosoma's frames: every 4th of the 120 fps capture) with ``--method
interaction-mesh`` and reports, side by side with its kinematic warm start on the same scene:
robot-scene penetration, contact preservation, foot skating, joint-limit violations, key-point
error, jerk, and time per frame. Prints one JSON object per clip, then a summary.

The peer, holosoma's own retargeter, runs in its own virtual environment: see
``benchmarks/peer_holosoma.py``; ``--peer-python`` runs it on the same clips in the same run.

Usage: .venv/bin/python benchmarks/interaction_retarget.py [--clips DIR ...] [--fps 30]
    [--peer-python /path/to/peer/venv/bin/python]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from humimic.configs import InteractionConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.retarget import Retargeter
from humimic.retarget.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "holosoma_climb"
_KEYS = ("max_scene_penetration_mm", "mean_scene_penetration_mm", "scene_penetration_frames",
         "human_contacts", "contact_preservation", "scene_foot_skating_mm_per_s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clips", type=Path, nargs="+",
                        default=sorted(p for p in DATA.glob("mocap_climb_seq_*") if p.is_dir()))  # fmt: skip
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--peer-python", type=Path, default=None)
    args = parser.parse_args()
    if not args.clips:
        raise SystemExit(f"no clips: expected holosoma_climb clip folders under {DATA}")
    t0 = time.perf_counter()
    rt = Retargeter("g1", "holosoma", RetargetConfig(fps=args.fps), method="interaction-mesh",
                    mesh=InteractionConfig())  # fmt: skip
    rows = []
    for folder in args.clips:
        clip = load_clip(next(folder.glob("*.npy")))
        scene = load_scene(folder)
        t = time.perf_counter()
        result = rt.run(clip, scene=scene)
        r = result.report
        total = time.perf_counter() - t
        row = {
            "clip": folder.name,
            "frames": r["frames"],
            "fps": r["fps"],
            "interaction_mesh": {
                **{k: r[k] for k in _KEYS},
                "joint_limit_violations": r["joint_limit_violations"],
                "max_ground_penetration_mm": r["max_ground_penetration_mm"],
                "keypoint_error_mm_mean": r["keypoint_error_mm_mean"],
                "mean_joint_jerk": r["mean_joint_jerk"],
                "interaction_frames_per_second": r["interaction_frames_per_second"],
                "frames_per_second_with_kinematic_pass": r["frames"] / total,
            },
            "kinematic": {
                **{k: r["kinematic"][k] for k in _KEYS},
                "frames_per_second": r["frames"] / r["kinematic_seconds"],
            },
        }
        if args.peer_python is not None:
            contacts = (result.motion.extras or {})["scene_contacts"]
            row["holosoma"] = _peer(args.peer_python, folder, rt, contacts)
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {
        "benchmark": "interaction_retarget",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "robot": "g1",
        "fps": args.fps,
        "clips": rows,
        "seconds": time.perf_counter() - t0,
    }
    print(json.dumps(out, indent=2))


def _peer(python: Path, folder: Path, rt: Retargeter, contacts: np.ndarray) -> dict:
    """holosoma's retargeter on the same clip (``benchmarks/peer_holosoma.py``), its own
    evaluation, and its result measured with our scene metrics."""
    out = Path("/tmp") / f"humimic_peer_{folder.name}"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "peer_holosoma.py"),
           "--peer-python", str(python), "--clip", str(folder), "--out", str(out)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        return {"error": res.stderr.strip()[-2000:]}
    peer = json.loads(res.stdout)
    peer.pop("eval_raw", None)
    peer["our_metrics"] = _our_metrics_of_peer(Path(peer["output_npz"]), folder, rt, contacts)
    return peer


HOLOSOMA_SCALE = 1.32 / 1.78
"""holosoma's fixed human and scene scale (G1 height over human height)."""


def _our_metrics_of_peer(result: Path, folder: Path, rt: Retargeter, contacts: np.ndarray) -> dict:
    """Our scene metrics on holosoma's result, in holosoma's own frame (its scene: the boxes
    scaled by 0.7416 about the origin; its human: the capture, toes' lowest point moved to 0,
    scaled the same), on our G1 model (same joints; our hands are meshes, its are spheres).
    The human's contacts are ours (``contacts``, from our run on the same frames), so both
    results are scored on the same (frame, key point, object) contacts."""
    from humimic.retarget.interaction import contact_bodies
    from humimic.retarget.kinematic import ik_model
    from humimic.retarget.metrics import evaluate_scene

    with np.load(result) as z:
        qpos = z["qpos"]
    m = rt.map
    scene = load_scene(folder).to_robot(scale=HOLOSOMA_SCALE, yaw=0.0, origin=np.zeros(3),
                                        ground=0.0, z_offset=0.0)  # fmt: skip
    model, _ = ik_model(rt.robot, m, scene=scene)
    report, _ = evaluate_scene(model, qpos, scene, 30.0, keypoint_bodies=contact_bodies(m),
                               human_contacts=contacts,
                               foot_bodies=[f.body for f in m.feet.values()])  # fmt: skip
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    out = {k: getattr(report, k) for k in _KEYS}
    out["joint_limit_violations"] = int(
        np.sum((qpos[:, 7:] < lo - 1e-6) | (qpos[:, 7:] > hi + 1e-6))
    )
    return out


if __name__ == "__main__":
    main()
