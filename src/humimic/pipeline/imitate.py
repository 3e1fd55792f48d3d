"""``humimic imitate``: a clip in, a policy that performs it out, with its report: retarget,
train (refining first where the recipe needs it), evaluate, export, report."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from humimic.configs.jobs import EvalSettings, ExportSettings, ImitateSettings
from humimic.configs.runs import TrainSettings
from humimic.errors import InputError, MissingDependencyError, OutputPathError
from humimic.io import atomic_write_text, json_ready

PHYSICS: dict[str, dict[str, Any]] = {
    "nominal": {"dr": "none", "physics": None},
    "dr_default": {"dr": "default", "physics": None},
    "backpack": {"dr": "none", "physics": "backpack"},
    "worn_knees": {"dr": "none", "physics": "worn_knees"},
}
"""The evaluations of a job: label -> ``humimic eval`` settings (the last two are the shipped
robots that no training step sees)."""

EVAL_OVERHEAD_MIN = 1.0
"""Minutes the evaluations, the learning curve, the export and the pictures take after
training, about (2 cores, a 3 s clip: 0.8 min measured): for the ETA."""

Screenshot = Callable[[Path, Path, Path], None]
"""``screenshot(eval_mcap, png, gif)``: pictures of the evaluation's first episode beside its
reference (a filmstrip, a video); raises :class:`InputError` saying why it cannot."""


def _stage(k: int, name: str, started: float, quiet: bool, note: str = "") -> None:
    if not quiet:
        mins = (time.perf_counter() - started) / 60
        print(f"[{k}/5] {name} ({mins:.1f} min in){': ' + note if note else ''}", flush=True)


def _check(s: ImitateSettings) -> None:
    """Everything that can be refused before any work: settings, the clip, the folder."""
    s.validate()
    if s.clip.is_dir():
        _folder_clips(s.clip, s.out)
    elif not s.clip.is_file():
        raise InputError(f"{s.clip}: no such clip file or folder")
    if s.out.exists() and (not s.out.is_dir() or any(s.out.iterdir())):
        raise InputError(f"--out {s.out}: must be a new or empty folder")


def _folder_clips(folder: Path, out: Path) -> tuple[list[Path], bool]:
    """The clips of a folder job and whether they are robot motions already (then trained on
    as they are) rather than human clips (then retargeted first).

    Raises:
        InputError: No clip, clips in subfolders (a library is one folder), robot motions
            mixed with human clips, or ``out`` inside the folder.
    """
    from humimic.datasets import SUPPORTED_SUFFIXES

    if out.resolve() == folder.resolve() or folder.resolve() in out.resolve().parents:
        raise InputError(f"--out {out}: inside the clip folder {folder}; humimic never writes "
                         "into its inputs")  # fmt: skip
    found = sorted(f for f in folder.rglob("*") if f.suffix.lower() in SUPPORTED_SUFFIXES)
    if not found:
        raise InputError(f"{folder}: the folder holds no clip ({', '.join(SUPPORTED_SUFFIXES)})")
    nested = next((f for f in found if f.parent != folder), None)
    if nested is not None:
        raise InputError(f"{folder}: {nested.relative_to(folder)} is in a subfolder; put the "
                         "library's clips in one folder")  # fmt: skip
    robot = [f.suffix == ".npz" and _is_robot_motion(f) for f in found]
    if any(robot) and not all(robot):
        first = found[robot.index(True)]
        raise InputError(f"{folder}: {first.name} is a robot motion beside human clips; a job "
                         "takes a folder of one or the other")  # fmt: skip
    return found, all(robot)


def imitate(s: ImitateSettings, *, screenshot: Screenshot | None = None) -> dict[str, Any]:
    """Run the whole job into ``s.out``; returns the report's numbers (also ``report.json``).

    Stages: (1) retarget the clip (``motion.npz`` and its report; a robot motion is used as
    it is); (2) ``humimic train`` for ``s.minutes`` (``run/``; its refined reference is
    ``run/reference.npz``); (3) evaluate the last checkpoint under nominal physics, DR
    ``default`` and the shipped unseen robots (``eval_*.json``; ``eval_dr_default.mcap``
    holds the first randomized episode), and the checkpoints along the way (the learning
    curve); (4) export ``policy.onnx``; (5) the plots and ``report.md``.

    Bad input (the clip, the settings, a folder that is not new or empty) is refused before
    anything is written. Every file is written whole (atomically) when its stage ends.
    """
    from humimic.pipeline.batch import plan_retarget

    _check(s)
    started = time.perf_counter()
    finish = datetime.now() + timedelta(minutes=s.minutes + EVAL_OVERHEAD_MIN)
    if not s.quiet:
        print(f"humimic imitate {s.clip.name} -> {s.out}: about {s.minutes + EVAL_OVERHEAD_MIN:.0f} "
              f"min, done about {finish:%H:%M}")  # fmt: skip
    out = s.out
    motion_path = out / "motion.npz"
    batch = None
    if s.clip.is_dir():
        motion_path = out / "motions"
    elif s.clip.suffix == ".npz" and _is_robot_motion(s.clip):
        from humimic.motion import load_motion

        if load_motion(s.clip).robot != s.robot:
            raise InputError(f"{s.clip}: a motion of another robot than --robot {s.robot}")
    else:
        batch = plan_retarget((s.clip,), motion_path, report=out / "motion.json", robot=s.robot)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"--out {out}: cannot create the folder: {e.strerror or e}") from None
    try:
        return _stages(s, batch, motion_path, started, screenshot)
    except BaseException:
        if created and not (out / "run" / "config.yaml").exists():  # Nothing trained yet.
            shutil.rmtree(out, ignore_errors=True)
        raise


def _stages(
    s: ImitateSettings, batch: Any, motion_path: Path, started: float,
    screenshot: Screenshot | None,
) -> dict[str, Any]:  # fmt: skip
    """The five stages of :func:`imitate` (its checks done, its folder made)."""
    from humimic.pipeline.reference import prepare_reference
    from humimic.tracking.train import train

    out = s.out

    _stage(1, "retarget", started, s.quiet, s.clip.name)
    report: dict[str, Any] = {"clip": str(s.clip), "robot": s.robot, "minutes": s.minutes}
    library = s.clip.is_dir()
    if library:
        motion_path, report["retarget"] = _retarget_folder(s, motion_path)
    elif batch is not None:
        from humimic.pipeline.batch import frame_bars

        (result,) = list(batch.run(progress=frame_bars(s.quiet)))
        report["retarget"] = {k: result.report.get(k) for k in _RETARGET_KEYS}
    else:
        motion_path = s.clip
        report["retarget"] = None

    _stage(2, "train", started, s.quiet, f"{s.minutes:g} min, refining first if needed")
    run = out / "run"
    settings = TrainSettings(motion=motion_path, out=run, robot=s.robot, num_envs=s.num_envs,
                             device=s.device, seed=s.seed, max_minutes=s.minutes,
                             quiet=s.quiet)  # fmt: skip
    t_train = time.perf_counter()
    settings = prepare_reference(settings, quiet=s.quiet)
    last = train(settings, started=t_train)
    report["train"] = {"iterations": int(last.get("iteration", 0)),
                       "env_steps": int(last.get("env_steps", 0)),
                       "seconds": float(last.get("seconds", 0.0)),
                       "reference": str(settings.motion)}  # fmt: skip
    if library:
        from humimic.tracking.task import library_files

        trained = {f.stem for f in library_files(settings.motion)}
        report["train"]["left_out"] = sorted(
            f.stem for f in library_files(motion_path) if f.stem not in trained
        )

    _stage(3, "evaluate", started, s.quiet, f"{s.episodes} episodes x {len(PHYSICS)} physics")
    report["eval"], trace = _evaluate(s, run, library)
    # A library's learning curve is training's alone: evaluating every checkpoint on every
    # clip would cost more than the evaluations above.
    curve = [] if library else _curve(run, s)
    report["curve"] = curve

    _stage(4, "export", started, s.quiet)
    from humimic.tracking.export import export

    report["onnx"] = str(export(ExportSettings(run=run, out=out / "policy.onnx")))

    _stage(5, "report", started, s.quiet)
    _plots(run, curve, trace, out)
    report["screenshot"] = _screenshot(screenshot, out)
    report["wall_seconds"] = time.perf_counter() - started
    atomic_write_text(out / "report.json", json.dumps(json_ready(report), indent=2) + "\n")
    atomic_write_text(out / "report.md", render_report(report, s))
    if not s.quiet:
        print(f"wrote {out / 'report.md'} ({report['wall_seconds'] / 60:.1f} min)")
    return report


_RETARGET_KEYS = ("frames", "fps", "keypoint_error_mm_mean", "foot_skating_mm_per_s",
                  "max_ground_penetration_mm", "joint_limit_violations")  # fmt: skip


def _is_robot_motion(path: Path) -> bool:
    """Whether an ``.npz`` is a humimic robot motion (else: joint positions of a human)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return "schema_version.npy" in z.namelist()
    except (OSError, zipfile.BadZipFile):
        return False  # The clip reader names what is wrong with it.


