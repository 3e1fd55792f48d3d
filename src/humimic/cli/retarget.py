"""``humimic retarget``, ``refine``, ``replay``, ``demo`` and ``convert``: human clips to robot
motions, dynamics, and motion files."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import tyro

from humimic.configs import (
    RETARGET_CONFIGS,
    DynamicsConfig,
    InteractionConfig,
    RetargetConfig,
    retarget_default,
)
from humimic.configs.choices import RetargetPreset, RobotName
from humimic.configs.runs import check_device
from humimic.errors import InputError
from humimic.io import check_not_input, check_writable, json_ready
from humimic.pipeline.batch import Method, frame_bars

if TYPE_CHECKING:
    from humimic.pipeline.dataset import DatasetSummary

MAX_ROBUSTNESS = 1000
"""The most perturbed replays ``humimic refine --robustness`` makes for its report."""


MAX_WORKERS = 1024
"""Most worker processes one machine runs (beyond it, surely a typo)."""


def _check_workers(workers: int | None) -> None:
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise InputError(f"--workers {workers}: must be in 1 to {MAX_WORKERS}")


@dataclass(frozen=True, kw_only=True)
class RetargetCommand:
    """Retarget human motion clips (BVH, FBX, SMPL-family parameters, joint-position arrays,
    a robot's motion) to a robot."""

    inputs: Annotated[tuple[Path, ...], tyro.conf.Positional]
    """Clip files (.bvh, .fbx, .npy, .npz, GVHMR's .pt) or folders of them."""
    robot: RobotName = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    out: Path
    """Output .npz for one input; an output folder for several inputs or a folder."""
    report: Path | None = None
    """Quality report (JSON) for one input; with several, one <name>.json per clip in --out."""
    body_model: Path | None = None
    """For SMPL / SMPL+H / SMPL-X parameter files (AMASS .npz): the folder of your body model
    files (smplx/SMPLX_NEUTRAL.npz and the like; licence-gated, never shipped). Default:
    $HUMIMIC_BODY_MODELS."""
    format: Literal["npz", "csv"] = "npz"
    """csv: also write each motion as <name>.csv (per row: base x y z, quaternion qx qy qz qw,
    joint positions in the robot's order; BeyondMimic's and GMR's layout) with
    <name>.csv.yaml (robot, frame rate, joint order) beside the .npz."""
    units: str = "auto"
    """BVH and FBX units: auto (from the skeleton's height), m, cm, mm, inch, or metres per
    file unit."""
    up: Literal["auto", "y", "z"] = "auto"
    """Up axis of BVH and FBX files. auto: y for BVH (its convention), found from the skeleton
    for FBX (the spine above the legs). Arrays of positions are z up."""
    skeleton: str | None = None
    """Skeleton name for the map (default: detected from the joint names)."""
    map: Path | None = None
    """Your own human-to-robot map (YAML); default: the shipped map for skeleton and robot."""
    menagerie_root: Path | None = None
    """A MuJoCo Menagerie folder (or the robot's own folder) to load the robot from."""
    start: int | None = None
    """First source frame to use (default: 1 for CMU files, whose frame 0 is a T-pose)."""
    preset: RetargetPreset = "default"
    """Named IK settings (humimic.configs); --ik.* flags change single fields on top of it."""
    ik: RetargetConfig = field(default_factory=retarget_default)
    """IK settings (defaults: those of --preset)."""
    method: Method = "kinematic"
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
    workers: int | None = None
    """With a folder or several clips: clips retargeted at once, each in its own process
    (default: the cores). Every outcome goes to <out>/manifest.jsonl; a rerun resumes."""
    ray: str | None = None
    """With a folder or several clips: run them as Ray tasks on a cluster (its address, or
    auto), or on a local Ray instance of --workers CPUs (local). Needs pip install ray
    (the ray extra); inputs and --out on a path every node sees."""

    def validate(self) -> None:
        """Check the settings before any clip is read; :class:`InputError` names the flag."""
        _check_workers(self.workers)
        self.ik.validate()
        self.mesh.validate()
        self.dyn.validate()
        if self.start is not None and self.start < 0:
            raise InputError(f"--start {self.start}: must be a frame number >= 0")


def scan_preset(argv: list[str]) -> str:
    """The ``--preset`` on a command line, before it is parsed (``default`` without one)."""
    for i, a in enumerate(argv):
        if a == "--preset" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--preset="):
            return a.split("=", 1)[1]
    return "default"


def retarget_defaults(argv: list[str]) -> RetargetCommand:
    """The defaults of ``humimic retarget`` for a command line: the ``--ik.*`` settings of
    its ``--preset`` (an unknown preset is left for the parser to refuse)."""
    preset = scan_preset(argv)
    if preset not in RETARGET_CONFIGS:
        preset = "default"
    return RetargetCommand(
        inputs=tyro.MISSING, out=tyro.MISSING, preset=preset, ik=RETARGET_CONFIGS[preset]()
    )


@dataclass(frozen=True, kw_only=True)
class RefineCommand:
    """Make a motion dynamically feasible: sampling MPC in MuJoCo, so that its stored controls
    replay open-loop on the simulated robot (humimic.retarget.dynamics)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """A robot motion (.npz), e.g. from humimic retarget; or a folder of them (each refined on
    its own, outcomes in <out>/manifest.jsonl, a rerun resumes: docs/datasets.md)."""
    out: Path
    """The refined motion (.npz), with its dynamic section; a folder for a folder."""
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
    workers: int | None = None
    """With a folder: motions refined at once, each in its own process (default: the cores)."""
    ray: str | None = None
    """With a folder: run them as Ray tasks (a cluster's address, auto, or local)."""

    def validate(self) -> None:
        """Check the settings before the motion is read; :class:`InputError` names the flag."""
        _check_workers(self.workers)
        self.dyn.validate()
        if self.backend == "warp":
            check_device(self.device)
        if not 0 <= self.robustness <= MAX_ROBUSTNESS:
            raise InputError(f"--robustness {self.robustness}: must be in 0 to {MAX_ROBUSTNESS}")


@dataclass(frozen=True, kw_only=True)
class ReplayCommand:
    """Replay a refined motion's controls open-loop and check that they reproduce its
    stored states (exit code 1 if they differ by more than --tol)."""

    motion: Annotated[Path, tyro.conf.Positional]
    """A motion with a dynamic section (humimic refine), .npz or .mcap."""
    tol: float = 1e-9
    """Largest accepted difference of qpos and qvel."""

    def validate(self) -> None:
        """Check ``--tol``; :class:`InputError` names it."""
        if not self.tol >= 0:  # NaN fails too: it would call every replay different.
            raise InputError(f"--tol {self.tol}: must be a number >= 0")


@dataclass(frozen=True, kw_only=True)
class ConvertCommand:
    """Convert a motion between .npz, .mcap (lossless both ways) and .csv (the layout
    BeyondMimic's and GMR's trackers read: per row base x y z, base quaternion qx qy qz qw,
    the joint positions in the robot's order; the robot, frame rate and joint order in a
    <file>.csv.yaml beside it)."""

    src: Annotated[Path, tyro.conf.Positional]
    """The motion to read (.npz, .mcap or .csv)."""
    dst: Annotated[Path, tyro.conf.Positional]
    """The file to write (.npz, .mcap or .csv); it must not be the source."""
    robot: str | None = None
    """A .csv source's robot (default: its .csv.yaml's)."""
    fps: float | None = None
    """A .csv source's frame rate (default: its .csv.yaml's)."""

    def validate(self) -> None:
        if self.fps is not None and self.fps <= 0:
            raise InputError(f"--fps {self.fps}: must be positive")


def _units(units: str) -> str | float:
    """``--units``: a unit name, or metres per file unit."""
    try:
        return float(units)
    except ValueError:
        return units


def _knees(r: dict) -> str:
    """The summary's turned-knee part: nothing for a model without knees (or an old report)."""
    n = r.get("turned_knee_frames")
    if n is None:
        return ""
    return f" | turned knees {n} frames (worst {r['worst_knee_turn_deg']:.0f} deg)"


def measured(value: float | None, spec: str, scale: float = 1.0) -> str:
    """A report figure for a summary line: ``n/a`` where nothing was measured (a metric over
    zero events is None, never a perfect score)."""
    return "n/a" if value is None else format(scale * value, spec)


def print_summary(r: dict, path: Path, spacing: float | None = None) -> None:
    """One line of a retargeting report; with a scene, a second, and a warning for objects
    sampled more coarsely than ``spacing`` [m] (``--mesh.scene_spacing``)."""
    print(
        f"{Path(r['input']).name} -> {path}: {r['frames']} frames at {r['fps']:g} fps, "
        f"{r['frames_per_second']:.0f} frames/s | key points {r['keypoint_error_mm_mean']:.1f} mm "
        f"(p95 {r['keypoint_error_mm_p95']:.1f}) | skating "
        f"{measured(r['foot_skating_mm_per_s'], '.0f')} mm/s (planted "
        f"{measured(r.get('planted_foot_skating_mm_per_s'), '.0f')}) | "
        f"ground penetration {r['max_ground_penetration_mm']:.1f} mm | lowest foot (median) "
        f"{r['median_lowest_foot_mm']:.1f} mm | joint-limit violations {r['joint_limit_violations']} "
        f"| self-collision frames {r['self_collision_frames']} "
        f"(max {r['max_self_penetration_mm']:.1f} mm) | jerk {r['mean_joint_jerk']:.0f} rad/s^3"
        + _knees(r)
    )
    if "map_written" in r:
        print(
            f"  map: no shipped skeleton map fits {Path(r['input']).name}'s joints; one was "
            f"proposed from their names and tree: {r['map_written']} (check it, edit it, and "
            f"give it back with --map {r['map_written']})"
        )
    if "max_scene_penetration_mm" in r:
        k = r["kinematic"]
        print(
            f"  scene: penetration max {r['max_scene_penetration_mm']:.1f} mm in "
            f"{r['scene_penetration_frames']} frames (kinematic: {k['max_scene_penetration_mm']:.1f}"
            f" mm in {k['scene_penetration_frames']}) | contacts kept "
            f"{measured(r['contact_preservation'], '.0f', 100)}% of {r['human_contacts']} "
            f"(kinematic: {measured(k['contact_preservation'], '.0f', 100)}%) | planted feet "
            f"{measured(r['planted_foot_gap_mm'], '.1f')} mm above the surface (kinematic: "
            f"{measured(k['planted_foot_gap_mm'], '.1f')}) | skating "
            f"{measured(r['scene_foot_skating_mm_per_s'], '.0f')} mm/s | interaction "
            f"{r['interaction_frames_per_second']:.0f} frames/s"
        )
        if not r["human_contacts"]:
            print(
                f"warning: {Path(r['input']).name}: the human never touches the scene (0 "
                "human-scene contacts), so contact preservation is not measured (n/a); look "
                "at the clip with its scene (humimic view MOTION --human CLIP --scene SCENE): "
                "a scene placed off the motion, or contacts beyond the detection distance",
                file=sys.stderr,
            )
        floor = r.get("scene_floor") or {}
        if floor.get("from", "").startswith("z = 0"):
            print(
                f"warning: {Path(r['input']).name}: no toe of the human rests on a scene object, "
                "so the scene's floor is taken at z = 0 of the clip's frame; if it is elsewhere, "
                "give it: --ik.floor-height H",
                file=sys.stderr,
            )
        wanted = 1e3 * spacing if spacing is not None else None
        coarse = {n: s for n, s in r["scene_spacing_mm"].items() if wanted and s > 1.01 * wanted}
        if coarse:
            print(
                f"warning: objects too large to sample every {wanted:.0f} mm were sampled more "
                "coarsely: " + ", ".join(f"{n} every {s:.0f} mm" for n, s in coarse.items()),
                file=sys.stderr,
            )


def print_dynamics(report: dict, out: Path) -> None:
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


def retarget_clips(cmd: RetargetCommand) -> list[dict]:
    """Retarget the clips of ``humimic retarget``, printing each one's summary; returns the
    reports.

    Every input is read and checked before any retargeting, so bad input fails the whole call
    before anything is written (:func:`humimic.pipeline.batch.plan_retarget`).
    """
    from humimic.pipeline.batch import plan_retarget

    if len(cmd.inputs) > 1 or any(p.is_dir() for p in cmd.inputs):
        return _retarget_dataset(cmd)
    if cmd.ray is not None or cmd.workers is not None:
        raise InputError(
            f"{'--ray' if cmd.ray is not None else '--workers'}: for a folder or several clips; "
            "one clip runs in this process"
        )
    batch = plan_retarget(
        cmd.inputs, cmd.out, report=cmd.report, robot=cmd.robot, method=cmd.method, ik=cmd.ik,
        mesh=cmd.mesh, dyn=cmd.dyn, units=_units(cmd.units), up=cmd.up, skeleton=cmd.skeleton,
        map_file=cmd.map, menagerie_root=cmd.menagerie_root, start=cmd.start, scene=cmd.scene,
        csv=cmd.format == "csv", body_model=cmd.body_model,
    )  # fmt: skip
    reports = []
    for r in batch.run(progress=frame_bars(cmd.quiet)):
        print_summary(r.report, r.motion_path, cmd.mesh.scene_spacing)
        if "dynamics" in r.report:
            print_dynamics(r.report["dynamics"], r.motion_path)
        reports.append(r.report)
    return reports


def _retarget_dataset(cmd: RetargetCommand) -> list[dict]:
    """A folder or several clips: every clip on its own in a pool of processes, outcomes in
    the manifest (:mod:`humimic.pipeline.dataset`); the summary at the end; exit 2 naming the
    manifest when any clip failed."""
    from humimic.pipeline.batch import ClipOptions
    from humimic.pipeline.dataset import run_dataset, summary_lines

    if cmd.report is not None:
        raise InputError("--report names one file: with several inputs the reports go in --out")
    if cmd.workers is not None and cmd.workers < 1:
        raise InputError(f"--workers {cmd.workers}: must be at least 1")
    opts = ClipOptions(robot=cmd.robot, method=cmd.method, ik=cmd.ik, mesh=cmd.mesh,
                       units=_units(cmd.units), up=cmd.up, skeleton=cmd.skeleton,
                       map_file=cmd.map, menagerie_root=cmd.menagerie_root, start=cmd.start,
                       scene=cmd.scene, body_model=cmd.body_model)  # fmt: skip
    summary = run_dataset(cmd.inputs, cmd.out, opts, dyn=cmd.dyn, csv=cmd.format == "csv",
                          workers=cmd.workers, ray=cmd.ray, quiet=cmd.quiet)  # fmt: skip
    _finish_dataset(summary_lines(summary), summary, "clips")
    return [r.get("headline", {}) for r in summary.done]


def _finish_dataset(lines: list[str], summary: DatasetSummary, noun: str) -> None:
    """Print a dataset run's summary; :class:`InputError` (exit 2) when any input failed,
    naming the first and the manifest."""
    for line in lines:
        print(line)
    if summary.failed:
        first = summary.failed[0]
        raise InputError(
            f"{len(summary.failed)} of {len(summary.done) + len(summary.failed)} {noun} failed "
            f"(first: {first['input']}: {first.get('error', '?')}); the others are written; "
            f"see {summary.manifest}"
        )


def run_retarget(cmd: RetargetCommand) -> None:
    """Run ``humimic retarget``."""
    retarget_clips(cmd)


def run_refine(cmd: RefineCommand) -> None:
    """Run ``humimic refine``."""
    from humimic.motion import load_motion
    from humimic.pipeline.batch import save_with_report
    from humimic.retarget.dynamics import refine

    cmd.validate()
    if cmd.motion.is_dir():
        from humimic.pipeline.dataset import motion_files, summary_lines
        from humimic.pipeline.refining import REFINE_HEADLINE, refine_motions

        if cmd.report is not None:
            raise InputError("--report names one file: with a folder the reports go in --out")
        if cmd.out.suffix:
            raise InputError(f"{cmd.out}: with a folder --out must be a folder")
        summary = refine_motions(motion_files(cmd.motion, cmd.out), cmd.out, cmd.dyn,
                                 robustness=cmd.robustness, backend=cmd.backend,
                                 device=cmd.device, workers=cmd.workers, ray=cmd.ray,
                                 quiet=cmd.quiet)  # fmt: skip
        lines = summary_lines(summary, REFINE_HEADLINE, ("dynamics_mpjpe_mm",),
                              done="motions refined")  # fmt: skip
        _finish_dataset(lines, summary, "motions")
        return
    if cmd.ray is not None or cmd.workers is not None:
        raise InputError(
            f"{'--ray' if cmd.ray is not None else '--workers'}: for a folder of motions; "
            "one motion runs in this process"
        )
    if cmd.out.suffix != ".npz":
        raise InputError(f"{cmd.out}: the refined motion must end in .npz")
    check_not_input(cmd.out, {"the motion": cmd.motion}, "--out")
    check_not_input(cmd.report, {"the motion": cmd.motion, "--out": cmd.out}, "--report")
    check_writable(cmd.out)
    if cmd.report is not None:
        check_writable(cmd.report)
    motion = load_motion(cmd.motion)
    with frame_bars(cmd.quiet)(cmd.motion.name, motion.num_frames - 1) as update:
        refined, report = refine(motion, cmd.dyn, robustness=cmd.robustness, progress=update,
                                 backend=cmd.backend, device=cmd.device)  # fmt: skip
    report = json_ready(report)
    save_with_report(refined, cmd.out, report, cmd.report)
    print_dynamics(report, cmd.out)


def run_replay(cmd: ReplayCommand) -> int:
    """Run ``humimic replay``; returns the exit code."""
    from humimic.pipeline.files import read_any_motion
    from humimic.retarget.dynamics import check_replay

    cmd.validate()
    r = check_replay(read_any_motion(cmd.motion))
    ok = max(r["max_qpos_error"], r["max_qvel_error"]) <= cmd.tol
    print(f"{int(r['steps'])} physics steps replayed: max |qpos| error {r['max_qpos_error']:.2e}, "
          f"max |qvel| error {r['max_qvel_error']:.2e} ({'reproduced' if ok else 'DIFFERENT'})")  # fmt: skip
    return 0 if ok else 1


def run_convert(cmd: ConvertCommand) -> None:
    """Run ``humimic convert``."""
    from humimic.formats.csv_motion import write_motion_csv
    from humimic.formats.mcap import write_motion_mcap
    from humimic.motion import save_motion
    from humimic.pipeline.files import read_any_motion
    from humimic.robots.model import motion_model

    if cmd.dst.suffix not in (".npz", ".mcap", ".csv"):
        raise InputError(f"{cmd.dst}: convert to .npz, .mcap or .csv")
    check_not_input(cmd.dst, {"the source": cmd.src}, "the destination")
    motion = read_any_motion(cmd.src, robot=cmd.robot, fps=cmd.fps)
    if cmd.src.suffix != ".csv":  # A CSV was read on its robot's model, its joints checked.
        motion_model(motion, str(cmd.src))  # A motion of the robot it names, or refused.
    if cmd.dst.suffix == ".mcap":
        write_motion_mcap(motion, cmd.dst)
    elif cmd.dst.suffix == ".csv":
        side = write_motion_csv(cmd.dst, motion.qpos, fps=motion.fps, robot=motion.robot,
                                joint_names=tuple(motion.joint_names))  # fmt: skip
        print(f"wrote {side} (robot, frame rate, joint order)")
    else:
        save_motion(motion, cmd.dst)
    print(f"wrote {cmd.dst} ({motion.num_frames} frames)")
