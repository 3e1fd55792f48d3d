"""Batch retargeting: clip files and folders of them to motion files with their reports.

:func:`plan_retarget` reads and checks every input and output path, so that bad input fails
the whole batch before anything is written; :meth:`RetargetBatch.run` then writes clip by clip.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from humimic.configs import DynamicsConfig, InteractionConfig, RetargetConfig
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready
from humimic.motion import Motion, save_motion
from humimic.robots.maps import builtin_maps, compose_map, map_data, robot_map_file
from humimic.robots.maps.detect import match_skeleton, propose_skeleton_map

if TYPE_CHECKING:
    from humimic.datasets import HumanClip
    from humimic.datasets.scene import Scene
    from humimic.retarget import Retargeter

Progress = Callable[[str, int], AbstractContextManager[Callable[[int], Any]]]
"""Makes a progress bar: ``progress(description, total)`` is a context manager whose value is
called with the number of frames done since its last call."""

Method = Literal["kinematic", "interaction-mesh", "dynamics"]


def frame_bars(quiet: bool) -> Progress:
    """A :data:`Progress` of tqdm bars counting frames (disabled if ``quiet``)."""
    from tqdm import tqdm

    @contextmanager
    def bar(description: str, total: int) -> Iterator[Callable[[int], Any]]:
        with tqdm(total=total, desc=description, unit="frame", disable=quiet,
                  leave=False) as b:  # fmt: skip
            yield b.update

    return bar


def _no_progress(description: str, total: int) -> AbstractContextManager[Callable[[int], Any]]:
    del description, total
    return nullcontext(lambda n: None)


def clip_files(inputs: tuple[Path, ...], out: Path) -> list[tuple[Path, Path]]:
    """Input files, each with its output name (relative to its input folder, without suffix).

    Folders are searched recursively for clip files; an output folder inside an input
    folder is refused (humimic never writes into its inputs).

    Raises:
        InputError: A missing input, a folder without clips, an output inside an input
            folder, or two inputs that would be written under the same name.
    """
    from humimic.datasets import SUPPORTED_SUFFIXES

    out_dir = out.resolve()
    files: list[tuple[Path, Path]] = []
    for p in inputs:
        if p.is_dir():
            if out_dir == p.resolve() or p.resolve() in out_dir.parents:
                raise InputError(
                    f"--out {out}: inside the input folder {p}; humimic never writes into "
                    "its inputs: choose a folder outside it"
                )
            found = sorted(f for f in p.rglob("*") if f.suffix.lower() in SUPPORTED_SUFFIXES)
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


def save_with_report(motion: Motion, path: Path, report: dict, report_path: Path | None) -> None:
    """Write the motion, then its JSON report (strict JSON: no NaN); no motion is left
    without its report."""
    save_motion(motion, path)
    if report_path is not None:
        try:
            atomic_write_text(report_path, json.dumps(report, indent=2, allow_nan=False) + "\n")
        except BaseException:
            path.unlink(missing_ok=True)
            raise


@dataclass(frozen=True, kw_only=True)
class ClipJob:
    """One clip of a batch, read and checked.

    Attributes:
        source: The clip's file.
        clip: The clip, from its start frame on.
        scene: Its scene (``interaction-mesh``), else None.
        motion_path: Where its motion goes (``.npz``).
        report_path: Where its JSON report goes, or None.
        map_path: Where the map proposed for its rig goes (``<motion>.map.yaml``), or None
            where a shipped or given map is used.
    """

    source: Path
    clip: HumanClip
    scene: Scene | None
    motion_path: Path
    report_path: Path | None
    map_path: Path | None = None


@dataclass(frozen=True, kw_only=True)
class ClipResult:
    """One clip retargeted and written.

    Attributes:
        source: The clip's file.
        motion_path: The motion written.
        report_path: The report written, or None.
        report: The report (JSON-ready): the retargeter's quality metrics, ``start_frame``,
            and ``dynamics`` for ``--method dynamics``.
    """

    source: Path
    motion_path: Path
    report_path: Path | None
    report: dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class RetargetBatch:
    """A batch whose inputs are read and checked (:func:`plan_retarget`); :meth:`run` writes.

    Attributes:
        jobs: The clips, in order.
        retargeters: One retargeter per skeleton of the clips.
        method: The retargeting method.
        fps: The output frame rate.
        dyn: Settings of the dynamics refinement (``dynamics``).
    """

    jobs: list[ClipJob]
    retargeters: dict[str, Retargeter]
    method: Method
    fps: float
    dyn: DynamicsConfig = field(default_factory=DynamicsConfig)
    csv: bool = False
    """Also write each motion as CSV beside its ``.npz`` (:mod:`humimic.formats.csv_motion`)."""

    def run(self, progress: Progress | None = None) -> Iterator[ClipResult]:
        """Retarget and write the clips one by one, yielding each as it is written.

        Args:
            progress: Progress bars, one per clip and pass (default: none).
        """
        bar = progress or _no_progress
        for job in self.jobs:
            clip, name = job.clip, job.source.name
            retargeter = self.retargeters[clip.skeleton]
            total = clip.num_frames_at(self.fps) * (1 if job.scene is None else 2)  # Two passes.
            with bar(name, total) as update:
                result = retargeter.run(clip, progress=update, scene=job.scene)
            motion, extra = result.motion, {}
            if self.method == "dynamics":
                from humimic.retarget.dynamics import refine

                with bar(f"{name} (dynamics)", motion.num_frames - 1) as update:
                    motion, extra["dynamics"] = refine(motion, self.dyn, progress=update)
            report = json_ready(
                {**result.report, **extra, "start_frame": int(clip.meta["start_frame"])}
            )
            if job.map_path is not None:
                # Written first: a motion is never left without the map that made it, nor
                # the map without its motion (removed if the motion cannot be written).
                text = yaml.safe_dump(map_data(retargeter.map), sort_keys=False)
                atomic_write_text(job.map_path, text)
                report["map_written"] = str(job.map_path)
            csv = job.motion_path.with_suffix(".csv") if self.csv else None
            try:
                if csv is not None:  # Before the motion: no motion without its CSV.
                    from humimic.formats.csv_motion import write_motion_csv

                    write_motion_csv(csv, motion.qpos, fps=motion.fps, robot=motion.robot,
                                     joint_names=tuple(motion.joint_names))  # fmt: skip
                    report["csv_written"] = str(csv)
                save_with_report(motion, job.motion_path, report, job.report_path)
            except BaseException:
                if job.map_path is not None:
                    job.map_path.unlink(missing_ok=True)
                if csv is not None:
                    from humimic.formats.csv_motion import meta_path

                    csv.unlink(missing_ok=True)
                    meta_path(csv).unlink(missing_ok=True)
                raise
            yield ClipResult(source=job.source, motion_path=job.motion_path,
                             report_path=job.report_path, report=report)  # fmt: skip


def check_settings(robot: str, method: Method, ik: RetargetConfig, mesh: InteractionConfig,
                    dyn: DynamicsConfig, scene: Path | None) -> None:  # fmt: skip
    """The settings, before any input is read; :class:`InputError` names the flag."""
    from humimic.robots import get_robot

    get_robot(robot, "--robot")
    ik.validate()
    mesh.validate()
    if method == "dynamics":
        from humimic.retarget.dynamics import physics_steps_per_frame
        from humimic.sim.setup import DEFAULT_SIM_DT

        dyn.validate()
        if physics_steps_per_frame(ik.fps, DEFAULT_SIM_DT) is None:
            raise InputError(
                f"--method dynamics: --ik.fps {ik.fps} is not a whole number of physics "
                "steps per frame (50 fps is)"
            )
    if (method == "interaction-mesh") != (scene is not None):
        raise InputError(
            "--method interaction-mesh needs --scene"
            if scene is None
            else "--scene is used by --method interaction-mesh only"
        )


def other_inputs(map_file: Path | None, scene: Path | None) -> dict[str, Path]:
    """The inputs besides the clips, by flag (no output may overwrite them)."""
    others: dict[str, Path] = {}
    if map_file is not None:
        others["--map"] = map_file
    if scene is not None and str(scene) != "auto":
        others["--scene"] = scene
    return others


def output_paths(
    inputs: tuple[Path, ...],
    files: list[tuple[Path, Path]],
    out: Path,
    report: Path | None,
    others: dict[str, Path],
    *,
    folder: bool = False,
) -> list[tuple[Path, Path | None]]:
    """Each clip's motion and report paths, checked: none is an input (``others``: the inputs
    besides the clips, by flag), every one can be written. ``out`` is a folder when ``folder``
    is true, there are several clips, or an input is a folder."""
    several = folder or len(files) > 1 or any(p.is_dir() for p in inputs)
    if several:
        if out.suffix:
            raise InputError(f"{out}: with several inputs --out must be a folder")
        if report is not None:
            raise InputError("--report names one file: with several inputs the reports go in --out")
        outs: list[tuple[Path, Path | None]] = [
            (out / f"{n}.npz", out / f"{n}.json") for _, n in files
        ]
    else:
        if out.suffix != ".npz":
            raise InputError(f"{out}: the output motion file must end in .npz")
        outs = [(out, report)]
    read = {f"the input {f}": f for f, _ in files} | others
    for motion_path, report_path in outs:
        check_not_input(motion_path, read, "--out")
        check_not_input(report_path, {**read, "--out": motion_path}, "--report")
        check_writable(motion_path)
        if report_path is not None:
            check_writable(report_path)
    return outs


def _read_clip(
    path: Path,
    units: str | float,
    up: str,
    skeleton: str | None,
    start: int | None,
    body_model: Path | None = None,
) -> HumanClip:
    """A clip from its file, from ``start`` on (default: 1 for CMU files, whose frame 0 is a
    T-pose; else 0)."""
    from humimic.datasets import load_bvh, load_clip
    from humimic.pipeline.robot_clip import is_motion_file, robot_motion_clip

    if path.suffix.lower() == ".bvh":
        clip = load_bvh(path, units=units, up="y" if up == "auto" else up, skeleton=skeleton)
    elif path.suffix.lower() == ".fbx":
        from humimic.datasets.fbx import load_fbx

        clip = load_fbx(path, units=units, up=up, skeleton=skeleton)
    elif is_motion_file(path):  # A robot's motion: robot-to-robot retargeting.
        clip = robot_motion_clip(path)
    else:
        clip = load_clip(path, skeleton=skeleton, body_model=body_model)
    first = start if start is not None else (1 if clip.skeleton == "cmu" else 0)
    if not 0 <= first < clip.num_frames:
        raise InputError(f"{path}: --start {first} outside the clip's {clip.num_frames} frames")
    return clip.slice(first)


@dataclass(frozen=True, kw_only=True)
class ClipOptions:
    """What :func:`plan_clip` needs besides the clip's paths (the flags of ``retarget``)."""

    robot: str = "g1"
    method: Method = "kinematic"
    ik: RetargetConfig = field(default_factory=RetargetConfig)
    mesh: InteractionConfig = field(default_factory=InteractionConfig)
    units: str | float = "auto"
    up: str = "auto"
    skeleton: str | None = None
    map_file: Path | None = None
    menagerie_root: Path | None = None
    start: int | None = None
    scene: Path | None = None
    body_model: Path | None = None