def _evaluate(s: ImitateSettings, run: Path, library: bool) -> tuple[dict[str, Any], Any]:
    """The last checkpoint under each physics of :data:`PHYSICS` (JSON per physics; the
    randomized one's first episode as MCAP, of the first clip for a library; where the
    randomized episodes fail as ``failures_dr_default.png``); returns the metrics and that
    episode. A library is evaluated clip by clip (``clips`` in each physics' results)."""
    from humimic.tracking.curve import plot_failures
    from humimic.tracking.evaluate import (
        evaluate_library,
        failure_table,
        library_clips,
        run_evaluation,
        write_eval_mcap,
    )

    results, trace = {}, None
    for label, kw in PHYSICS.items():
        # The field's protocols are deterministic plays without DR: once, on the nominal robot.
        es = EvalSettings(run=run, episodes=s.episodes, device=s.device, **kw)
        nominal = label == "nominal"
        clips = library_clips(es) if library else None
        if clips is not None:
            r, evs = evaluate_library(es, clips, protocols=nominal)
            ev = evs[0]
        else:
            ev = run_evaluation(es, protocols=nominal)
            r = ev.results
        atomic_write_text(s.out / f"eval_{label}.json", json.dumps(json_ready(r), indent=2) + "\n")
        if label == "dr_default":
            write_eval_mcap(s.out / "eval_dr_default.mcap", ev.motion, ev.joint_names,
                            ev.step_dt, ev.policy, ev.open_loop, ev.results)  # fmt: skip
            plot_failures(failure_table(r), r["step_dt"], s.out / "failures_dr_default.png",
                          "where the policy's episodes fail under DR default")  # fmt: skip
            trace = ev
        results[label] = {k: r[k] for k in ("policy", "open_loop", "protocols", "clips")
                          if k in r}  # fmt: skip
    return results, trace


