"""Whole datasets: every clip of the inputs retargeted on a pool of worker processes, each clip
on its own (a bad clip fails alone), every outcome recorded in a manifest, so that an
interrupted run (Ctrl-C, ``kill -9``, a crash) resumes and redoes nothing that finished.

The manifest, ``<out>/manifest.jsonl``, holds one JSON record per line, appended (and synced to
disk) as each clip ends: the input (its output name, path, size, SHA-256), the settings' digest,
the status (``done`` or ``failed``), the report's headline figures or the error, the time. The
last record of an input counts. On a rerun an input is skipped when its last record is ``done``
(or refused as bad input) for the same bytes and settings and its outputs are there; a changed
input, changed settings, or a failure that was not the input's (a worker that died) are redone.
Outputs are written atomically (a temporary file renamed into place), so a killed run leaves no
half-written motion; the temporary files it leaves are removed on the next run.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any

from humimic.configs import DynamicsConfig
from humimic.errors import HumimicError, InputError
from humimic.pipeline.batch import (
    ClipOptions,
    RetargetBatch,
    check_settings,
    clip_files,
    other_inputs,
    output_paths,
    plan_clip,
)

MANIFEST_NAME = "manifest.jsonl"

HEADLINE = (
    "frames",
    "keypoint_error_mm_mean",
    "keypoint_error_mm_p95",
    "foot_skating_mm_per_s",
    "max_ground_penetration_mm",
    "joint_limit_violations",
    "self_collision_frames",
    "max_self_penetration_mm",
)
"""The report's figures a manifest record keeps (the full report is the clip's ``.json``)."""

WORST = ("keypoint_error_mm_mean", "max_ground_penetration_mm", "self_collision_frames",
         "joint_limit_violations")  # fmt: skip
"""The figures the summary names the worst clips by."""


@dataclass(frozen=True, kw_only=True)
class DatasetTask:
    """One input of a dataset run."""

    key: str  # its output name, relative to --out, without suffix
    source: Path
    motion_path: Path
    report_path: Path
    size: int
    sha256: str


@dataclass(kw_only=True)
class DatasetSummary:
    """What a dataset run did.

    Attributes:
        done: Records of the clips retargeted now.
        skipped: Records of the clips a previous run finished (unchanged).
        failed: Records of the clips that failed now.
        manifest: The manifest's path.
        seconds: Wall time of this run.
    """

    done: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, Any]] = field(default_factory=list)
    failed: list[dict[str, Any]] = field(default_factory=list)
    manifest: Path = Path()
    seconds: float = 0.0


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def settings_digest(settings: dict[str, Any]) -> str:
    """A digest of every setting that changes an output (dataclasses by their fields)."""
    data = {k: asdict(v) if is_dataclass(v) and not isinstance(v, type) else v
            for k, v in settings.items()}  # fmt: skip
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class Manifest:
    """The append-only record of a dataset run (``manifest.jsonl``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.last: dict[str, dict[str, Any]] = {}
        self.unreadable = 0
        if path.is_file():
            for line in path.read_text(errors="replace").splitlines():
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:  # A line cut by a kill: that clip is redone.
                    self.unreadable += 1
                    continue
                if isinstance(rec, dict) and isinstance(rec.get("key"), str):
                    self.last[rec["key"]] = rec
            with open(path, "rb+") as f:  # A line cut by a kill: end it, lest the next join it.
                f.seek(0, os.SEEK_END)
                if f.tell():
                    f.seek(-1, os.SEEK_END)
                    if f.read(1) != b"\n":
                        f.write(b"\n")

    def append(self, record: dict[str, Any]) -> None:
        line = json.dumps(record, allow_nan=False, default=str) + "\n"
        try:
            with open(self.path, "a") as f:
                f.write(line)
                f.flush()
                os.fsync(f.fileno())
        except OSError as e:  # A full disk, a folder taken away.
            raise InputError(f"{self.path}: cannot record {record['key']} ({e.strerror})") from None
        self.last[record["key"]] = record


def default_workers() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # Not Linux.
        return max(1, os.cpu_count() or 1)


_RETARGETERS: dict[str, Any] = {}
"""A worker process's retargeters, one per skeleton, kept across its clips."""


def task_outcome(work: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """A task's record: ``done`` with the headline ``work()`` returns, or ``failed`` with the
    error, its kind (``input``: refused, not redone on a rerun; ``internal``: a bug or a
    resource, redone), and the seconds it took."""
    t0 = time.perf_counter()
    try:
        out: dict[str, Any] = {"status": "done", "headline": work()}
    except HumimicError as e:
        out = {"status": "failed", "error_kind": "input", "error": str(e)}
    except Exception as e:  # Not the input's fault: recorded, redone on a rerun.
        out = {"status": "failed", "error_kind": "internal", "error": f"{type(e).__name__}: {e}"}
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


def retarget_task(task: DatasetTask, opts: ClipOptions, dyn: DynamicsConfig, csv: bool) -> dict:
    """Retarget and write one clip (in a worker process); its outcome as a record."""

    def work() -> dict[str, Any]:
        job = plan_clip(task.source, task.motion_path, task.report_path, opts, _RETARGETERS)
        batch = RetargetBatch(jobs=[job], retargeters=_RETARGETERS, method=opts.method,
                              fps=opts.ik.fps, dyn=dyn, csv=csv)  # fmt: skip
        (result,) = list(batch.run())
        return {k: result.report.get(k) for k in HEADLINE}

    return task_outcome(work)


def motion_files(folder: Path, out: Path) -> list[tuple[Path, Path]]:
    """The robot motions (``.npz`` with ``qpos`` and ``robot``) under a folder, each with its
    output name; other ``.npz`` (arrays of human joint positions) are left alone, unreadable ones
    kept (each then fails alone, saying why).

    Raises:
        InputError: No motion there, or ``out`` inside the folder.
    """
    from humimic.npyio import npz_keys

    if out.resolve() == folder.resolve() or folder.resolve() in out.resolve().parents:
        raise InputError(f"--out {out}: inside the input folder {folder}; humimic never writes "
                         "into its inputs: choose a folder outside it")  # fmt: skip
    found = []
    for f in sorted(folder.rglob("*.npz")):
        try:
            keys = npz_keys(f)
        except InputError:
            keys = set()
        # A motion, or unreadable (no arrays found): the latter fails on its own, saying why.
        take = {"qpos", "robot"} <= keys or not keys
        if take:
            found.append((f, f.relative_to(folder).with_suffix("")))
    if not found:
        raise InputError(f"{folder}: no robot motion (.npz with qpos and robot) in this folder")
    return found


def _stale_temporaries(tasks: list[DatasetTask]) -> list[Path]:
    """Temporary files a killed run left beside the outputs (``.<name>.*.tmp``)."""
    found = []
    for t in tasks:
        for target in (t.motion_path, t.report_path):
            if target.parent.is_dir():
                found += list(target.parent.glob(f".{target.name}.*.tmp"))
    return found


def plan_tasks(
    files: list[tuple[Path, Path]],
    outs: list[tuple[Path, Path | None]],
    out: Path,
    digest: str,
) -> tuple[list[DatasetTask], list[dict[str, Any]], Manifest]:
    """Inputs (with their output names) split into those to run (largest first) and those a
    previous run finished (their records), and the manifest; the folder made, stale temporary
    files removed.

    Raises:
        InputError: ``--out`` a file, a manifest that is not a file, a folder not made.
    """
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: a file, not a folder")
    if (out / MANIFEST_NAME).exists() and not (out / MANIFEST_NAME).is_file():
        raise InputError(f"--out {out}: {MANIFEST_NAME} there is not a file")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"--out {out}: cannot create the folder ({e.strerror})") from None
    manifest = Manifest(out / MANIFEST_NAME)
    tasks, skipped = [], []
    for (f, name), (motion_path, report_path) in zip(files, outs, strict=True):
        assert report_path is not None
        task = DatasetTask(key=name.as_posix(), source=f.absolute(),
                           motion_path=motion_path.absolute(),
                           report_path=report_path.absolute(), size=f.stat().st_size,
                           sha256=file_sha256(f))  # fmt: skip
        rec = manifest.last.get(task.key)
        same = (
            rec is not None and rec.get("sha256") == task.sha256 and rec.get("settings") == digest
        )
        if (
            same
            and rec is not None
            and (
                (rec.get("status") == "done" and motion_path.is_file() and report_path.is_file())
                or (rec.get("status") == "failed" and rec.get("error_kind") == "input")
            )
        ):
            skipped.append(rec)
        else:
            tasks.append(task)
    for tmp in _stale_temporaries(tasks):
        tmp.unlink(missing_ok=True)
    tasks.sort(key=lambda t: -t.size)
    return tasks, skipped, manifest


def plan_dataset(
    inputs: tuple[Path, ...],
    out: Path,
    opts: ClipOptions,
    *,
    dyn: DynamicsConfig | None = None,
    csv: bool = False,
) -> tuple[list[DatasetTask], list[dict[str, Any]], Manifest, str]:
    """The clips of a retargeting run, split into those to retarget (largest first) and those a
    previous run finished, with the manifest and the settings' digest. Settings and paths are
    checked before anything is written.

    Raises:
        InputError: A bad flag, a missing input, an output that cannot be written.
    """
    dyn = dyn or DynamicsConfig()
    check_settings(opts.robot, opts.method, opts.ik, opts.mesh, dyn, opts.scene)
    if not inputs:
        raise InputError("give at least one input clip or folder")
    if out.suffix:
        raise InputError(f"{out}: with several inputs --out must be a folder")
    files = clip_files(inputs, out)
    outs = output_paths(inputs, files, out, None, other_inputs(opts.map_file, opts.scene))
    digest = settings_digest({"opts": opts, "dyn": dyn, "csv": csv})
    tasks, skipped, manifest = plan_tasks(files, outs, out, digest)
    return tasks, skipped, manifest, digest


def run_dataset(
    inputs: tuple[Path, ...],
    out: Path,
    opts: ClipOptions,
    *,
    dyn: DynamicsConfig | None = None,
    csv: bool = False,
    workers: int | None = None,
    ray: str | None = None,
    on_record: Callable[[dict[str, Any]], None] | None = None,
    quiet: bool = False,
) -> DatasetSummary:
    """Retarget every clip of ``inputs`` into ``out`` (see the module's text).

    Args:
        workers: Processes (default: the cores); with ``ray="local"``, the local instance's CPUs.
        ray: Run the clips as Ray tasks (one CPU each) instead of a process pool: a cluster's
            address, ``auto`` (the cluster this machine belongs to), or ``local`` (start a
            local instance). Inputs and outputs must be on a path every node sees; this
            process keeps the manifest. A Ray instance this process already started is used
            as it is.
        on_record: Called with each record as it is written (for progress and logs).
        quiet: No progress bar.

    Returns:
        The summary; failed clips are in it, not raised.

    Raises:
        InputError: Bad settings or paths (before anything is written).
        KeyboardInterrupt: Interrupted; what finished is in the manifest.
    """
    dyn = dyn or DynamicsConfig()
    t0 = time.perf_counter()
    tasks, skipped, manifest, digest = plan_dataset(inputs, out, opts, dyn=dyn, csv=csv)
    return run_tasks(tasks, skipped, manifest, digest, retarget_task, (opts, dyn, csv),
                     workers=workers, ray=ray, on_record=on_record, quiet=quiet, t0=t0)  # fmt: skip


def run_tasks(
    tasks: list[DatasetTask],
    skipped: list[dict[str, Any]],
    manifest: Manifest,
    digest: str,
    fn: Callable[..., dict[str, Any]],
    args: tuple,
    *,
    workers: int | None = None,
    ray: str | None = None,
    on_record: Callable[[dict[str, Any]], None] | None = None,
    quiet: bool = False,
    t0: float | None = None,
) -> DatasetSummary:
    """Run ``fn(task, *args)`` for every task (in this process, a pool of ``workers``
    processes, or Ray), recording each outcome in the manifest as it ends."""
    from tqdm import tqdm

    t0 = time.perf_counter() if t0 is None else t0
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: must be at least 1")
    n = min(workers or default_workers(), max(len(tasks), 1))
    summary = DatasetSummary(skipped=skipped, manifest=manifest.path)
    bar = tqdm(total=len(tasks), unit="clip", disable=quiet or not tasks, desc="clips")
    frames = 0

    def record(task: DatasetTask, result: dict[str, Any]) -> None:
        nonlocal frames
        rec = {"key": task.key, "input": str(task.source), "size": task.size,
               "sha256": task.sha256, "settings": digest, "motion": str(task.motion_path),
               "report": str(task.report_path), **result,
               "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}  # fmt: skip
        manifest.append(rec)
        (summary.done if rec["status"] == "done" else summary.failed).append(rec)
        frames += int((rec.get("headline") or {}).get("frames") or 0)
        bar.update(1)
        bar.set_postfix(failed=len(summary.failed),
                        fps=f"{frames / max(time.perf_counter() - t0, 1e-9):.0f}")  # fmt: skip
        if on_record is not None:
            on_record(rec)

    try:
        if ray is not None:
            _run_ray(tasks, fn, args, ray, workers, record)
        elif n == 1:
            for task in tasks:
                record(task, fn(task, *args))
        else:
            _run_pool(tasks, fn, args, n, record)
    finally:
        bar.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def _run_pool(
    tasks: list[DatasetTask],
    fn: Callable[..., dict[str, Any]],
    args: tuple,
    workers: int,
    record: Callable[[DatasetTask, dict[str, Any]], None],
) -> None:
    """The tasks on a pool of processes, one BLAS thread each (the cores go to the clips).

    Forked where the platform can (Linux): the workers start with the retargeting code
    imported here once, not each importing it anew (spawned workers took 2-3 s each to start,
    a fifth of a 50-clip run); this process holds no model, no thread of its own and no open
    output when it forks. Spawned elsewhere."""
    threads = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                              "MKL_NUM_THREADS")}  # fmt: skip
    os.environ.update({k: "1" for k in threads})
    methods = multiprocessing.get_all_start_methods()
    method = "fork" if "fork" in methods else "spawn"
    if method == "fork":
        import humimic.retarget  # noqa: F401 - imported once, before the workers fork

    try:
        pool = ProcessPoolExecutor(max_workers=workers,
                                   mp_context=multiprocessing.get_context(method))  # fmt: skip
    finally:
        for k, v in threads.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    pending: dict[Future[dict], DatasetTask] = {}
    queue = list(tasks)
    try:
        while queue or pending:
            while queue and len(pending) < 2 * workers:
                task = queue.pop(0)
                pending[pool.submit(fn, task, *args)] = task
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                task = pending.pop(fut)
                try:
                    result = fut.result()
                except Exception as e:  # The worker died (killed, out of memory).
                    result = {"status": "failed", "error_kind": "internal",
                              "error": f"worker process died: {type(e).__name__}: {e}"}  # fmt: skip
                record(task, result)
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


