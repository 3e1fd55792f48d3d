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

    # retarget with holosoma, then score the result with holosoma's own evaluation
    python benchmarks/peer_holosoma.py --peer-python /work/peer_venv/bin/python \
        --clip /work/shared/data/holosoma_climb/mocap_climb_seq_0 --out /work/peer_out/seq_0 \
        [--max-frames 400]
    # only score a result that someone else produced, with holosoma's own evaluation
    python benchmarks/peer_holosoma.py --peer-python /work/peer_venv/bin/python \
        --clip /work/shared/data/holosoma_climb/mocap_climb_seq_0 --out /tmp/peer_eval \
        --evaluate RESULT.npz

The clip is staged under ``OUT/peer_data/<clip>/`` (holosoma writes scaled scene files next to its
input, and needs the G1+boxes scene XML from its own demo data).  Its result is written to
``OUT/result/<clip>_original.npz`` (keys ``qpos`` (T, 36) = [xyz, quat wxyz, 29 G1 joints],
``human_joints`` (T, 53, 3) scaled human, ``fps`` = 30, ``cost``).  One JSON object goes to stdout.

With ``--evaluate RESULT.npz`` nothing is retargeted: RESULT.npz must hold ``qpos`` (T, 36) in the
same layout, in holosoma's world frame (z up, the clip's boxes scaled by 1.32 / 1.78 about the
origin, floor at z = 0) at 30 fps, frame t being 120 fps input frame 4 t, T at most the clip's
30 fps frame count; an optional scalar ``cost`` is holosoma's optimisation cost.  It is copied to
``OUT/result/<clip>_original.npz`` (``qpos``, ``cost`` (NaN when RESULT.npz has none: then
``opt_cost`` is reported as null and ``opt_cost_meaningful`` is false), ``fps``) and scored; the
evaluation compares frame t with human frame 4 t, so a shorter result is scored on its prefix.
RESULT.npz is checked (and copied) before ``OUT/result`` is emptied, so it may lie there.
Caveat: holosoma's ``contact_preservation`` is 1.0 for any qpos on these clips (its
``mj_geomDistance`` is capped at distmax 0.1 = its contact threshold, and it never sets the robot
to frame t), so only penetration and sliding say anything about a result.

Exit code 2: peer python or holosoma missing, peer mujoco >= 4, or a bad clip or RESULT.npz;
1: a holosoma run failed or its evaluation printed no metrics.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

SCENE_XML = "g1_29dof_spherehand_w_multi_boxes.xml"
ROBOT_URDF = "models/g1/g1_29dof_spherehand.urdf"
DOWNSAMPLE = 4  # holosoma keeps every 4th frame of the 120 fps mocap and calls it 30 fps
NQ = 36  # free joint (7) + 29 G1 joints; the boxes are static, so holosoma's scene has no more
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

# argv: RESULT.npz, destination npz, max frames, qpos width, clip length in words.  Prints {"error": ...} or a summary;
# writes atomically (temp file + rename) only what holosoma's robot_terrain evaluation reads.
PREPARE = """import json, os, sys, numpy as np
src, dst, max_t, nq, clip_len = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
def fail(msg):
    print(json.dumps({'error': ' '.join(str(msg).split())}))
    sys.exit(0)
try:
    d = np.load(src, allow_pickle=False)
except Exception as exc:
    fail(f'cannot read it: {exc}')
if not hasattr(d, 'files'):
    fail('it is a single .npy array, not an npz archive holding qpos')
keys = list(d.files)
if 'qpos' not in keys:
    fail(f'no qpos array (keys: {keys}); expected qpos (T, {nq})')
q = d['qpos']
if q.ndim != 2 or q.shape[1] != nq or not np.issubdtype(q.dtype, np.number):
    fail(f'qpos has shape {tuple(q.shape)} and dtype {q.dtype}; expected numbers of shape (T, {nq})')
if q.shape[0] < 2:
    fail(f'qpos has {q.shape[0]} frames; the evaluation needs at least 2')
if q.shape[0] > max_t:
    fail(f'qpos has {q.shape[0]} frames but the clip has only {clip_len}')
if not np.isfinite(q).all():
    fail(f'qpos has non-finite values in frames {np.flatnonzero(~np.isfinite(q).all(1))[:5].tolist()}')
cost = float('nan')
if 'cost' in keys:
    c = d['cost']
    if c.size != 1 or not np.issubdtype(c.dtype, np.number):
        fail(f'cost has shape {tuple(c.shape)} and dtype {c.dtype}; expected one number')
    cost = float(c.reshape(()))
tmp = dst + '.tmp'
with open(tmp, 'wb') as f:
    np.savez(f, qpos=q.astype(np.float64), cost=np.float64(cost), fps=np.int64(30))
os.replace(tmp, dst)
print(json.dumps({'frames': int(q.shape[0]), 'cost_given': 'cost' in keys, 'keys': keys}))"""