def _retarget_folder(s: ImitateSettings, motions: Path) -> tuple[Path, dict[str, Any] | None]:
    """Stage 1 of a folder job: robot motions are the library as they are; human clips are
    retargeted on worker processes into ``motions`` (its manifest records each outcome). A
    clip that fails is printed and left out. Returns the library and what retargeting did.

    Raises:
        InputError: Every clip failed.
    """
    from humimic.configs import retarget_default
    from humimic.pipeline.batch import ClipOptions
    from humimic.pipeline.dataset import run_dataset

    _, robot_motions = _folder_clips(s.clip, s.out)
    if robot_motions:
        return s.clip, None
    summary = run_dataset((s.clip,), motions, ClipOptions(robot=s.robot, ik=retarget_default()),
                          quiet=s.quiet)  # fmt: skip
    failed = {r["key"]: r["error"] for r in summary.failed}
    for name, error in failed.items():
        print(f"left out of the job: {name} (retargeting failed: {error})")
    if not summary.done:
        raise InputError(f"{s.clip}: no clip of the folder could be retargeted: "
                         f"{next(iter(failed.values()))}")  # fmt: skip
    return motions, {"clips": {r["key"]: r["headline"] for r in summary.done},
                     "failed": failed, "seconds": summary.seconds}  # fmt: skip


def _curve(run: Path, s: ImitateSettings) -> list[dict[str, float]]:
    from humimic.tracking.curve import evaluation_curve

    return evaluation_curve(run, episodes=min(8, s.episodes), dr="default", points=8,
                            device=s.device)  # fmt: skip


def per_body_errors(ev: Any) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """The tracked bodies' world position errors over the first policy episode of an
    evaluation: times [s] Shape: (K,), errors [mm] Shape: (K, B), and the body names."""
    from humimic.motion import motion_from_qpos
    from humimic.robots import get_robot, nominal_model
    from humimic.tracking.config import tracking_task

    motion = ev.motion
    qpos = np.asarray(ev.policy.qpos)
    k = min(len(qpos), motion.num_frames)
    model = nominal_model(get_robot(motion.robot))
    rolled = motion_from_qpos(model, qpos[:k], motion.fps, motion.robot)
    names = tracking_task(motion.robot, "none").body_names
    idx = [rolled.body_names.index(b) for b in names]
    ref = [motion.body_names.index(b) for b in names]
    err = np.linalg.norm(rolled.body_pos_w[:, idx] - motion.body_pos_w[:k, ref], axis=-1)
    return np.arange(k) * ev.step_dt, 1e3 * err, names


