"""Run and time the PEER retargeter (OmniRetarget's ``holosoma-retargeting`` 0.1.0) on a climb clip.

holosoma needs numpy 2.3.5 and cvxpy, so it lives in its own venv and is only ever run as a
subprocess with that venv's python; nothing from it is imported here (this script is stdlib only).

Setup (once, outside the repo)::

    python3 -m venv /work/peer_venv
    /work/peer_venv/bin/pip install torch==2.13.0          # local CPU wheel, install first
    /work/peer_venv/bin/pip install holosoma-retargeting==0.1.0
    # it does not pin mujoco; under mujoco 4 its joint Jacobians are zero (joints never move):
    /work/peer_venv/bin/pip uninstall -y mujoco mujoco-core mujoco-studio
    /work/peer_venv/bin/pip install mujoco==3.3.7

Usage::

    python benchmarks/peer_holosoma.py --peer-python /work/peer_venv/bin/python \
        --clip /work/shared/data/holosoma_climb/mocap_climb_seq_0 --out /work/peer_out/seq_0 \
        [--max-frames 400]

The clip is staged under ``OUT/peer_data/<clip>/`` (holosoma writes scaled scene files next to its
input, and needs the G1+boxes scene XML from its own demo data).  Its result is written to
``OUT/result/<clip>_original.npz`` (keys ``qpos`` (T, 36) = [xyz, quat wxyz, 29 G1 joints],
``human_joints`` (T, 53, 3) scaled human, ``fps`` = 30, ``cost``).  One JSON object goes to stdout.
Exit code 2: peer python or holosoma missing, or peer mujoco >= 4; 1: a holosoma run failed.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

SCENE_XML = "g1_29dof_spherehand_w_multi_boxes.xml"
ROBOT_URDF = "models/g1/g1_29dof_spherehand.urdf"
DOWNSAMPLE = 4  # holosoma keeps every 4th frame of the 120 fps mocap and calls it 30 fps
QPOS_LAYOUT = "[0:3] pelvis pos (m, world, z up), [3:7] pelvis quat wxyz, [7:36] 29 G1 joints"

PROBE = """import importlib.metadata as md, importlib.util as u, json, pathlib
s = u.find_spec('holosoma_retargeting')
print(json.dumps({'version': md.version('holosoma-retargeting'), 'mujoco': md.version('mujoco'),
                  'pkg': str(pathlib.Path(s.origin).parent) if s and s.origin else None}))"""

SHAPES = """import json, sys, numpy as np
out = {}
for p in sys.argv[1:]:
    d = np.load(p)
    desc = lambda a: {'shape': list(a.shape), 'dtype': str(a.dtype)}
    out[p] = {k: desc(d[k]) for k in d.files} if p.endswith('.npz') else desc(d)
    if p.endswith('.npz') and 'fps' in d.files:
        out[p]['fps']['value'] = float(d['fps'])
print(json.dumps(out))"""

TRUNCATE = "import sys, numpy as np; np.save(sys.argv[2], np.load(sys.argv[1])[: int(sys.argv[3])])"

METRIC_RE = re.compile(r"^(\w+): mean=([-+\d.eEinfna]+), std=([-+\d.eEinfna]+)\s*$", re.M)
TQDM_RE = re.compile(r"(\d+)/(\d+) \[(?:(\d+):)?(\d+):(\d+)<")


class UsageError(Exception):
    """A problem with the inputs or the peer installation (exit code 2)."""


def run_py(python: str, code: str, *args: str) -> str:
    res = subprocess.run([python, "-c", code, *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise UsageError(
            f"{python} -c ... failed: {res.stderr.strip().splitlines()[-1:] or res.returncode}"
        )
    return res.stdout


def probe_peer(python: str, allow_mujoco4: bool) -> tuple[str, str, Path]:
    exe = Path(python)
    if not exe.is_file():
        raise UsageError(
            f"peer python not found: {python} (create /work/peer_venv, see the module docstring)"
        )
    try:
        info = json.loads(run_py(python, PROBE))
    except (UsageError, json.JSONDecodeError) as exc:
        raise UsageError(f"holosoma-retargeting is not installed for {python}: {exc}") from None
    if not info.get("pkg"):
        raise UsageError(f"holosoma_retargeting package not importable by {python}")
    if int(info["mujoco"].split(".")[0]) >= 4 and not allow_mujoco4:
        # mujoco 4 enums break holosoma's `jnt_type in (mjJNT_HINGE, ...)`: joints stay frozen.
        raise UsageError(
            f"peer has mujoco {info['mujoco']}; holosoma 0.1.0 needs mujoco<4 "
            f"(run: {python} -m pip uninstall -y mujoco mujoco-core mujoco-studio && "
            f"{python} -m pip install mujoco==3.3.7)"
        )
    return str(info["version"]), str(info["mujoco"]), Path(info["pkg"])


def stage_clip(python: str, pkg: Path, clip: Path, root: Path, max_frames: int | None) -> Path:
    """Copy the clip to ROOT/<clip> with absolute mesh paths, adding holosoma's scene XML."""
    npys = sorted(clip.glob("*.npy"))
    if len(npys) != 1 or not (clip / "box_assets.xml").is_file():
        raise UsageError(
            f"{clip} is not a holosoma climbing clip (need one *.npy and box_assets.xml)"
        )
    dst = root / clip.name
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for name in ("multi_boxes.obj", "multi_boxes.urdf", "box_body.xml"):
        shutil.copy2(clip / name, dst / name)
    shutil.copytree(clip / "box_models", dst / "box_models")
    if max_frames:
        run_py(python, TRUNCATE, str(npys[0]), str(dst / npys[0].name), str(max_frames))
    else:
        shutil.copy2(npys[0], dst / npys[0].name)
    # Mesh paths in box_assets.xml are relative to the scene's meshdir: make them absolute.
    assets = (clip / "box_assets.xml").read_text()
    assets = re.sub(
        r'file="[^"]*box_models/([^"/]+)"', lambda m: f'file="{dst / "box_models" / m[1]}"', assets
    )
    (dst / "box_assets.xml").write_text(assets)
    scenes = [clip / SCENE_XML, *sorted(pkg.glob(f"demo_data/climb/*/{SCENE_XML}"))]
    scene = next((p for p in scenes if p.is_file()), None)
    if scene is None:
        raise UsageError(f"no {SCENE_XML} in {clip} or in the holosoma demo data")
    text = re.sub(r'meshdir="[^"]*"', f'meshdir="{pkg / "models/g1/meshes"}"', scene.read_text())
    (dst / SCENE_XML).write_text(text)
    return npys[0]