DEEP = """import json, sys, mujoco, numpy as np
xml, npz, tol = sys.argv[1], sys.argv[2], float(sys.argv[3])
m = mujoco.MjModel.from_xml_path(xml)
d = mujoco.MjData(m)
q = np.load(npz)['qpos']
name = lambda g: m.geom(g).name or m.body(m.geom_bodyid[g]).name
scene = [g for g in range(m.ngeom) if 'ground' in name(g) or 'box' in name(g).lower()]
robot = [g for g in range(m.ngeom) if g not in scene and m.geom_bodyid[g] > 0
         and (m.geom_contype[g] or m.geom_conaffinity[g])]
ft, out = np.zeros(6), []
for t in range(len(q)):
    d.qpos[:] = 0.0
    d.qpos[: q.shape[1]] = q[t]
    mujoco.mj_kinematics(m, d)
    for g in robot:
        for o in scene:
            dist = mujoco.mj_geomDistance(m, d, g, o, 0.05, ft)
            if dist < -tol:
                out.append([t, name(g), name(o), round(-1000 * dist, 1)])
print(json.dumps(out))"""
"""Every robot geom deeper than holosoma's tolerance in the floor or a box, per frame, on
holosoma's own model (its geoms are not ours: sphere hands, the foot mesh)."""

PENETRATION_TOL = 0.01
"""holosoma's evaluation counts a frame as penetrating past this depth [m]."""

METRIC_RE = re.compile(r"^(\w+): mean=([-+\d.eEinfna]+), std=([-+\d.eEinfna]+)\s*$", re.M)
TQDM_RE = re.compile(r"(\d+)/(\d+) \[(?:(\d+):)?(\d+):(\d+)<")


class UsageError(Exception):
    """A problem with the inputs or the peer installation (exit code 2)."""


@dataclass(frozen=True, kw_only=True)
class Staged:
    """A clip staged for holosoma under OUT, with the peer it is run by."""

    python: str
    version: str
    mujoco: str
    pkg: Path  # the holosoma_retargeting package folder (the cwd of every run)
    clip: Path
    out: Path
    data_root: Path  # OUT/peer_data: holosoma's --data_path / --data_dir
    res_dir: Path  # OUT/result: holosoma's --save_dir / --res_dir
    frames_raw: int  # 120 fps frames of the staged clip (after --max-frames)

    @property
    def result(self) -> Path:
        """The file holosoma's evaluation scores (it globs ``*_original.npz`` in res_dir)."""
        return self.res_dir / f"{self.clip.name}_original.npz"

    @property
    def frames_used(self) -> int:
        """30 fps frames holosoma makes of the clip (every DOWNSAMPLE-th 120 fps frame)."""
        return len(range(0, self.frames_raw, DOWNSAMPLE))

    @property
    def urdf_args(self) -> list[str]:
        # Only the URDF's file name matters: it selects the *_spherehand_w_multi_boxes scene XML.
        return ["--robot-config.robot-urdf-file", str(self.pkg / ROBOT_URDF)]

    def head(self) -> dict[str, object]:
        """The report fields both modes share."""
        return {
            "peer": "holosoma-retargeting",
            "peer_version": self.version,
            "peer_mujoco": self.mujoco,
            "robot": "g1_29dof_spherehand",
            "clip": self.clip.name,
            "frames_in_120fps": self.frames_raw,
            "frames_in_used": self.frames_used,
        }


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
    """Copy the clip to ROOT/<clip> with absolute mesh paths, adding holosoma's scene XML.

    Returns:
        The staged human motion ``.npy`` (what holosoma reads).
    """
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
    staged_npy = dst / npys[0].name
    if max_frames:
        run_py(python, TRUNCATE, str(npys[0]), str(staged_npy), str(max_frames))
    else:
        shutil.copy2(npys[0], staged_npy)
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
    return staged_npy


