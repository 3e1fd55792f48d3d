"""Interaction-mesh retargeting against the kinematic method on the real climbing clips.

For each clip of ``../shared/data/holosoma_climb`` (or ``--clips``), retargets to the G1 at
30 fps (holosoma's frames: every 4th of the 120 fps capture) with ``--method
interaction-mesh`` and reports, side by side with its kinematic warm start on the same scene:
robot-scene penetration, contact preservation, foot skating, joint-limit violations, key-point
error, jerk, and time per frame. Prints one JSON object per clip, then a summary.

The peer, holosoma's own retargeter, runs in its own virtual environment: see
``benchmarks/peer_holosoma.py``; ``--peer-python`` runs it on the same clips in the same run.

With ``--peer-python``, the clips are retargeted at holosoma's fixed scale (1.32 / 1.78; ours
is otherwise the clip's leg ratio, about 1.8% larger), so that holosoma's own evaluation can
score our result in its scene (moved into its frame) beside its own result. With
``--no-peer-retarget`` holosoma is not rerun; our metrics are then given for the result its
last full run left in ``/tmp/humimic_peer_<clip>`` where there is one.

Usage: .venv/bin/python benchmarks/interaction_retarget.py [--clips DIR ...] [--fps 30]
    [--peer-python /path/to/peer/venv/bin/python [--no-peer-retarget]]
    [--scale holosoma|NUMBER] [--still-speed V] [--still-reach R] [--still-travel S]
    [--stick-height-scale H]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from humimic.configs import InteractionConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.datasets.scene import load_scene
from humimic.errors import InputError
from humimic.retarget import Retargeter
from humimic.retarget.interaction import feet_planted

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "holosoma_climb"
MESH_FLAGS = ("still_speed", "still_reach", "still_travel", "stick_height_scale")
"""``--mesh.*`` settings the benchmark takes (``--still-speed`` ...)."""
_KEYS = ("max_scene_penetration_mm", "mean_scene_penetration_mm", "scene_penetration_frames",
         "human_contacts", "contact_preservation", "scene_foot_skating_mm_per_s",
         "planted_foot_gap_mm", "floating_planted_feet")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clips", type=Path, nargs="+",
                        default=sorted(p for p in DATA.glob("mocap_climb_seq_*") if p.is_dir()))  # fmt: skip
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--peer-python", type=Path, default=None)
    parser.add_argument("--scale", default=None, type=_scale,
                        help="human-to-robot scale: a number, or 'holosoma' (1.32 / 1.78, "
                             "holosoma's); default: the leg ratio, or holosoma's with --peer-python")  # fmt: skip
    parser.add_argument(
        "--no-peer-retarget",
        action="store_true",
        help="with --peer-python: only holosoma's evaluation of our result",
    )
    for name in MESH_FLAGS:
        parser.add_argument(
            "--" + name.replace("_", "-"),
            type=float,
            default=None,
            help=f"--mesh.{name} for our retargeter (default: its default)",
        )
    args = parser.parse_args()
    if not args.clips:
        raise SystemExit(f"no clips: expected holosoma_climb clip folders under {DATA}")
    scale = args.scale
    if scale is None and args.peer_python is not None:
        scale = HOLOSOMA_SCALE  # holosoma's evaluation scores a result in its own scene.
    mesh = dataclasses.replace(
        InteractionConfig(),
        **{k: v for k in MESH_FLAGS if (v := getattr(args, k)) is not None},
    )  # fmt: skip
    try:
        mesh.validate()
    except InputError as e:
        parser.error(str(e))
    t0 = time.perf_counter()
    rt = Retargeter("g1", "holosoma", RetargetConfig(fps=args.fps, scale=scale),
                    method="interaction-mesh", mesh=mesh)  # fmt: skip
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
            # Where the clip's floor was put: planted toe height = floor_m + toe_clearance_m.
            "scene_floor": r["scene_floor"],
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
            extras = result.motion.extras or {}
            row["interaction_mesh"]["holosoma_evaluation"] = _peer_evaluation(
                args.peer_python, folder, result.motion.qpos, extras["scene_poses"]
            )
            planted = feet_planted(rt.map, extras["human_contacts"], extras["scene_contacts"])
            if not args.no_peer_retarget:
                row["holosoma"] = _peer(args.peer_python, folder, rt, extras["scene_contacts"],
                                        planted)  # fmt: skip
            elif (stored := _peer_dir(folder) / "result" / f"{folder.name}_original.npz").exists():
                row["holosoma"] = {  # Our metrics on the result of an earlier full run.
                    "stored_result": str(stored),
                    "our_metrics": _our_metrics_of_peer(stored, folder, rt,
                                                        extras["scene_contacts"], planted),
                }  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {
        "benchmark": "interaction_retarget",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "robot": "g1",
        "fps": args.fps,
        "scale": scale if scale is not None else "leg ratio",
        "mesh_config": dataclasses.asdict(mesh),
        "clips": rows,
        "seconds": time.perf_counter() - t0,
    }
    print(json.dumps(out, indent=2))


def _peer_dir(folder: Path) -> Path:
    """Where holosoma's run on a clip goes."""
    return Path("/tmp") / f"humimic_peer_{folder.name}"


