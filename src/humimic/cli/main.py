"""``humimic``: one console script, one subcommand per verb (tyro over dataclasses)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
import tyro

from humimic.configs import (
    DynamicsConfig,
    InteractionConfig,
    RetargetConfig,
    retarget_default,
    retarget_fast,
)
from humimic.configs.runs import (
    DistillSettings,
    EvalSettings,
    ExportSettings,
    LoopSettings,
    TrainSettings,
    check_device,
)
from humimic.errors import HumimicError, InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready

if TYPE_CHECKING:
    from humimic.motion import Motion

RETARGET_CONFIGS = {"default": retarget_default, "fast": retarget_fast}
"""Named retargeting configurations (factories); see :mod:`humimic.configs`."""

MAX_ROBUSTNESS = 1000
"""The most perturbed replays ``humimic refine --robustness`` makes for its report."""

_PRESET = ["default"]
"""The --preset found on the command line before parsing: the base the --ik.* flags change."""


def _scan_preset(argv: list[str]) -> str:
    for i, a in enumerate(argv):
        if a == "--preset" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--preset="):
            return a.split("=", 1)[1]
    return "default"


@dataclass(frozen=True, kw_only=True)
class RetargetCommand:
    """Retarget human motion clips (BVH, joint-position arrays) to a robot."""

    inputs: Annotated[tuple[Path, ...], tyro.conf.Positional]
    """Clip files (.bvh, .npy, .npz) or folders of them."""
    robot: str = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    out: Path
    """Output .npz for one input; an output folder for several inputs or a folder."""
    report: Path | None = None
    """Quality report (JSON) for one input; with several, one <name>.json per clip in --out."""
    units: str = "auto"
    """BVH units: auto, m, cm, mm, inch, or metres per file unit."""
    up: Literal["y", "z"] = "y"
    """Up axis of BVH files (arrays of positions are z up)."""
    skeleton: str | None = None
    """Skeleton name for the map (default: detected from the joint names)."""
    map: Path | None = None
    """Your own human-to-robot map (YAML); default: the shipped map for skeleton and robot."""
    menagerie_root: Path | None = None
    """A MuJoCo Menagerie folder (or the robot's own folder) to load the robot from."""
    start: int | None = None
    """First source frame to use (default: 1 for CMU files, whose frame 0 is a T-pose)."""
    preset: Literal["default", "fast"] = "default"
    """Named IK settings (humimic.configs); --ik.* flags change single fields on top of it."""
    ik: RetargetConfig = field(default_factory=lambda: RETARGET_CONFIGS[_PRESET[0]]())
    """IK settings (defaults: those of --preset)."""
    method: Literal["kinematic", "interaction-mesh", "dynamics"] = "kinematic"
    """kinematic (mink IK), interaction-mesh (keeps the contacts with --scene), or dynamics
    (kinematic, then humimic refine: a motion that replays open-loop in simulation)."""
    scene: Path | None = None
    """The scene of the clips (interaction-mesh): a scene .yaml, a mesh (.obj/.stl) or a
    folder with box_models/*.obj (holosoma's layout); 'auto': each clip's own folder."""
    mesh: InteractionConfig = field(default_factory=InteractionConfig)
    """Interaction-mesh settings."""
    dyn: DynamicsConfig = field(default_factory=DynamicsConfig)
    """Dynamics settings (--method dynamics; see humimic refine)."""
    quiet: bool = False
    """No progress bars; print only the report summary."""


@dataclass(frozen=True, kw_only=True)
class RefineCommand:
    """Make a motion dynamically feasible: sampling MPC in MuJoCo, so that its stored controls
    replay open-loop on the simulated robot (humimic.retarget.dynamics)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """A robot motion (.npz), e.g. from humimic retarget."""
    out: Path
    """The refined motion (.npz), with its dynamic section."""
    report: Path | None = None
    """Report (JSON): open-loop replays of the input and of the result, robustness, compute."""
    dyn: DynamicsConfig = field(default_factory=DynamicsConfig)
    """Sampler settings."""
    robustness: int = 8
    """Replays of the result on perturbed physics, for the report."""
    backend: Literal["cpu", "warp"] = "cpu"
    """Simulator of the sampled rollouts: cpu (mujoco.rollout) or warp (MuJoCo Warp on --device;
    humimic[gpu])."""
    device: str = "cpu"
    """Where the warp backend simulates (cuda)."""
    quiet: bool = False
    """No progress bar."""


@dataclass(frozen=True, kw_only=True)
class ReplayCommand:
    """Replay a refined motion's controls open-loop and check that they reproduce its
    stored states (exit code 1 if they differ by more than --tol)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """A motion with a dynamic section (humimic refine), .npz or .mcap."""
    tol: float = 1e-9
    """Largest accepted difference of qpos and qvel."""


@dataclass(frozen=True, kw_only=True)
class DemoCommand:
    """Fetch a real climbing clip (PyPI package holosoma-retargeting) and retarget it."""

    robot: str = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    out: Path = Path("out/demo")
    """Output folder."""
    clip: int = 0
    """Which climbing sequence (0-2)."""
    quiet: bool = False
    """No progress bars; print only the report."""


@dataclass(frozen=True, kw_only=True)
class ViewCommand:
    """Look at a motion in the browser, beside the human it came from (viser)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """Robot motion (.npz or .mcap)."""
    human: Path | None = None
    """The human clip it was retargeted from (.bvh, .npy, .npz), drawn as a skeleton."""
    scene: Path | None = None
    """Scene objects, in the clip's frame: a scene file (.yaml; moving objects follow the
    motion's scene_poses), a mesh file (.obj, .stl, .ply) or a folder of them."""
    rollout: Path | None = None
    """A rollout or robot log (.mcap with /qpos, or /base_pose and /joint_states). Default: the
    motion file's own /qpos when it is an MCAP that has one (``humimic eval --mcap``)."""
    host: str = "127.0.0.1"
    """Address to bind; 127.0.0.1 keeps the viewer on this machine (0.0.0.0 exposes it)."""
    port: int = 8080
    """TCP port (1-65535; 0: any free port). A taken port moves on to the next free one, and
    the printed URL says which."""
    frame: int = 0
    """Frame to show first."""
    screenshot: Path | None = None
    """Save a PNG of the viewer (headless Chromium, which must be installed) and exit."""
    duration: float | None = None
    """Stop after this many seconds (default: run until Ctrl-C)."""


@dataclass(frozen=True, kw_only=True)
class ConvertCommand:
    """Convert a motion between .npz and .mcap (lossless both ways)."""

    src: Annotated[Path, tyro.conf.Positional]
    """The motion to read (.npz or .mcap)."""
    dst: Annotated[Path, tyro.conf.Positional]
    """The file to write (.npz or .mcap); it must not be the source."""


@dataclass(frozen=True, kw_only=True)
class RobotsList:
    """List the registered robots."""


@dataclass(frozen=True, kw_only=True)
class RobotsExport:
    """Write the exact nominal MJCF humimic simulates with (meshes copied beside it)."""

    name: Annotated[str, tyro.conf.Positional]
    """Robot name."""
    out: Path
    """Output .xml file."""
    menagerie_root: Path | None = None
    """A MuJoCo Menagerie folder (or the robot's own folder) to load the robot from."""


@dataclass(frozen=True, kw_only=True)
class RobotsCommand:
    """Robot registry: list robots, export the nominal model."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[RobotsList, tyro.conf.subcommand("list")]
        | Annotated[RobotsExport, tyro.conf.subcommand("export")]
    ]
    """list or export."""


@dataclass(frozen=True, kw_only=True)
class SysidSimulate:
    """Write a realistic fixed-base robot log (MCAP) from the nominal model plus injected effects."""

    robot: str = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    inject: tyro.conf.UseAppendAction[tuple[str, ...]] = ()
    """An effect as EFFECT:JOINT[,JOINT...]=VALUE, e.g. coulomb_friction:left_knee_joint=2.0;
    repeat the flag for more."""
    duration: float = 40.0
    """Seconds."""
    seed: int = 0
    """Seed of the excitation signal and the sensor noise."""
    out: Path
    """Output .mcap file."""


@dataclass(frozen=True, kw_only=True)
class SysidResidual:
    """The nominal model's k-step open-loop prediction error on a robot log, per joint."""

    log: Annotated[Path, tyro.conf.Positional]
    """Robot log (.mcap): /joint_states, /joint_commands, metadata 'robot'."""
    horizon: float = 0.5
    """Prediction window [s]."""
    report: Path | None = None
    """Write the numbers as JSON here."""


@dataclass(frozen=True, kw_only=True)
class SysidDiagnose:
    """Find the joint-level effects the nominal model lacks in a robot log, size them, write
    the corrected model and a report (fit on the first 70%, scored on the last 30%)."""

    log: Annotated[Path, tyro.conf.Positional]
    """Robot log (.mcap)."""
    out_dir: Path
    """Folder for model.xml, report.json, report.md (with plots), residual_net.pt."""
    horizon: float = 0.5
    """Prediction window [s]."""
    residual_net: Literal["auto", "always", "never"] = "auto"
    """Fit a residual actuator network: when the effects leave the log unexplained (auto)."""


@dataclass(frozen=True, kw_only=True)
class SysidCommand:
    """Real2sim: simulate robot logs with injected effects; measure the simulator's residual."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[SysidSimulate, tyro.conf.subcommand("simulate")]
        | Annotated[SysidResidual, tyro.conf.subcommand("residual")]
        | Annotated[SysidDiagnose, tyro.conf.subcommand("diagnose")]
    ]
    """simulate, residual or diagnose."""


@dataclass(frozen=True, kw_only=True)
class FetchCommand:
    """Download public data sets for humimic at run time."""

    what: Annotated[Literal["climb"], tyro.conf.Positional] = "climb"
    """climb: the holosoma climbing clips with box meshes."""


def _clip_files(inputs: tuple[Path, ...], out: Path) -> list[tuple[Path, Path]]:
    """Input files, each with its output name (relative to its input folder, without suffix).

    Files inside the output folder are skipped, so outputs of an earlier run are not read.
    """
    from humimic.datasets import SUPPORTED_SUFFIXES

    out_dir = out.resolve()
    files: list[tuple[Path, Path]] = []
    for p in inputs:
        if p.is_dir():
            found = sorted(
                f
                for f in p.rglob("*")
                if f.suffix.lower() in SUPPORTED_SUFFIXES and out_dir not in f.resolve().parents
            )
            if not found:
                raise InputError(f"{p}: folder holds no {', '.join(SUPPORTED_SUFFIXES)} files")
            files += [(f, f.relative_to(p).with_suffix("")) for f in found]
        elif p.exists():
            files.append((p, Path(p.stem)))
        else:
            raise InputError(f"{p}: no such file or folder")
    seen: dict[Path, Path] = {}
    for f, name in files:
        if name in seen:
            raise InputError(f"{f} and {seen[name]} would both be written as {name}.npz")
        seen[name] = f
    return files


def run_retarget(cmd: RetargetCommand) -> list[dict]:
    """Run ``humimic retarget``; returns the reports.

    Every input is read and checked before any retargeting, so bad input fails the whole call
    before anything is written.
    """
    from tqdm import tqdm

    from humimic.datasets import HumanClip, load_bvh, load_clip
    from humimic.datasets.scene import Scene, load_scene
    from humimic.retarget import Retargeter
    from humimic.robots import get_robot

    get_robot(cmd.robot, "--robot")  # Unknown robot: fail before any work.
    cmd.ik.validate()
    cmd.mesh.validate()
    if cmd.method == "dynamics":
        from humimic.retarget.dynamics import physics_steps_per_frame
        from humimic.tracking.config import tracking_task

        cmd.dyn.validate()
        if physics_steps_per_frame(cmd.ik.fps, tracking_task(cmd.robot, dr="none").sim_dt) is None:
            raise InputError(
                f"--method dynamics: --ik.fps {cmd.ik.fps} is not a whole number of physics "
                "steps per frame (50 fps is)"
            )
    if (cmd.method == "interaction-mesh") != (cmd.scene is not None):
        raise InputError(
            "--method interaction-mesh needs --scene"
            if cmd.scene is None
            else "--scene is used by --method interaction-mesh only"
        )
    if not cmd.inputs:
        raise InputError("give at least one input clip or folder")
    files = _clip_files(cmd.inputs, cmd.out)
    several = len(files) > 1 or any(p.is_dir() for p in cmd.inputs)
    if several:
        if cmd.out.suffix:
            raise InputError(f"{cmd.out}: with several inputs --out must be a folder")
        if cmd.report is not None:
            raise InputError("--report names one file: with several inputs the reports go in --out")
        outs = [(cmd.out / f"{n}.npz", cmd.out / f"{n}.json") for _, n in files]
    else:
        if cmd.out.suffix != ".npz":
            raise InputError(f"{cmd.out}: the output motion file must end in .npz")
        outs = [(cmd.out, cmd.report)]
    inputs = {f"the input {f}": f for f, _ in files}
    if cmd.map is not None:
        inputs["--map"] = cmd.map
    if cmd.scene is not None and str(cmd.scene) != "auto":
        inputs["--scene"] = cmd.scene
    for motion_path, report_path in outs:
        check_not_input(motion_path, inputs, "--out")
        check_not_input(report_path, {**inputs, "--out": motion_path}, "--report")
        check_writable(motion_path)
        if report_path is not None:
            check_writable(report_path)

    # Read and check everything first.
    clips: list[HumanClip] = []
    scenes: list[Scene | None] = []
    retargeters: dict[str, Retargeter] = {}
    for f, _ in files:
        if f.suffix.lower() == ".bvh":
            clip = load_bvh(f, units=_units(cmd.units), up=cmd.up, skeleton=cmd.skeleton)
        else:
            clip = load_clip(f, skeleton=cmd.skeleton)
        start = cmd.start if cmd.start is not None else (1 if clip.skeleton == "cmu" else 0)
        if not 0 <= start < clip.num_frames:
            raise InputError(f"{f}: --start {start} outside the clip's {clip.num_frames} frames")
        clip = clip.slice(start)
        if clip.skeleton not in retargeters:
            retargeters[clip.skeleton] = Retargeter(
                cmd.robot,
                clip.skeleton,
                cmd.ik,
                map_file=cmd.map,
                menagerie_root=cmd.menagerie_root,
                method="kinematic" if cmd.method == "dynamics" else cmd.method,
                mesh=cmd.mesh,
            )
        retargeters[clip.skeleton].check(clip)
        clips.append(clip)
        if cmd.scene is None:
            scenes.append(None)
        else:
            scenes.append(load_scene(f.parent if str(cmd.scene) == "auto" else cmd.scene))

    reports = []
    for (f, _), clip, scene, (motion_path, report_path) in zip(
        files, clips, scenes, outs, strict=True
    ):
        total = clip.num_frames_at(cmd.ik.fps) * (1 if scene is None else 2)  # Two passes.
        with tqdm(total=total, desc=f.name, unit="frame", disable=cmd.quiet, leave=False) as bar:
            result = retargeters[clip.skeleton].run(clip, progress=bar.update, scene=scene)
        motion, extra = result.motion, {}
        if cmd.method == "dynamics":
            from humimic.retarget.dynamics import refine

            with tqdm(total=motion.num_frames - 1, desc=f"{f.name} (dynamics)", unit="frame",
                      disable=cmd.quiet, leave=False) as bar:  # fmt: skip
                motion, extra["dynamics"] = refine(motion, cmd.dyn, progress=bar.update)
        report = json_ready(
            {**result.report, **extra, "start_frame": int(clip.meta["start_frame"])}
        )
        _save_with_report(motion, motion_path, report, report_path)
        _print_summary(result.report, motion_path, cmd.mesh.scene_spacing)
        if "dynamics" in extra:
            _print_dynamics(report["dynamics"], motion_path)
        reports.append(report)
    return reports


def _save_with_report(motion: Motion, path: Path, report: dict, report_path: Path | None) -> None:
    """Write the motion, then its JSON report; no motion is left without its report."""
    from humimic.motion import save_motion

    save_motion(motion, path)
    if report_path is not None:
        try:
            atomic_write_text(report_path, json.dumps(report, indent=2, allow_nan=False) + "\n")
        except BaseException:
            path.unlink(missing_ok=True)
            raise


def _print_dynamics(report: dict, out: Path) -> None:
    """The summary of a dynamics refinement (humimic refine, retarget --method dynamics)."""
    k, d = report["kinematic_replay"], report["dynamics_replay"]
    fl = report.get("reference_flight")
    if (
        fl
        and fl["flight_frames"]
        and abs(fl["com_z_acc_in_flight"] - fl["gravity_z"]) > 0.3 * abs(fl["gravity_z"])
    ):
        print(
            f"warning: in the reference's {fl['flight_frames']} flight frames (both feet off the "
            f"ground) its centre of mass accelerates at {fl['com_z_acc_in_flight']:.1f} m/s^2 "
            f"vertically, not {fl['gravity_z']:.2f}: no physical motion follows it exactly "
            f"(the closest arcs of free fall are {fl['ballistic_gap_mm']:.0f} mm RMS from its "
            "centre of mass's height)"
        )
    print(f"open-loop replay, kinematic: {'fell at ' + format(k['seconds_until_fall'], '.2f') + ' s' if k['fell'] else 'stayed up'}, "
          f"MPJPE {k['mpjpe_mm']:.0f} mm; refined: {'fell at ' + format(d['seconds_until_fall'], '.2f') + ' s' if d['fell'] else 'stayed up'}, "
          f"MPJPE {d['mpjpe_mm']:.0f} mm")  # fmt: skip
    rob = report["robustness"]
    if rob["stayed_up"] is not None:
        print(
            f"perturbed physics: {100 * rob['stayed_up']:.0f}% of {rob['replays']} replays stayed up"
        )
    print(
        f"compute: {report['cpu_seconds_per_motion_second']:.0f} CPU s per second of motion; wrote {out}"
    )


def _units(units: str) -> str | float:
    try:
        return float(units)
    except ValueError:
        return units


def _print_summary(r: dict, path: Path, spacing: float | None = None) -> None:
    """One line of the report; with a scene, a second, and a warning for objects sampled more
    coarsely than ``spacing`` [m] (``--mesh.scene_spacing``)."""
    print(
        f"{Path(r['input']).name} -> {path}: {r['frames']} frames at {r['fps']:g} fps, "
        f"{r['frames_per_second']:.0f} frames/s | key points {r['keypoint_error_mm_mean']:.1f} mm "
        f"(p95 {r['keypoint_error_mm_p95']:.1f}) | skating {r['foot_skating_mm_per_s']:.0f} mm/s | "
        f"ground penetration {r['max_ground_penetration_mm']:.1f} mm | lowest foot (median) "
        f"{r['median_lowest_foot_mm']:.1f} mm | joint-limit violations {r['joint_limit_violations']} "
        f"| self-collision frames {r['self_collision_frames']} "
        f"(max {r['max_self_penetration_mm']:.1f} mm) | jerk {r['mean_joint_jerk']:.0f} rad/s^3"
    )
    if "max_scene_penetration_mm" in r:
        k = r["kinematic"]
        print(
            f"  scene: penetration max {r['max_scene_penetration_mm']:.1f} mm in "
            f"{r['scene_penetration_frames']} frames (kinematic: {k['max_scene_penetration_mm']:.1f}"
            f" mm in {k['scene_penetration_frames']}) | contacts kept "
            f"{100 * r['contact_preservation']:.0f}% of {r['human_contacts']} (kinematic: "
            f"{100 * k['contact_preservation']:.0f}%) | planted feet {r['planted_foot_gap_mm']:.1f} mm"
            f" above the surface (kinematic: {k['planted_foot_gap_mm']:.1f}) | skating "
            f"{r['scene_foot_skating_mm_per_s']:.0f} mm/s | interaction "
            f"{r['interaction_frames_per_second']:.0f} frames/s"
        )
        wanted = 1e3 * spacing if spacing is not None else None
        coarse = {n: s for n, s in r["scene_spacing_mm"].items() if wanted and s > 1.01 * wanted}
        if coarse:
            print(
                f"warning: objects too large to sample every {wanted:.0f} mm were sampled more "
                "coarsely: " + ", ".join(f"{n} every {s:.0f} mm" for n, s in coarse.items()),
                file=sys.stderr,
            )


def run_demo(cmd: DemoCommand) -> dict:
    """Run ``humimic demo``: fetch a climbing clip, retarget it, print the full report."""
    from humimic.datasets import climb_clip_paths, find_climb_data

    root = find_climb_data(quiet=cmd.quiet)
    clips = climb_clip_paths(root)
    if not 0 <= cmd.clip < len(clips):
        raise InputError(f"--clip {cmd.clip}: choose 0 to {len(clips) - 1}")
    clip = clips[cmd.clip]
    out = cmd.out / f"{clip.stem}_{cmd.robot}.npz"
    report = out.with_suffix(".json")
    (r,) = run_retarget(
        RetargetCommand(inputs=(clip,), robot=cmd.robot, out=out, report=report, quiet=cmd.quiet)
    )
    print(json.dumps(r, indent=2, allow_nan=False))
    return r


def read_any_motion(path: Path):
    """A motion from .npz or .mcap."""
    from humimic.formats.mcap import read_motion_mcap
    from humimic.motion import load_motion

    if path.suffix == ".npz":
        return load_motion(path)
    if path.suffix == ".mcap":
        return read_motion_mcap(path)
    raise InputError(f"{path}: a motion must be .npz or .mcap")


def run_refine(cmd: RefineCommand) -> dict:
    """Run ``humimic refine``; returns the report."""
    from tqdm import tqdm

    from humimic.motion import load_motion
    from humimic.retarget.dynamics import refine

    cmd.dyn.validate()
    if cmd.backend == "warp":
        check_device(cmd.device)
    if cmd.out.suffix != ".npz":
        raise InputError(f"{cmd.out}: the refined motion must end in .npz")
    if not 0 <= cmd.robustness <= MAX_ROBUSTNESS:
        raise InputError(f"--robustness: must be in 0 to {MAX_ROBUSTNESS}, got {cmd.robustness}")
    check_not_input(cmd.out, {"the motion": cmd.motion}, "--out")
    check_not_input(cmd.report, {"the motion": cmd.motion, "--out": cmd.out}, "--report")
    check_writable(cmd.out)
    if cmd.report is not None:
        check_writable(cmd.report)
    motion = load_motion(cmd.motion)
    with tqdm(total=motion.num_frames - 1, desc=cmd.motion.name, unit="frame",
              disable=cmd.quiet, leave=False) as bar:  # fmt: skip
        refined, report = refine(motion, cmd.dyn, robustness=cmd.robustness, progress=bar.update,
                                 backend=cmd.backend, device=cmd.device)  # fmt: skip
    report = json_ready(report)
    _save_with_report(refined, cmd.out, report, cmd.report)
    _print_dynamics(report, cmd.out)
    return report


def run_replay(cmd: ReplayCommand) -> int:
    """Run ``humimic replay``; returns the exit code."""
    from humimic.retarget.dynamics import check_replay

    if not cmd.tol >= 0:  # NaN fails too: it would call every replay different.
        raise InputError(f"--tol {cmd.tol}: must be a number >= 0")
    r = check_replay(read_any_motion(cmd.motion))
    ok = max(r["max_qpos_error"], r["max_qvel_error"]) <= cmd.tol
    print(f"{int(r['steps'])} physics steps replayed: max |qpos| error {r['max_qpos_error']:.2e}, "
          f"max |qvel| error {r['max_qvel_error']:.2e} ({'reproduced' if ok else 'DIFFERENT'})")  # fmt: skip
    return 0 if ok else 1


def run_convert(cmd: ConvertCommand) -> None:
    """Run ``humimic convert``."""
    from humimic.formats.mcap import write_motion_mcap
    from humimic.motion import save_motion

    if cmd.dst.suffix not in (".npz", ".mcap"):
        raise InputError(f"{cmd.dst}: convert to .npz or .mcap")
    check_not_input(cmd.dst, {"the source": cmd.src}, "the destination")
    motion = read_any_motion(cmd.src)
    if cmd.dst.suffix == ".mcap":
        write_motion_mcap(motion, cmd.dst)
    else:
        save_motion(motion, cmd.dst)
    print(f"wrote {cmd.dst} ({motion.num_frames} frames)")


def load_rollout(rollout: Path | None, motion_path: Path, motion) -> np.ndarray | None:
    """The rollout ``humimic view`` shows, sampled at the motion's frames: ``rollout``'s, else
    the motion MCAP's own ``/qpos`` if it has one, else none. Shape: (frames, nq)."""
    from humimic.formats.mcap import qpos_from_log, read_mcap, sample_at

    if rollout is not None:
        log = read_mcap(rollout)
    elif motion_path.suffix == ".mcap":
        log = read_mcap(motion_path, topics=["/qpos"])
        if not log.messages.get("/qpos"):
            return None
    else:
        return None
    times, qpos = qpos_from_log(log, motion.joint_names)
    ref_t = np.round(np.arange(motion.num_frames) * 1e9 / motion.fps).astype(np.int64)
    return sample_at(times - times[0], qpos, ref_t)


def run_view(cmd: ViewCommand) -> None:
    """Run ``humimic view``."""
    import time

    from humimic.datasets import load_clip
    from humimic.robots import get_robot, nominal_model
    from humimic.viewer import Viewer, load_scene_meshes
    from humimic.viewer.app import check_host, check_port

    t0 = time.perf_counter()
    check_port(cmd.port)  # Bad addresses fail at once, before the motion loads.
    check_host(cmd.host)
    if cmd.duration is not None and not cmd.duration >= 0:  # NaN fails too; 0: start, stop.
        raise InputError(f"--duration {cmd.duration}: must be a number of seconds >= 0")
    if cmd.screenshot is not None:
        inputs = {"the motion": cmd.motion, "--human": cmd.human, "--rollout": cmd.rollout}
        check_not_input(cmd.screenshot, inputs, "--screenshot")
        check_writable(cmd.screenshot)
    motion = read_any_motion(cmd.motion)
    model = nominal_model(get_robot(motion.robot, str(cmd.motion)))
    names = tuple(model.joint(j).name for j in range(1, model.njnt))
    if names != motion.joint_names:
        raise InputError(f"{cmd.motion}: joint names do not match robot {motion.robot}")
    human = load_clip(cmd.human) if cmd.human is not None else None
    scene = load_scene_meshes(cmd.scene) if cmd.scene is not None else None
    rollout = load_rollout(cmd.rollout, cmd.motion, motion)
    viewer = Viewer(
        motion, model, human=human, scene=scene, rollout_qpos=rollout, host=cmd.host, port=cmd.port
    )
    if not 0 <= cmd.frame < motion.num_frames:
        raise InputError(f"--frame {cmd.frame}: the motion has {motion.num_frames} frames")
    try:
        viewer.start(frame=cmd.frame)
    except OSError as e:
        raise InputError(
            f"--host {cmd.host} --port {cmd.port}: cannot serve there ({e.strerror})"
        ) from None
    print(
        f"humimic view: {viewer.url} ({motion.num_frames} frames, loaded in "
        f"{time.perf_counter() - t0:.1f} s); Ctrl-C to stop",
        flush=True,
    )
    try:
        if cmd.screenshot is not None:
            from humimic.viewer.browser import screenshot

            screenshot(viewer.url, cmd.screenshot, wait=8.0)
            print(f"wrote {cmd.screenshot}")
        else:
            viewer.serve_forever(cmd.duration)
    finally:
        viewer.stop()


def run_diagnose(cmd: SysidDiagnose) -> dict:
    """Run ``humimic sysid diagnose``."""
    from humimic.real2sim.report import run_diagnosis

    report = run_diagnosis(cmd.log, cmd.out_dir, horizon=cmd.horizon, residual_net=cmd.residual_net)
    before, after = report["error_before"], report["error_after"]
    print(f"{cmd.log.name}: held-out k-step error {before['kstep_rmse_rad'] * 1e3:.2f} mrad "
          f"nominal -> {after['kstep_rmse_rad'] * 1e3:.2f} mrad corrected "
          f"({report['seconds']:.0f} s)")  # fmt: skip
    for e in report["effects"]:
        if e["confidence"] >= 0.5:
            where = e.get("body") or ", ".join(e["joints"])
            print(f"claimed: {e['effect']} on {where} = {e['params']['value']:.4g} "
                  f"{e['params']['unit']} (confidence {e['confidence']:.2f})")  # fmt: skip
    for s in report["not_identifiable"]:
        print(f"not identifiable from this log: {s['effect']} on {len(s['joints'])} joints")
    if report["unexplained"]:
        print("unexplained: " + ", ".join(report["unexplained_joints"]))
    if report["residual_model"] is not None:
        net = report["residual_model"]
        print(f"residual actuator network: {net['error_after']['kstep_rmse_rad'] * 1e3:.2f} mrad "
              f"held out -> {net['path']}")  # fmt: skip
    print(f"wrote {cmd.out_dir / 'report.md'}, report.json, model.xml")
    return report


def run_sysid(cmd: SysidSimulate | SysidResidual | SysidDiagnose) -> None:
    """Run ``humimic sysid simulate|residual|diagnose``."""
    from humimic.real2sim import LogSettings, kstep_error, simulate_log, write_robot_log
    from humimic.robots import get_robot
    from humimic.sim.effects import parse_injection

    if isinstance(cmd, SysidSimulate):
        robot = get_robot(cmd.robot, "--robot")
        injections = [parse_injection(text) for text in cmd.inject]
        if cmd.out.suffix != ".mcap":
            raise InputError(f"{cmd.out}: the log must be an .mcap file")
        if not 1.0 <= cmd.duration <= 3600.0:
            raise InputError(f"--duration {cmd.duration}: choose 1 to 3600 s")
        check_writable(cmd.out)
        log = simulate_log(robot, injections, LogSettings(duration=cmd.duration, seed=cmd.seed))
        write_robot_log(log, cmd.out)
        print(f"wrote {cmd.out}: {log.q.shape[0]} states, {log.t_cmd.size} commands, "
              f"{len(log.joint_names)} joints")  # fmt: skip
        return
    if isinstance(cmd, SysidDiagnose):
        run_diagnose(cmd)
        return
    if cmd.report is not None:
        check_not_input(cmd.report, {"the log": cmd.log}, "--report")
        check_writable(cmd.report)
    from humimic.real2sim.report import load_fixed_base_log

    robot, model, log = load_fixed_base_log(cmd.log)
    names = log.joint_names
    err = kstep_error(model, log, horizon=cmd.horizon)
    result = {"robot": robot.name, "log": str(cmd.log), "error_nominal": err.as_report(names)}
    worst = sorted(result["error_nominal"]["per_joint"].items(), key=lambda kv: -kv[1])[:5]
    print(f"{cmd.log.name}: nominal k-step RMSE {err.kstep_rmse_rad * 1e3:.2f} mrad over "
          f"{err.horizon_s} s windows; worst joints: "
          + ", ".join(f"{n} {v * 1e3:.2f}" for n, v in worst))  # fmt: skip
    if cmd.report is not None:
        atomic_write_text(cmd.report, json.dumps(json_ready(result), indent=2) + "\n")


def run_robots(cmd: RobotsList | RobotsExport) -> None:
    from humimic.robots import export_nominal, get_robot, robot_names

    if isinstance(cmd, RobotsList):
        for name in robot_names():
            cfg = get_robot(name)
            print(f"{name:6s} {cfg.description} [{cfg.license}]")
        return
    path = export_nominal(
        get_robot(cmd.name, "robots export"), cmd.out, menagerie_root=cmd.menagerie_root
    )
    print(f"wrote {path} (meshes in {path.parent / (path.stem + '_assets')})")


def run_fetch(cmd: FetchCommand) -> None:
    from humimic.datasets import fetch_holosoma_climb

    print(fetch_holosoma_climb())


def run_train(cmd: TrainSettings) -> None:
    """Run ``humimic train``."""
    from humimic.tracking.distributed import Ranks
    from humimic.tracking.train import train

    last = train(cmd)
    if last and Ranks.from_env().main:  # Under torchrun, rank 0 speaks for the run.
        print(f"{cmd.out}: {int(last['iteration'])} iterations, mean reward "
              f"{last.get('mean_reward', float('nan')):.4g}, mean episode length "
              f"{last.get('mean_episode_length', float('nan')):.1f} steps")  # fmt: skip


def run_distill(cmd: DistillSettings) -> None:
    """Run ``humimic distill``."""
    from humimic.tracking.distill import distill

    row = distill(cmd)
    if "loss_behavior" in row:
        print(f"{cmd.out}: {int(row['iteration'])} iterations, imitation loss "
              f"{row['loss_behavior']:.4g}, mean episode length "
              f"{row['mean_episode_length']:.1f} steps")  # fmt: skip


def run_eval(cmd: EvalSettings) -> None:
    """Run ``humimic eval``."""
    from humimic.tracking.evaluate import evaluate

    result = evaluate(cmd)
    if "physics" in result:
        print(f"physics {result['physics']['name']}: {result['physics']['description']}")
    for name in ("policy", "open_loop"):
        m = result[name]
        print(f"{name:9s}: success {100 * m['success_rate']:.0f}%, global MPJPE "
              f"{m['mpjpe_global_mm']:.1f} mm, root-relative {m['mpjpe_root_mm']:.1f} mm, "
              f"joint error {m['joint_error_rad']:.3f} rad")  # fmt: skip
    if cmd.out is not None:
        print(f"wrote {cmd.out}")
    if "mcap" in result:
        print(f"wrote {result['mcap']} (humimic view {result['mcap']})")


def run_loop(cmd: LoopSettings) -> None:
    """Run ``humimic loop``."""
    from humimic.pipeline.loop import loop

    r = loop(cmd)
    for name in ("before", "after", "after_nominal"):
        if name in r:
            p = r[name]["policy"]
            print(f"{name:13s}: success {100 * p['success_rate']:.0f}%, global MPJPE "
                  f"{p['mpjpe_global_mm']:.1f} mm, joint error {p['joint_error_rad']:.3f} rad")  # fmt: skip
    print(f"sysid claimed: {', '.join(r['sysid']['claimed']) or 'nothing'}")
    print(f"wrote {cmd.out / 'loop.md'}")


Commands = (
    Annotated[RetargetCommand, tyro.conf.subcommand("retarget")]
    | Annotated[RefineCommand, tyro.conf.subcommand("refine")]
    | Annotated[ReplayCommand, tyro.conf.subcommand("replay")]
    | Annotated[DemoCommand, tyro.conf.subcommand("demo")]
    | Annotated[ViewCommand, tyro.conf.subcommand("view")]
    | Annotated[ConvertCommand, tyro.conf.subcommand("convert")]
    | Annotated[RobotsCommand, tyro.conf.subcommand("robots")]
    | Annotated[SysidCommand, tyro.conf.subcommand("sysid")]
    | Annotated[FetchCommand, tyro.conf.subcommand("fetch")]
    | Annotated[TrainSettings, tyro.conf.subcommand("train")]
    | Annotated[DistillSettings, tyro.conf.subcommand("distill")]
    | Annotated[EvalSettings, tyro.conf.subcommand("eval")]
    | Annotated[ExportSettings, tyro.conf.subcommand("export")]
    | Annotated[LoopSettings, tyro.conf.subcommand("loop")]
)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``humimic`` console script. Bad input exits with code 2."""
    args = sys.argv[1:] if argv is None else argv
    preset = _scan_preset(args)
    _PRESET[0] = preset if preset in RETARGET_CONFIGS else "default"
    cmd = tyro.cli(
        Commands,  # type: ignore[arg-type]
        args=args,
        prog="humimic",
        config=(tyro.conf.OmitSubcommandPrefixes,),
    )
    try:
        if isinstance(cmd, RetargetCommand):
            run_retarget(cmd)
        elif isinstance(cmd, RefineCommand):
            run_refine(cmd)
        elif isinstance(cmd, ReplayCommand):
            return run_replay(cmd)
        elif isinstance(cmd, DemoCommand):
            run_demo(cmd)
        elif isinstance(cmd, ViewCommand):
            run_view(cmd)
        elif isinstance(cmd, ConvertCommand):
            run_convert(cmd)
        elif isinstance(cmd, SysidCommand):
            run_sysid(cmd.command)
        elif isinstance(cmd, RobotsCommand):
            run_robots(cmd.command)
        elif isinstance(cmd, FetchCommand):
            run_fetch(cmd)
        elif isinstance(cmd, TrainSettings):
            run_train(cmd)
        elif isinstance(cmd, DistillSettings):
            run_distill(cmd)
        elif isinstance(cmd, EvalSettings):
            run_eval(cmd)
        elif isinstance(cmd, LoopSettings):
            run_loop(cmd)
        elif isinstance(cmd, ExportSettings):
            from humimic.tracking.export import export

            print(f"wrote {export(cmd)}")
    except InputError as e:
        print(f"humimic: error: {e}", file=sys.stderr)
        return 2
    except HumimicError as e:
        print(f"humimic: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("humimic: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