def stage(args: argparse.Namespace) -> Staged:
    """Probe the peer and stage the clip under OUT/peer_data (OUT/result is left alone)."""
    version, mj_version, pkg = probe_peer(args.peer_python, args.allow_mujoco4)
    clip = args.clip.resolve()
    if not clip.is_dir():
        raise UsageError(f"clip folder not found: {clip}")
    out = args.out.resolve()
    data_root, res_dir = out / "peer_data", out / "result"
    if args.evaluate is not None:
        evaluated = args.evaluate.resolve()
        if not evaluated.is_file():
            raise UsageError(f"--evaluate: file not found: {evaluated}")
    npy = stage_clip(args.peer_python, pkg, clip, data_root, args.max_frames)
    shapes = json.loads(run_py(args.peer_python, SHAPES, str(npy)))
    return Staged(
        python=args.peer_python, version=version, mujoco=mj_version, pkg=pkg, clip=clip,
        out=out, data_root=data_root, res_dir=res_dir,
        frames_raw=int(shapes[str(npy)]["shape"][0]),
    )  # fmt: skip


def fresh_res_dir(st: Staged) -> None:
    """Empty OUT/result: holosoma's evaluation scores every ``*_original.npz`` in it."""
    if st.res_dir.exists():
        shutil.rmtree(st.res_dir)
    st.res_dir.mkdir(parents=True)


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


def parse_metrics(log: str) -> dict[str, dict[str, float | None]]:
    """holosoma's printed ``name: mean=..., std=...`` lines; NaN and inf become None (JSON)."""

    def num(text: str) -> float | None:
        value = float(text)
        return value if math.isfinite(value) else None

    return {k: {"mean": num(mu), "std": num(sd)} for k, mu, sd in METRIC_RE.findall(log)}


def run_eval(st: Staged, nice: int) -> tuple[list[str], float, str, dict[str, object]]:
    """Run holosoma's evaluation on ``st.result``; returns (command, wall s, log, metrics)."""
    cmd = [st.python, str(st.pkg / "evaluation/eval_retargeting.py"),
           "--res_dir", str(st.res_dir), "--data_dir", str(st.data_root),
           "--data_type", "robot_terrain", *st.urdf_args]  # fmt: skip
    log_path = st.out / "eval.log"
    wall, log = run_logged(cmd, st.pkg, log_path, nice)
    metrics: dict[str, object] = dict(parse_metrics(log))
    if not metrics:  # e.g. "No evaluation results produced." when qpos cannot be read
        print(f"error: holosoma's evaluation printed no metrics (log: {log_path})", file=sys.stderr)
        raise SystemExit(1)
    return cmd, wall, log, metrics


def retarget_and_evaluate(st: Staged, nice: int) -> dict[str, object]:
    """Retarget the staged clip with holosoma, time it, and score it with holosoma's evaluation."""
    retarget_cmd = [st.python, str(st.pkg / "examples/robot_retarget.py"),
                    "--data_path", str(st.data_root), "--task-type", "climbing",
                    "--task-name", st.clip.name, "--data_format", "mocap", *st.urdf_args,
                    "--save_dir", str(st.res_dir)]  # fmt: skip
    rt_wall, rt_log = run_logged(retarget_cmd, st.pkg, st.out / "retarget.log", nice)
    eval_cmd, ev_wall, ev_log, metrics = run_eval(st, nice)

    arrays = json.loads(run_py(st.python, SHAPES, str(st.result)))[str(st.result)]
    frames_out = arrays["qpos"]["shape"][0]
    loops = TQDM_RE.findall(rt_log)
    loop_s = None
    if loops:
        _, _, h, m, s = loops[-1]
        loop_s = int(h or 0) * 3600 + int(m) * 60 + int(s)
    return {
        **st.head(),
        "frames_out": frames_out,
        "output_fps": arrays.get("fps", {}).get("value"),
        "wall_s": round(rt_wall, 2),
        "frames_per_s": round(frames_out / rt_wall, 3),
        "solve_loop_s_tqdm": loop_s,
        "solve_loop_frames_per_s": round(frames_out / loop_s, 3) if loop_s else None,
        "eval_wall_s": round(ev_wall, 2),
        "metrics": metrics,
        "eval_raw": ev_log.strip(),
        "output_npz": str(st.result),
        "output_arrays": arrays,
        "qpos_layout": QPOS_LAYOUT,
        "commands": {"retarget": retarget_cmd, "eval": eval_cmd, "cwd": str(st.pkg)},
    }