def _peer(
    python: Path, folder: Path, rt: Retargeter, contacts: np.ndarray, planted: np.ndarray
) -> dict:
    """holosoma's retargeter on the same clip (``benchmarks/peer_holosoma.py``), its own
    evaluation, and its result measured with our scene metrics."""
    out = _peer_dir(folder)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "peer_holosoma.py"),
           "--peer-python", str(python), "--clip", str(folder), "--out", str(out)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        return {"error": res.stderr.strip()[-2000:]}
    peer = json.loads(res.stdout)
    peer.pop("eval_raw", None)
    peer["our_metrics"] = _our_metrics_of_peer(Path(peer["output_npz"]), folder, rt, contacts,
                                               planted)  # fmt: skip
    return peer


HOLOSOMA_SCALE = 1.32 / 1.78
"""holosoma's fixed human and scene scale (G1 height over human height)."""


def _scale(text: str) -> float:
    """``--scale``: ``holosoma`` or a positive number."""
    if text == "holosoma":
        return HOLOSOMA_SCALE
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected 'holosoma' or a positive number, got {text!r}")
    return value


def _to_holosoma_frame(qpos: np.ndarray, scene_poses: np.ndarray, folder: Path) -> np.ndarray:
    """Our result moved into holosoma's world frame (its scene: the boxes scaled by
    ``HOLOSOMA_SCALE`` about the capture's origin). Retargeted at that scale, our frame differs
    from it by a turn about z and a shift: the one that takes our first box onto its."""
    from humimic.transforms import matrix_to_quat, quat_mul, quat_to_matrix

    theirs = load_scene(folder).to_robot(scale=HOLOSOMA_SCALE, yaw=0.0, origin=np.zeros(3),
                                         ground=0.0, z_offset=0.0).objects[0].poses[0]  # fmt: skip
    ours = scene_poses[0, 0]
    rot = quat_to_matrix(theirs[3:]) @ quat_to_matrix(ours[3:]).T
    if not np.allclose(rot[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise SystemExit(f"{folder.name}: our frame and holosoma's differ by more than a yaw")
    out = qpos.copy()
    out[:, :3] = qpos[:, :3] @ rot.T + (theirs[:3] - rot @ ours[:3])
    out[:, 3:7] = quat_mul(np.broadcast_to(matrix_to_quat(rot), qpos[:, 3:7].shape), qpos[:, 3:7])
    return out


def _peer_evaluation(python: Path, folder: Path, qpos: np.ndarray, scene_poses: np.ndarray) -> dict:
    """holosoma's own evaluation of our result (``peer_holosoma.py --evaluate``), in its frame."""
    out = Path("/tmp") / f"humimic_ours_{folder.name}"
    out.mkdir(parents=True, exist_ok=True)
    npz = out / "ours.npz"
    np.savez(npz, qpos=_to_holosoma_frame(qpos, scene_poses, folder))
    cmd = [sys.executable, str(ROOT / "benchmarks" / "peer_holosoma.py"), "--peer-python",
           str(python), "--clip", str(folder), "--out", str(out / "eval"), "--evaluate", str(npz)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        return {"error": res.stderr.strip()[-2000:]}
    report = json.loads(res.stdout)
    return {k: report[k] for k in ("metrics", "penetrating_pairs", "eval_wall_s")}


def _our_metrics_of_peer(
    result: Path, folder: Path, rt: Retargeter, contacts: np.ndarray, planted: np.ndarray
) -> dict:
    """Our scene metrics on holosoma's result, in holosoma's own frame (its scene: the boxes
    scaled by 0.7416 about the origin; its human: the capture, toes' lowest point moved to 0,
    scaled the same), on our G1 model (same joints; our hands are meshes, its are spheres).
    The human's contacts are ours (``contacts`` and the feet's ``planted``, from our run on
    the same frames), so both results are scored on the same contacts."""
    from humimic.retarget.interaction import contact_bodies
    from humimic.retarget.metrics import evaluate_scene
    from humimic.retarget.robot_model import ik_model

    with np.load(result) as z:
        qpos = z["qpos"]
    m = rt.map
    scene = load_scene(folder).to_robot(scale=HOLOSOMA_SCALE, yaw=0.0, origin=np.zeros(3),
                                        ground=0.0, z_offset=0.0)  # fmt: skip
    model, _ = ik_model(rt.robot, m, scene=scene)
    report, _ = evaluate_scene(model, qpos, scene, 30.0, keypoint_bodies=contact_bodies(m),
                               human_contacts=contacts,
                               foot_bodies=[f.body for f in m.feet.values()],
                               feet_planted=planted)  # fmt: skip
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    out = {k: getattr(report, k) for k in _KEYS}
    out["joint_limit_violations"] = int(
        np.sum((qpos[:, 7:] < lo - 1e-6) | (qpos[:, 7:] > hi + 1e-6))
    )
    return out


if __name__ == "__main__":
    main()