def plan_clip(
    f: Path,
    motion_path: Path,
    report_path: Path | None,
    opts: ClipOptions,
    retargeters: dict[str, Retargeter],
) -> ClipJob:
    """Read and check one clip: its map (shipped, matched by joint names, or proposed and
    written beside its motion), its retargeter (made once per skeleton, kept in
    ``retargeters``), its scene. Nothing is written.

    Raises:
        InputError: Naming the file or flag.
    """
    from humimic.retarget import Retargeter

    robot, scene = opts.robot, opts.scene
    auto_scene = scene is not None and str(scene) == "auto"
    clip = _read_clip(f, opts.units, opts.up, opts.skeleton, opts.start, opts.body_model)
    rmap, map_path = None, None
    if (
        opts.map_file is None
        and opts.skeleton is None
        and (clip.skeleton, robot) not in builtin_maps()
    ):
        # A rig with no shipped map: a shipped skeleton map its joint names match, or a
        # map proposed from its joint names and tree (written next to the motion).
        robot_file = robot_map_file(robot)
        if robot_file is None:
            raise InputError(f"--robot {robot}: no shipped robot map; give one with --map")
        sk = match_skeleton(clip.names) or propose_skeleton_map(clip.names, clip.parents, str(f))
        rmap = compose_map(sk, robot_file)
        if sk.skeleton == "proposed":
            map_path = motion_path.with_suffix(".map.yaml")
            check_not_input(map_path, {f"the input {f}": f}, "the proposed map")
            check_writable(map_path)
            clip = replace(clip, skeleton=f"proposed:{f}")
        else:
            clip = replace(clip, skeleton=sk.skeleton)
    if clip.skeleton not in retargeters:
        retargeters[clip.skeleton] = Retargeter(
            robot,
            clip.skeleton,
            opts.ik,
            map_file=opts.map_file,
            menagerie_root=opts.menagerie_root,
            retarget_map=rmap,
            method="kinematic" if opts.method == "dynamics" else opts.method,
            mesh=opts.mesh,
        )
    retargeters[clip.skeleton].check(clip)
    clip_scene = None
    if scene is not None:
        from humimic.datasets.scene import load_scene

        clip_scene = load_scene(f.parent if auto_scene else scene)
    return ClipJob(source=f, clip=clip, scene=clip_scene, motion_path=motion_path,
                   report_path=report_path, map_path=map_path)  # fmt: skip