def _plots(run: Path, curve: list[dict[str, float]], ev: Any, out: Path) -> None:
    """``learning_curve.png`` and ``body_error.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from humimic.io import atomic_write
    from humimic.tracking.curve import plot_learning_curve, progress_rows

    plot_learning_curve(progress_rows(run), curve, out / "learning_curve.png",
                        f"{run.parent.name}: training and evaluation (DR default)")  # fmt: skip
    t, err, names = per_body_errors(ev)
    fig, ax = plt.subplots(figsize=(9, 4))
    worst = np.argsort(err.mean(axis=0))[::-1][:6]
    for b in worst:
        ax.plot(t, err[:, b], label=names[b])
    ax.plot(t, err.mean(axis=1), "k--", label="mean of all tracked bodies")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("world position error [mm]")
    ax.set_title("first evaluation episode under DR default: the six worst bodies")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_write(out / "body_error.png") as f:
        fig.savefig(f, format="png", dpi=90)
    plt.close(fig)


def _screenshot(screenshot: Screenshot | None, out: Path) -> str | None:
    """The randomized rollout beside its reference (``rollout.png``, a filmstrip, and
    ``rollout.gif``), or why there is none."""
    if screenshot is None:
        return None
    png = out / "rollout.png"
    try:
        screenshot(out / "eval_dr_default.mcap", png, out / "rollout.gif")
    except (InputError, MissingDependencyError) as e:  # No renderer here: the report says so.
        return f"not taken: {e}"
    return str(png)


def _measured(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f}"


def render_report(r: dict[str, Any], s: ImitateSettings) -> str:
    """``report.md`` from the job's numbers."""
    lines = [f"# humimic imitate: {Path(r['clip']).name} on the {r['robot']}", ""]
    if r["retarget"] and "clips" in r["retarget"]:
        rt = r["retarget"]
        lines += [f"Retargeted {len(rt['clips'])} clips in {rt['seconds']:.0f} s"
                  + (f"; left out (failed): {', '.join(rt['failed'])}" if rt["failed"] else "")
                  + ".", ""]  # fmt: skip
    elif r["retarget"]:
        rt = r["retarget"]
        lines += [f"Retargeted: {rt['frames']} frames at {rt['fps']:g} fps, key points "
                  f"{rt['keypoint_error_mm_mean']:.1f} mm, foot skating "
                  f"{_measured(rt['foot_skating_mm_per_s'])} mm/s, ground penetration "
                  f"{rt['max_ground_penetration_mm']:.1f} mm, joint-limit violations "
                  f"{rt['joint_limit_violations']}.", ""]  # fmt: skip
    t = r["train"]
    if t.get("left_out"):
        lines += [f"Left out of training (refining failed): {', '.join(t['left_out'])}.", ""]
    lines += [f"Trained {t['seconds'] / 60:.1f} min of wall time (refining included): "
              f"{t['iterations']} PPO iterations, {t['env_steps']:,} env steps; reference "
              f"`{t['reference']}`.", "",
              f"Evaluated on {s.episodes} episodes per physics"
              + (" and clip" if r["eval"].get("nominal", {}).get("clips") else "")
              + ", each the whole clip from its first frame (policy, and the open loop: the "
              "stored controls alone):", "",
              "| physics | controller | success | mean steps | global MPJPE mm | "
              "root-relative MPJPE mm | joint error rad |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for label, ev in r["eval"].items():
        for ctl in ("policy", "open_loop"):
            m = ev[ctl]
            lines.append(f"| {label} | {ctl.replace('_', ' ')} | {100 * m['success_rate']:.0f}% | "
                         f"{m['mean_steps']:.0f} | {m['mpjpe_global_mm']:.0f} | "
                         f"{m['mpjpe_root_mm']:.0f} | {m['joint_error_rad']:.3f} |")  # fmt: skip
    clips = r["eval"].get("dr_default", {}).get("clips")
    proto = r["eval"].get("nominal", {}).get("protocols")
    if clips:
        lines += ["", "Per clip (the tables above are the means over the clips):", "",
                  "| clip | frames | DR default success | global MPJPE mm | root-relative MPJPE "
                  "mm | BeyondMimic | PHC |", "|---|---|---|---|---|---|---|"]  # fmt: skip
        for name, c in clips.items():
            m = c["policy"]
            fate = {k: "n/a" if proto is None else
                       ("fails" if proto[k]["per_clip"][name]["failed"] else "ok")
                       for k in ("beyondmimic", "phc")}  # fmt: skip
            lines.append(f"| {name} | {c['frames']} | {100 * m['success_rate']:.0f}% | "
                         f"{m['mpjpe_global_mm']:.0f} | {m['mpjpe_root_mm']:.0f} | "
                         f"{fate['beyondmimic']} | {fate['phc']} |")  # fmt: skip
    if proto is not None:
        lines += ["", *protocol_lines(proto)]
    lines += ["", "Where the randomized episodes fail: ![failures](failures_dr_default.png)"]
    first = next((c for c in r["curve"] if c["success_rate"] > 0.0), None)
    lines += ["", "Learning curve (training episodes, and checkpoints evaluated under DR "
              "default): ![learning curve](learning_curve.png)", "",
              ("First evaluated checkpoint that completed the clip (on at least one episode): "
               + (f"iteration {first['iteration']:.0f}, {first['seconds'] / 60:.1f} min."
                  if first else "none.")) if r["curve"] else
              "A library's curve is training's alone (no checkpoint evaluated per clip).", "",
              "Per-body error of the first randomized episode: ![per-body error](body_error.png)",
              ""]  # fmt: skip
    shot = r.get("screenshot")
    if shot and not shot.startswith("not taken"):
        lines += ["The first randomized episode (top) beside the reference (bottom), "
                  "rendered by MuJoCo: ![rollout](rollout.png); the whole episode: "
                  "![video](rollout.gif); `humimic view eval_dr_default.mcap` plays it.",
                  ""]  # fmt: skip
    else:
        lines += [f"Rollout pictures: {shot or 'not asked for'}; `humimic view "
                  "eval_dr_default.mcap` shows the rollout.", ""]  # fmt: skip
    lines += [f"The policy: `{r['onnx']}` (ONNX; its PD targets are the run's action base plus "
              "the scaled actions, docs/tracking.md).", "",
              f"Total: {r['wall_seconds'] / 60:.1f} min.", ""]  # fmt: skip
    return "\n".join(lines)


def verdict(r: dict[str, Any]) -> str:
    """One line on what a job's policy does, from its measured numbers: the share of the
    randomized episodes that complete the clip(s) and their error, and the protocols'
    failures (on the nominal robot)."""
    dr = r["eval"]["dr_default"]["policy"]
    share, mm = dr["success_rate"], dr["mpjpe_global_mm"]
    what = ("tracks the clip" if share >= 0.9 else
            "tracks the clip in part" if share >= 0.5 else "does not track the clip yet")  # fmt: skip
    line = (f"verdict: the {r['robot']} {what}: {100 * share:.0f}% of "
            f"{dr['episodes']} randomized episodes complete it (global MPJPE {mm:.0f} mm)")  # fmt: skip
    proto = r["eval"].get("nominal", {}).get("protocols")
    if proto is not None:
        bm, phc = proto["beyondmimic"], proto["phc"]
        line += (f"; on the nominal robot {bm['failed_clips']} of {bm['clips']} clips fail "
                 f"BeyondMimic's protocol and {100 * (phc['success_rate'] or 0.0):.0f}% pass "
                 "PHC's")  # fmt: skip
    if share < 0.9:
        line += f"; {r['minutes']:g} min of training: more minutes (--minutes) help"
    return line + "."


def protocol_lines(p: dict[str, Any]) -> list[str]:
    """The field's protocols (:mod:`humimic.tracking.protocols`) as report lines: each rule,
    then its result."""

    def num(x: float | None, fmt: str) -> str:
        return "n/a" if x is None else format(x, fmt)

    bm, phc = p["beyondmimic"], p["phc"]
    a = phc["all"]
    return [
        f"BeyondMimic's protocol ({bm['rule']}): {bm['failed_clips']} of {bm['clips']} clips "
        f"failed, mean normalized return {num(bm['mean_normalized_return'], '.2f')}.", "",
        f"PHC's protocol ({phc['rule']}): success {num(phc['success_rate'], '.0%')}; global "
        f"MPJPE {num(a['mpjpe_global_mm'], '.1f')} mm, root-relative "
        f"{num(a['mpjpe_root_mm'], '.1f')} mm, velocity error "
        f"{num(a['vel_error_mm_per_frame'], '.1f')} mm/frame, acceleration error "
        f"{num(a['acc_error_mm_per_frame2'], '.2f')} mm/frame^2 (at the policy rate).",
    ]  # fmt: skip


__all__ = ["PHYSICS", "imitate", "per_body_errors", "protocol_lines", "render_report", "verdict"]