def write_eval_input(st: Staged, evaluated: Path) -> dict[str, object]:
    """Check RESULT.npz, empty OUT/result and write it there as ``st.result`` for holosoma.

    Raises:
        UsageError: RESULT.npz is unreadable or its qpos does not fit the clip (nothing emptied).
    """
    clip_len = (
        f"{st.frames_used} frames at 30 fps (every {DOWNSAMPLE}th of {st.frames_raw} at 120 fps)"
    )
    checked = st.out / "evaluate_input.npz"  # outside res_dir: RESULT.npz may lie in there
    info = json.loads(run_py(st.python, PREPARE, str(evaluated), str(checked),
                             str(st.frames_used), str(NQ), clip_len))  # fmt: skip
    if "error" in info:
        raise UsageError(f"--evaluate {evaluated}: {info['error']}")
    fresh_res_dir(st)
    checked.replace(st.result)
    return info


def evaluate_only(
    st: Staged, evaluated: Path, info: dict[str, object], nice: int
) -> dict[str, object]:
    """Score a result someone else produced (written by write_eval_input) with holosoma's eval."""
    eval_cmd, ev_wall, ev_log, metrics = run_eval(st, nice)
    cost_given = bool(info["cost_given"])
    # Where its penetration check fires: the pairs, on the scaled scene its evaluation wrote.
    scaled = sorted((st.data_root / st.clip.name).glob("*_w_multi_boxes_scaled_*.xml"))
    deep = (
        json.loads(run_py(st.python, DEEP, str(scaled[0]), str(st.result), str(PENETRATION_TOL)))
        if scaled
        else None
    )
    report: dict[str, object] = {
        **st.head(),
        "frames_out": info["frames"],
        "evaluated": str(evaluated),
        "evaluated_keys": info["keys"],
        "eval_input_npz": str(st.result),
        "opt_cost_meaningful": cost_given,
    }
    if not cost_given:
        report["opt_cost_note"] = "RESULT.npz has no cost: NaN was written, opt_cost is not a cost"
    return {
        **report,
        "eval_wall_s": round(ev_wall, 2),
        "metrics": metrics,
        "penetrating_pairs": deep,
        "eval_raw": ev_log.strip(),
        "qpos_layout": QPOS_LAYOUT,
        "commands": {"eval": eval_cmd, "cwd": str(st.pkg)},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--peer-python", default="/work/peer_venv/bin/python", help="holosoma venv")
    ap.add_argument("--clip", type=Path, required=True, help="a holosoma_climb clip folder")
    ap.add_argument("--out", type=Path, required=True, help="staged data, result npz, logs")
    ap.add_argument("--max-frames", type=int, help="only the first N 120 fps input frames")
    ap.add_argument(
        "--evaluate",
        type=Path,
        metavar="RESULT.npz",
        help="do not retarget: score this qpos (T, 36) with holosoma's evaluation",
    )
    ap.add_argument("--nice", type=int, default=5, help="niceness of the runs (0: none)")
    ap.add_argument("--allow-mujoco4", action="store_true", help="run anyway (wrong results)")
    args = ap.parse_args()
    evaluated: Path | None = args.evaluate.resolve() if args.evaluate is not None else None
    try:
        st = stage(args)
        info = None
        if evaluated is not None:
            info = write_eval_input(st, evaluated)
        else:
            fresh_res_dir(st)
    except (UsageError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if evaluated is not None and info is not None:
        report = evaluate_only(st, evaluated, info, args.nice)
    else:
        report = retarget_and_evaluate(st, args.nice)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