def run_logged(cmd: list[str], cwd: Path, log: Path, nice: int) -> tuple[float, str]:
    if nice > 0 and shutil.which("nice"):
        cmd = ["nice", "-n", str(nice), *cmd]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    text = res.stdout + res.stderr
    log.write_text(text)
    if res.returncode != 0:
        tail = "\n".join(text.strip().splitlines()[-15:])
        print(
            f"error: {' '.join(cmd[:4])} ... exited {res.returncode} (log: {log})\n{tail}",
            file=sys.stderr,
        )
        raise SystemExit(1)
    return wall, text


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--peer-python", default="/work/peer_venv/bin/python", help="holosoma venv")
    ap.add_argument("--clip", type=Path, required=True, help="a holosoma_climb clip folder")
    ap.add_argument("--out", type=Path, required=True, help="staged data, result npz, logs")
    ap.add_argument("--max-frames", type=int, help="only the first N 120 fps input frames")
    ap.add_argument("--nice", type=int, default=5, help="niceness of the runs (0: none)")
    ap.add_argument("--allow-mujoco4", action="store_true", help="run anyway (wrong results)")
    args = ap.parse_args()
    try:
        version, mj_version, pkg = probe_peer(args.peer_python, args.allow_mujoco4)
        clip = args.clip.resolve()
        if not clip.is_dir():
            raise UsageError(f"clip folder not found: {clip}")
        out = args.out.resolve()
        data_root, res_dir = out / "peer_data", out / "result"
        if res_dir.exists():
            shutil.rmtree(res_dir)
        res_dir.mkdir(parents=True)
        src_npy = stage_clip(args.peer_python, pkg, clip, data_root, args.max_frames)
    except (UsageError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    # Only the URDF's file name matters: it selects the *_spherehand_w_multi_boxes scene XML.
    urdf = ["--robot-config.robot-urdf-file", str(pkg / ROBOT_URDF)]
    retarget_cmd = [args.peer_python, str(pkg / "examples/robot_retarget.py"),
                    "--data_path", str(data_root), "--task-type", "climbing",
                    "--task-name", clip.name, "--data_format", "mocap", *urdf,
                    "--save_dir", str(res_dir)]  # fmt: skip
    rt_wall, rt_log = run_logged(retarget_cmd, pkg, out / "retarget.log", args.nice)
    result = res_dir / f"{clip.name}_original.npz"
    eval_cmd = [args.peer_python, str(pkg / "evaluation/eval_retargeting.py"),
                "--res_dir", str(res_dir), "--data_dir", str(data_root),
                "--data_type", "robot_terrain", *urdf]  # fmt: skip
    ev_wall, ev_log = run_logged(eval_cmd, pkg, out / "eval.log", args.nice)

    shapes = json.loads(run_py(args.peer_python, SHAPES, str(src_npy), str(result)))
    frames_raw = shapes[str(src_npy)]["shape"][0]
    frames_raw = min(frames_raw, args.max_frames) if args.max_frames else frames_raw
    arrays = shapes[str(result)]
    frames_out = arrays["qpos"]["shape"][0]
    loops = TQDM_RE.findall(rt_log)
    loop_s = None
    if loops:
        _, _, h, m, s = loops[-1]
        loop_s = int(h or 0) * 3600 + int(m) * 60 + int(s)
    metrics = {k: {"mean": float(mu), "std": float(sd)} for k, mu, sd in METRIC_RE.findall(ev_log)}
    report = {
        "peer": "holosoma-retargeting",
        "peer_version": version,
        "peer_mujoco": mj_version,
        "robot": "g1_29dof_spherehand",
        "clip": clip.name,
        "frames_in_120fps": frames_raw,
        "frames_in_used": len(range(0, frames_raw, DOWNSAMPLE)),
        "frames_out": frames_out,
        "output_fps": arrays.get("fps", {}).get("value"),
        "wall_s": round(rt_wall, 2),
        "frames_per_s": round(frames_out / rt_wall, 3),
        "solve_loop_s_tqdm": loop_s,
        "solve_loop_frames_per_s": round(frames_out / loop_s, 3) if loop_s else None,
        "eval_wall_s": round(ev_wall, 2),
        "metrics": metrics,
        "eval_raw": ev_log.strip(),
        "output_npz": str(result),
        "output_arrays": arrays,
        "qpos_layout": QPOS_LAYOUT,
        "commands": {"retarget": retarget_cmd, "eval": eval_cmd, "cwd": str(pkg)},
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