def plan_retarget(
    inputs: tuple[Path, ...],
    out: Path,
    *,
    report: Path | None = None,
    robot: str = "g1",
    method: Method = "kinematic",
    ik: RetargetConfig | None = None,
    mesh: InteractionConfig | None = None,
    dyn: DynamicsConfig | None = None,
    units: str | float = "auto",
    up: str = "auto",
    skeleton: str | None = None,
    map_file: Path | None = None,
    menagerie_root: Path | None = None,
    start: int | None = None,
    scene: Path | None = None,
    csv: bool = False,
    body_model: Path | None = None,
) -> RetargetBatch:
    """Read and check a batch of clips (``humimic retarget``): nothing is written.

    Args:
        inputs: Clip files (``.bvh``, ``.fbx``, ``.npy``, ``.npz``) or folders of them.
        out: The output ``.npz`` for one input file; an output folder for several inputs or a
            folder (``<out>/<name relative to its folder>.npz`` and ``.json``).
        report: The JSON report of a single input.
        robot: Registry name.
        method: ``kinematic``, ``interaction-mesh`` (needs ``scene``) or ``dynamics``
            (kinematic, then :func:`humimic.retarget.dynamics.refine`).
        ik: IK settings (default: :func:`humimic.configs.retarget_default`).
        mesh: Interaction-mesh settings.
        dyn: Dynamics settings.
        units: BVH units (:func:`humimic.datasets.load_bvh`).
        up: Up axis of BVH and FBX files (``auto``: y for BVH, found from the skeleton for FBX).
        skeleton: Skeleton name for the map (default: detected).
        map_file: A human-to-robot map file (default: the shipped map).
        menagerie_root: Where to load the robot from.
        start: First source frame (default: 1 for CMU files, else 0).
        scene: The clips' scene (a scene file, a mesh, a folder); ``auto``: each clip's own
            folder.

    Raises:
        InputError: Bad settings or input (names the flag or file), before any output.
    """
    ik = ik or RetargetConfig()
    mesh = mesh or InteractionConfig()
    dyn = dyn or DynamicsConfig()
    check_settings(robot, method, ik, mesh, dyn, scene)
    if not inputs:
        raise InputError("give at least one input clip or folder")
    files = clip_files(inputs, out)
    outs = output_paths(inputs, files, out, report, other_inputs(map_file, scene))

    opts = ClipOptions(robot=robot, method=method, ik=ik, mesh=mesh, units=units, up=up,
                       skeleton=skeleton, map_file=map_file, menagerie_root=menagerie_root,
                       start=start, scene=scene, body_model=body_model)  # fmt: skip
    jobs: list[ClipJob] = []
    retargeters: dict[str, Retargeter] = {}
    for (f, _), (motion_path, report_path) in zip(files, outs, strict=True):
        jobs.append(plan_clip(f, motion_path, report_path, opts, retargeters))
    if csv:
        from humimic.formats.csv_motion import meta_path

        read = {f"the input {j.source}": j.source for j in jobs}
        for j in jobs:
            for p in (
                j.motion_path.with_suffix(".csv"),
                meta_path(j.motion_path.with_suffix(".csv")),
            ):
                check_not_input(p, read, "--format csv")
                check_writable(p)
    return RetargetBatch(jobs=jobs, retargeters=retargeters, method=method, fps=ik.fps, dyn=dyn,
                         csv=csv)  # fmt: skip


__all__ = [
    "ClipJob",
    "ClipResult",
    "Progress",
    "RetargetBatch",
    "clip_files",
    "frame_bars",
    "plan_retarget",
    "save_with_report",
]