RAY_PIN = "ray==2.60.0"
"""The Ray this runner is tested with (the ``ray`` extra)."""


def _import_ray() -> Any:
    import importlib

    try:
        return importlib.import_module("ray")
    except ImportError:
        raise InputError(
            f"--ray: the ray package is not installed: pip install {RAY_PIN} "
            "(or the extra: pip install 'humimic[ray]')"
        ) from None


def _run_ray(
    tasks: list[DatasetTask],
    fn: Callable[..., dict[str, Any]],
    args: tuple,
    address: str,
    workers: int | None,
    record: Callable[[DatasetTask, dict[str, Any]], None],
) -> None:
    """The tasks as Ray tasks of one CPU each; results recorded here as they arrive."""
    ray = _import_ray()
    if not ray.is_initialized():
        try:
            if address == "local":
                ray.init(num_cpus=workers or default_workers(), include_dashboard=False,
                         log_to_driver=False)  # fmt: skip
            else:
                ray.init(address=address, log_to_driver=False)
        except Exception as e:  # Ray's connection errors are many (ConnectionError, RuntimeError).
            detail = " ".join(str(e).split())[:300] or type(e).__name__
            raise InputError(f"--ray {address}: cannot connect ({detail})") from None
    remote = ray.remote(num_cpus=1, max_retries=0)(fn)
    pending = {remote.remote(t, *args): t for t in tasks}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                task = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as e:  # The task's worker died, or the node left.
                    result = {"status": "failed", "error_kind": "internal",
                              "error": f"Ray task failed: {type(e).__name__}: {e}"[:500]}  # fmt: skip
                record(task, result)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise


def summary_lines(s: DatasetSummary, headline: tuple[str, ...] = HEADLINE,
                  worst: tuple[str, ...] = WORST, done: str = "clips retargeted") -> list[str]:  # fmt: skip
    """The end-of-run summary: counts, failures with their reasons, the quality distribution
    over every finished clip (this run's and earlier ones'), the worst clips by each figure."""
    import numpy as np

    finished = [r for r in s.done + s.skipped if r.get("status") == "done"]
    earlier_failed = [r for r in s.skipped if r.get("status") == "failed"]
    lines = [
        f"{len(s.done)} {done}, {len(s.skipped)} unchanged since an earlier run "
        f"({len(earlier_failed)} of them refused then), {len(s.failed)} failed; "
        f"{s.seconds:.1f} s; manifest {s.manifest}"
    ]
    for r in s.failed + earlier_failed:
        lines.append(f"  failed: {r['input']}: {r.get('error', '?')}")
    if finished:
        lines.append(f"quality over {len(finished)} clips (median / 95th percentile / max):")
        for k in headline[1:]:
            v = np.array([float(x) for r in finished
                          if (x := (r.get("headline") or {}).get(k)) is not None])  # fmt: skip
            if v.size:
                lines.append(f"  {k}: {np.median(v):.3g} / {np.percentile(v, 95):.3g} / "
                             f"{v.max():.3g}")  # fmt: skip
        for k in worst:
            ranked = sorted((r for r in finished if (r.get("headline") or {}).get(k)),
                            key=lambda r: -float(r["headline"][k]))[:3]  # fmt: skip
            if ranked:
                names = ", ".join(f"{r['key']} ({float(r['headline'][k]):.3g})" for r in ranked)
                lines.append(f"  worst by {k}: {names}")
    return lines
