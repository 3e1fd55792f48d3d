"""``humimic``: one console script, one subcommand per verb (tyro over dataclasses)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from humimic.configs import RetargetConfig, retarget_default, retarget_fast
from humimic.errors import HumimicError, InputError
from humimic.io import atomic_write_text, check_writable

RETARGET_CONFIGS = {"default": retarget_default, "fast": retarget_fast}
"""Named retargeting configurations (factories); see :mod:`humimic.configs`."""


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
    ik: RetargetConfig = field(default_factory=retarget_default)
    """IK settings."""
    quiet: bool = False
    """No progress bars; print only the report summary."""


@dataclass(frozen=True, kw_only=True)
class DemoCommand:
    """Fetch a real climbing clip (PyPI package holosoma-retargeting) and retarget it."""

    robot: str = "g1"
    out: Path = Path("out/demo")
    """Output folder."""
    clip: int = 0
    """Which climbing sequence (0-2)."""
    quiet: bool = False


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


@dataclass(frozen=True, kw_only=True)
class FetchCommand:
    """Download public data sets for humimic at run time."""

    what: Annotated[Literal["climb"], tyro.conf.Positional] = "climb"
    """climb: the holosoma climbing clips with box meshes."""


def _clip_files(inputs: tuple[Path, ...]) -> list[Path]:
    from humimic.datasets import SUPPORTED_SUFFIXES

    files: list[Path] = []
    for p in inputs:
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.suffix.lower() in SUPPORTED_SUFFIXES)
            if not found:
                raise InputError(f"{p}: folder holds no {', '.join(SUPPORTED_SUFFIXES)} files")
            files += found
        elif p.exists():
            files.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    return files


def run_retarget(cmd: RetargetCommand) -> list[dict]:
    """Run ``humimic retarget``; returns the reports."""
    from tqdm import tqdm

    from humimic.datasets import load_bvh, load_clip
    from humimic.motion import save_motion
    from humimic.retarget import Retargeter
    from humimic.robots import get_robot

    get_robot(cmd.robot)  # Unknown robot: fail before any work.
    if not cmd.inputs:
        raise InputError("give at least one input clip or folder")
    files = _clip_files(cmd.inputs)
    several = len(files) > 1 or any(p.is_dir() for p in cmd.inputs)
    if several:
        if cmd.out.suffix:
            raise InputError(f"{cmd.out}: with several inputs --out must be a folder")
        if cmd.report is not None:
            raise InputError("--report names one file: with several inputs the reports go in --out")
        outs = [(cmd.out / f"{f.stem}.npz", cmd.out / f"{f.stem}.json") for f in files]
    else:
        if cmd.out.suffix != ".npz":
            raise InputError(f"{cmd.out}: the output motion file must end in .npz")
        outs = [(cmd.out, cmd.report)]
    for motion_path, report_path in outs:
        check_writable(motion_path)
        if report_path is not None:
            check_writable(report_path)

    base = retarget_default()
    changed = {
        f.name: getattr(cmd.ik, f.name)
        for f in fields(RetargetConfig)
        if getattr(cmd.ik, f.name) != getattr(base, f.name)
    }
    ik_cfg = replace(RETARGET_CONFIGS[cmd.preset](), **changed)
    retargeters: dict[str, Retargeter] = {}
    reports = []
    for f, (motion_path, report_path) in zip(files, outs, strict=True):
        if f.suffix.lower() == ".bvh":
            clip = load_bvh(f, units=_units(cmd.units), up=cmd.up, skeleton=cmd.skeleton)
        else:
            clip = load_clip(f, skeleton=cmd.skeleton)
        start = cmd.start if cmd.start is not None else (1 if clip.skeleton == "cmu" else 0)
        if not 0 <= start < clip.num_frames:
            raise InputError(f"{f}: --start {start} outside the clip's {clip.num_frames} frames")
        clip = clip.slice(start)
        key = clip.skeleton
        if key not in retargeters:
            retargeters[key] = Retargeter(
                cmd.robot,
                clip.skeleton,
                ik_cfg,
                map_file=cmd.map,
                menagerie_root=cmd.menagerie_root,
            )
        rt = retargeters[key]
        rt.validate(clip)
        total = clip.resample(ik_cfg.fps).num_frames
        with tqdm(total=total, desc=f.name, unit="frame", disable=cmd.quiet, leave=False) as bar:
            result = rt.run(clip, progress=bar.update)
        result.report["start_frame"] = start
        save_motion(result.motion, motion_path)
        text = json.dumps(result.report, indent=2)
        if report_path is not None:
            atomic_write_text(report_path, text + "\n")
        _print_summary(result.report, motion_path)
        reports.append(result.report)
    return reports


def _units(units: str) -> str | float:
    try:
        return float(units)
    except ValueError:
        return units


def _print_summary(r: dict, path: Path) -> None:
    print(
        f"{Path(r['input']).name} -> {path}: {r['frames']} frames at {r['fps']:g} fps, "
        f"{r['frames_per_second']:.0f} frames/s | key points {r['keypoint_error_mm_mean']:.1f} mm "
        f"(p95 {r['keypoint_error_mm_p95']:.1f}) | skating {r['foot_skating_mm_per_s']:.0f} mm/s | "
        f"ground penetration {r['max_ground_penetration_mm']:.1f} mm | lowest foot (median) "
        f"{r['median_lowest_foot_mm']:.1f} mm | joint-limit violations {r['joint_limit_violations']} "
        f"| self-collision frames {r['self_collision_frames']} "
        f"(max {r['max_self_penetration_mm']:.1f} mm) | jerk {r['mean_joint_jerk']:.0f} rad/s^3"
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
    print(json.dumps(r, indent=2))
    return r


def run_robots(cmd: RobotsList | RobotsExport) -> None:
    from humimic.robots import export_nominal, get_robot, robot_names

    if isinstance(cmd, RobotsList):
        for name in robot_names():
            cfg = get_robot(name)
            print(f"{name:6s} {cfg.description} [{cfg.license}]")
        return
    path = export_nominal(get_robot(cmd.name), cmd.out, menagerie_root=cmd.menagerie_root)
    print(f"wrote {path} (meshes in {path.parent / (path.stem + '_assets')})")


def run_fetch(cmd: FetchCommand) -> None:
    from humimic.datasets import fetch_holosoma_climb

    print(fetch_holosoma_climb())


Commands = (
    Annotated[RetargetCommand, tyro.conf.subcommand("retarget")]
    | Annotated[DemoCommand, tyro.conf.subcommand("demo")]
    | Annotated[RobotsCommand, tyro.conf.subcommand("robots")]
    | Annotated[FetchCommand, tyro.conf.subcommand("fetch")]
)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``humimic`` console script. Bad input exits with code 2."""
    cmd = tyro.cli(
        Commands,  # type: ignore[arg-type]
        args=argv,
        prog="humimic",
        config=(tyro.conf.OmitSubcommandPrefixes,),
    )
    try:
        if isinstance(cmd, RetargetCommand):
            run_retarget(cmd)
        elif isinstance(cmd, DemoCommand):
            run_demo(cmd)
        elif isinstance(cmd, RobotsCommand):
            run_robots(cmd.command)
        elif isinstance(cmd, FetchCommand):
            run_fetch(cmd)
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
