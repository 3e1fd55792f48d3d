"""Run folders: what ``humimic train`` writes and every later command reads.

A run folder holds ``config.yaml`` (everything resolved: the settings, the task, the PPO dict),
``progress.csv`` (one row per iteration), ``checkpoints/model_<iterations done>.pt`` and
``tensorboard/``; this module reads and writes them.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import fcntl
import hashlib
import io
import math
import os
import re
import sys
from collections.abc import Iterator
from dataclasses import asdict, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

import torch
import yaml

from humimic.configs.runs import PpoConfig, TaskSettings, TrainSettings
from humimic.errors import InputError, first_line
from humimic.io import atomic_write_text
from humimic.sim.randomization import DR_PROFILES
from humimic.tracking.config import TrackingConfig
from humimic.tracking.rsl import tracking_ppo, train_cfg

RUN_SCHEMA = 2
"""The layout version of a run folder's ``config.yaml`` (its ``schema`` key): 2 records every
task field; 1 (no ``schema`` key: run folders from before 2026-12-07) may lack fields added
since, which :func:`upgrade_run_config` fills as those runs trained."""

REFERENCE_FILE = "reference.npz"
"""The refined reference a run writes into its folder when it refined its motion itself
(:mod:`humimic.pipeline.reference`)."""
REFERENCE_LIBRARY = "reference"
"""The folder of a library run's refined clips, when it refined them itself."""
LIBRARY_LIST = "library.yaml"
"""The library such a run trains on, in :data:`REFERENCE_LIBRARY`: its refined clips and
the clips that were refined already."""


def yaml_ready(value: Any) -> Any:
    """A config as YAML-able data (functions by their import path)."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: yaml_ready(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, dict):
        return {str(k): yaml_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [yaml_ready(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if callable(value):
        return f"{value.__module__}:{getattr(value, '__qualname__', repr(value))}"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


@contextlib.contextmanager
def run_folder_lock(run: Path, has_run: bool, flag: str = "--out") -> Iterator[None]:
    """Hold an existing run folder for writing while the block runs: a second ``train`` or
    ``distill`` on it is refused while this one lives. The lock is the kernel's (``flock`` on
    the folder itself), so it leaves no file behind and ends with the process however it
    ends (``kill -9`` too): a killed run's folder is never locked out.

    Args:
        run: The run folder (it exists).
        has_run: Whether it held a run (``config.yaml``) when the settings were checked: a
            run that another process started meanwhile is refused too.
        flag: What messages name.

    Raises:
        InputError: Another process holds the folder, or wrote a run there meanwhile.
    """
    fd = os.open(run, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(
                f"{flag} {run}: another humimic process is writing this run folder; wait for "
                "it to end, or choose another folder"
            ) from None
        except OSError as e:  # A file system without locks (some network mounts).
            print(f"humimic: warning: {run}: cannot lock the run folder ({e.strerror or e}); "
                  "nothing stops a second run from writing into it", file=sys.stderr)  # fmt: skip
        if (run / "config.yaml").exists() and not has_run:
            raise InputError(
                f"{flag} {run}: another run was started in this folder meanwhile; choose "
                "another folder"
            )
        yield
    finally:
        os.close(fd)


def checkpoint_files(run: Path) -> list[Path]:
    """The run's ``checkpoints/model_<iterations done>.pt`` entries, oldest first (any kind of
    entry: :func:`read_checkpoint` refuses one that is not a regular file)."""
    folder = run / "checkpoints"
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.glob("model_*.pt")
             if (m := re.fullmatch(r"model_(\d+)\.pt", p.name))]  # fmt: skip
    return [p for _, p in sorted(found)]


def read_checkpoint(path: Path, flag: str = "--checkpoint") -> dict:
    """The contents of a checkpoint file (``torch.load(weights_only=True)``).

    Raises:
        InputError: The file is missing, damaged (truncated, random bytes, text) or holds
            something else than a humimic checkpoint; names ``flag`` and the file.
    """
    if not path.exists():
        raise InputError(f"{flag} {path}: no such file")
    if not path.is_file():
        what = "a folder" if path.is_dir() else "not a regular file"
        raise InputError(f"{flag} {path}: {what}, expected a checkpoint file")
    try:
        blob = torch.load(path, weights_only=True, map_location="cpu")
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot read: {e.strerror or e}") from None
    except Exception:  # torch raises many kinds for damaged files (pickle, zip, EOF, key).
        raise InputError(
            f"{flag} {path}: not a readable checkpoint (truncated, damaged, or not a file "
            "torch.save wrote)"
        ) from None
    it = blob.get("iter") if isinstance(blob, dict) else None
    if (
        not isinstance(it, int)
        or isinstance(it, bool)
        or not any(str(k).endswith("_state_dict") for k in blob)
    ):
        raise InputError(
            f"{flag} {path}: not a humimic checkpoint (expected 'iter' and the networks' "
            "state dicts)"
        )
    bad = _non_finite_tensor(blob)
    if bad is not None:
        raise InputError(
            f"{flag} {path}: {bad} holds NaN or infinite values (a training run that "
            "diverged): refusing to use it"
        )
    return blob


def _non_finite_tensor(blob: Any, where: str = "") -> str | None:
    """The first floating-point tensor of a checkpoint (state dicts nested in dicts and
    lists) with a NaN or an infinity, named by its keys; None when all are finite."""
    if isinstance(blob, torch.Tensor):
        if blob.is_floating_point() or blob.is_complex():
            return None if bool(torch.isfinite(blob).all()) else (where or "a tensor")
        return None
    if isinstance(blob, dict):
        items = blob.items()
    elif isinstance(blob, list | tuple):
        items = enumerate(blob)
    else:
        return None
    for key, value in items:
        found = _non_finite_tensor(value, f"{where}.{key}" if where else str(key))
        if found is not None:
            return found
    return None


def load_weights(runner: Any, blob: dict, path: Path, flag: str = "--checkpoint") -> None:
    """Load a checkpoint into a runner; one that does not fit its networks is an input error.

    Raises:
        InputError: Names ``flag`` and the file, with the first line of torch's reason.
    """
    try:
        runner.load_checkpoint(blob)
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(
            f"{flag} {path}: its networks do not fit this run's ({first_line(e)})"
        ) from None


def latest_checkpoint(run: Path, *, skip_damaged: bool = False) -> tuple[Path, dict] | None:
    """The newest checkpoint of a run (None: it has none yet).

    Args:
        run: The run folder.
        skip_damaged: Pass over newer files that do not load (damaged, NaN weights), each
            said on stderr, for the newest that does (``--resume`` after a crash). An entry
            that is not a regular file is refused all the same: no crash leaves one.

    Raises:
        InputError: The newest one does not load (or, with ``skip_damaged``, is not a
            regular file, or none loads): named, never passed over in silence.
    """
    files = checkpoint_files(run)
    for path in reversed(files):
        try:
            return path, read_checkpoint(path, "checkpoint")
        except InputError as e:
            if not skip_damaged or not path.is_file():
                raise InputError(
                    f"{e} (the run's newest; move it out of checkpoints/ to use the one before)"
                ) from None
            print(f"humimic: warning: skipping {e}", file=sys.stderr)
    if files:
        raise InputError(f"{run}: none of its {len(files)} checkpoints loads")
    return None


def resolve_checkpoint(
    run: Path, checkpoint: Path | None, flag: str = "--checkpoint"
) -> tuple[Path, dict]:
    """The given checkpoint file (``flag`` names it in errors), or the run's newest that
    loads."""
    if checkpoint is not None:
        return checkpoint, read_checkpoint(checkpoint, flag)
    found = latest_checkpoint(run)
    if found is None:
        raise InputError(f"{run}: the run has no readable checkpoint yet")
    return found


def run_files(run: Path) -> dict[str, Path]:
    """The files of a run folder that a command reads: what no output may overwrite (label ->
    path, for :func:`humimic.io.check_not_input`)."""
    files = {"the run's config.yaml": run / "config.yaml",
             "the run's progress.csv": run / "progress.csv"}  # fmt: skip
    if (run / REFERENCE_FILE).exists():
        files[f"the run's {REFERENCE_FILE}"] = run / REFERENCE_FILE
    lib = run / REFERENCE_LIBRARY
    if lib.is_dir():
        for path in [*sorted(lib.glob("*.npz")), lib / LIBRARY_LIST]:
            files[f"the run's {REFERENCE_LIBRARY}/{path.name}"] = path
    for path in checkpoint_files(run):
        files[f"the run's checkpoint {path.name}"] = path
    return files


def _physics_names() -> tuple[str, ...]:
    from humimic.sim.physics import SHIPPED

    return tuple(SHIPPED)


def resolved_source(value: str | None, names: Any) -> str | None:
    """A ``--dr`` or ``--physics`` value as a run records it: a name (one of ``names``) as is,
    a file path absolute."""
    if value is None or value in names:
        return value
    return str(Path(value).resolve())


def resolved_settings(s: TrainSettings) -> TrainSettings:
    """The settings with every file path absolute, PPO's as the run uses them
    (:func:`ppo_for`) and the action base resolved: what config.yaml records, so that ``eval``, ``export``, ``distill`` and
    ``--resume`` run from any folder find the files."""
    return replace(
        s,
        motion=s.motion.resolve(),
        out=s.out.resolve(),
        init_from=None if s.init_from is None else s.init_from.resolve(),
        dr=resolved_source(s.dr, DR_PROFILES) or s.dr,
        physics=resolved_source(s.physics, _physics_names()),
        ppo=ppo_for(s),
        task=_resolved_task(s.robot, s.task),
    )


def _resolved_task(robot: str, t: TaskSettings) -> TaskSettings:
    """The task settings with the action base, the feedback's root cost and delay and the
    DR replay share the run trains with (an unset flag: the robot's registered task's
    value), so that a later change of the defaults does not change what ``eval`` rebuilds
    or ``--resume`` continues."""
    from humimic.tracking.config import tracking_task

    task = tracking_task(robot, "none")
    return replace(
        t,
        action_base=t.action_base or task.action_base,
        feedback_root_cost=t.feedback_root_cost or task.feedback.base_position,
        feedback_delay=task.feedback_delay if t.feedback_delay is None else t.feedback_delay,
        dr_replay=task.adaptive.dr_replay if t.dr_replay is None else t.dr_replay,
    )


def settings_differences(old: Any, new: Any, names: tuple[str, ...], prefix: str = "") -> list[str]:
    """``name=old value`` for each named field that differs; a nested config's fields are
    compared one by one (``ppo.learning_rate=0.001``)."""
    out = []
    for name in names:
        a, b = getattr(old, name), getattr(new, name)
        if a == b:
            continue
        if is_dataclass(a) and is_dataclass(b):
            inner = tuple(f.name for f in fields(a))
            out += settings_differences(a, b, inner, f"{prefix}{name}.")
        else:
            out.append(f"{prefix}{name}={a!s}")
    return out


def upgrade_run_config(config: dict[str, Any], path: Path) -> dict[str, Any]:
    """``config`` (a run folder's config.yaml, read from ``path``) in the layout of
    :data:`RUN_SCHEMA`: the one place older run folders are read differently. Schema 1 (no
    ``schema`` key): a task recorded without a field added since trained as it was then
    (the default action base before action bases, the LQR root cost and anchor reward of
    before 2026-12-02, no command delay in the LQR design, no replay of failed DR draws).

    Raises:
        InputError: A schema newer than this humimic's, or not a schema number.
    """
    schema = config.get("schema", 1)
    if not isinstance(schema, int) or isinstance(schema, bool) or schema < 1:
        raise InputError(f"{path}: 'schema' must be a positive whole number, got {schema!r}")
    if schema > RUN_SCHEMA:
        raise InputError(
            f"{path}: written by a newer humimic (run folder schema {schema}; this one reads "
            f"up to {RUN_SCHEMA}): upgrade humimic"
        )
    if schema < 2 and isinstance(config.get("settings"), dict):
        config["settings"]["task"] = _task_v1(dict(config["settings"].get("task") or {}))
    config["schema"] = RUN_SCHEMA
    return config


def _task_v1(task: dict[str, Any]) -> dict[str, Any]:
    """A schema-1 task's fields as that run trained (see :func:`upgrade_run_config`)."""
    if task.get("action_base") is None:  # Recorded before action bases: the default pose.
        task["action_base"] = "default"
    if "feedback_root_cost" not in task:
        # Recorded before 2026-12-02: the LQR root cost and the anchor reward of then.
        task["feedback_root_cost"] = 10.0
        task["reward_stds"] = {"anchor_pos": 0.3, **(task.get("reward_stds") or {})}
        task["reward_weights"] = {"anchor_pos": 0.5, **(task.get("reward_weights") or {})}
    task.setdefault("feedback_delay", 0)  # Recorded before the delay-aware LQR: none.
    task.setdefault("dr_replay", 0.0)  # Recorded before the replay of failed draws: none.
    return task


def _settings_from(data: dict[str, Any]) -> TrainSettings:
    """Training settings from config.yaml's ``settings`` (upgraded, :func:`upgrade_run_config`):
    the nested configs from their mappings, PPO's resolved as :func:`resolved_settings`
    records it."""
    data["task"] = TaskSettings(**(data.get("task") or {}))
    if data.get("ppo") is not None:
        ppo = dict(data["ppo"])
        for key in ("actor_hidden_dims", "critic_hidden_dims", "rma_encoder_hidden_dims",
                    "encoder_groups"):  # fmt: skip
            if key in ppo:
                ppo[key] = tuple(ppo[key])
        if "obs_groups" in ppo:
            ppo["obs_groups"] = {k: tuple(v) for k, v in ppo["obs_groups"].items()}
        data["ppo"] = PpoConfig(**ppo)
    settings = TrainSettings(**data)
    return replace(settings, ppo=ppo_for(settings))


def write_run_config(run: Path, settings: TrainSettings, task: TrackingConfig, ppo: dict) -> None:
    """config.yaml: the resolved settings, task and PPO dict. A motion inside the run folder
    (its refined reference) is recorded relative to it, so that a copied or moved run reads
    its own; every motion's SHA-256 is recorded, so that one changed since is found
    (:func:`recorded_motion`)."""
    s = resolved_settings(settings)
    data = yaml_ready(asdict(s))
    blob: dict[str, Any] = {"schema": RUN_SCHEMA, "settings": data}
    if s.motion.is_relative_to(run.resolve()):
        data["motion"] = s.motion.relative_to(run.resolve()).as_posix()
        blob["motion_in_run"] = True
    if s.motion.exists():
        blob["motion_sha256"] = motion_sha256(s.motion)
    blob |= {"tracking": yaml_ready(task), "ppo": yaml_ready(ppo)}
    atomic_write_text(run / "config.yaml", yaml.safe_dump(blob, sort_keys=False))


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def motion_sha256(path: Path) -> str:
    """The SHA-256 of a motion file's bytes; for a library (a folder or a ``.yaml`` list,
    :func:`~humimic.tracking.task.library_entries`), of its clips' names, SHA-256s and weights
    other than 1, in order."""
    from humimic.tracking.task import is_library, library_entries

    if not is_library(path):
        return file_sha256(path)
    h = hashlib.sha256()
    for f, w in library_entries(path):
        h.update(f"{f.name}\n{file_sha256(f)}\n".encode())
        if w != 1.0:  # A library without weights hashes as before weights existed.
            h.update(f"weight {w!r}\n".encode())
    return h.hexdigest()


def recorded_motion(
    run: Path,
    recorded: tuple[dict[str, Any], TrainSettings] | None = None,
    hint: str = "pass --motion to use a motion as it is now",
) -> Path:
    """The motion a run trained on, checked: there, and (where config.yaml holds its SHA-256)
    unchanged since the run recorded it.

    Args:
        run: The run folder.
        recorded: What :func:`run_config` already read of it (default: read it).
        hint: What the message advises when the motion changed.

    Raises:
        InputError: Missing, or changed (names the run and the file).
    """
    config, settings = recorded or run_config(run)
    p = settings.motion
    if not p.exists():
        raise InputError(f"{run}: the run's motion {p} is missing (moved? pass --motion)")
    want = config.get("motion_sha256")
    try:
        changed = want is not None and motion_sha256(p) != want
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror or e}") from None
    if changed:
        raise InputError(
            f"{run}: the run's motion {p} has changed since the run recorded it (its SHA-256 "
            f"differs from config.yaml's); {hint}"
        )
    return p


def _started_in(run: Path, recorded_out: Path) -> Path | None:
    """The folder a run was started from, when its config recorded ``--out`` relative (older
    run folders): the run folder's path less the recorded one's parts, if they end it."""
    parts = Path(os.path.normpath(recorded_out)).parts
    if recorded_out.is_absolute() or ".." in parts:
        return None
    here = run.resolve().parts
    if parts and here[-len(parts) :] != parts:
        return None
    return Path(*here[: len(here) - len(parts)])


def _absolute(path: str, start: Path | None) -> Path:
    """A recorded path made absolute: as recorded, or (relative, from an older run folder)
    from the folder the run was started in if the file is there, else from this folder."""
    p = Path(path)
    if p.is_absolute():
        return p
    candidates = ([start / p] if start is not None else []) + [p.resolve()]
    return next((c.resolve() for c in candidates if c.exists()), candidates[0].resolve())


def run_config(run: Path) -> tuple[dict[str, Any], TrainSettings]:
    """A run's config.yaml and the training settings in it (a student's: its teacher's), with
    the file paths absolute (:func:`resolved_settings`; relative ones of older run folders are
    found where the run was started, see :func:`_absolute`)."""
    path = run / "config.yaml"
    if not path.is_file():
        raise InputError(f"{run}: not a humimic run folder (no config.yaml)")
    try:
        config = upgrade_run_config(yaml.safe_load(path.read_text()), path)
        data = dict(config["settings"])
        start = _started_in(run, Path(data["out"]))
        data["out"] = Path(data["out"])
        if config.get("motion_in_run"):  # The run's own reference, wherever the run is now.
            data["motion"] = (run / data["motion"]).resolve()
        else:
            data["motion"] = _absolute(data["motion"], start)
        if data.get("init_from") is not None:
            data["init_from"] = _absolute(data["init_from"], start)
        for key, names in (("dr", DR_PROFILES), ("physics", _physics_names())):
            if data.get(key) is not None and data[key] not in names:
                data[key] = str(_absolute(data[key], start))
        return config, _settings_from(data)
    except (
        yaml.YAMLError,
        KeyError,
        TypeError,
        ValueError,
        OSError,
        UnicodeDecodeError,
        AttributeError,
    ) as e:  # AttributeError: a mapping cut to a string (fuzz seed 36).
        raise InputError(f"{path}: not a humimic run configuration ({first_line(e)})") from None


def read_run_settings(run: Path) -> TrainSettings:
    """The settings a run was started with."""
    return run_config(run)[1]


def run_rsl_cfg(
    run: Path, recorded: tuple[dict[str, Any], TrainSettings] | None = None
) -> dict[str, Any]:
    """The rsl_rl ``train_cfg`` of a run: a PPO run's from its settings, a student's
    (``humimic distill``) as stored in its config.yaml (``recorded``: what
    :func:`run_config` already read of it)."""
    config, settings = recorded or run_config(run)
    if config.get("kind") != "student":
        return train_cfg(ppo_for(settings))
    if "rsl" not in config:
        raise InputError(f"{run}/config.yaml: a student run without its 'rsl' section")
    return copy.deepcopy(config["rsl"])


def ppo_for(settings: TrainSettings) -> PpoConfig:
    """The PPO configuration of a run: its ``--ppo.*`` settings, its variant's observation
    groups, its ``--num-steps-per-env``."""
    ppo = tracking_ppo(settings.variant, settings.ppo)
    if settings.num_steps_per_env is not None:
        ppo = replace(ppo, num_steps_per_env=settings.num_steps_per_env)
    return ppo


def trim_progress(path: Path, done: int) -> tuple[float, list[str] | None]:
    """Make a resumed run's progress.csv end at the checkpoint it resumes from.

    Rows past iteration ``done`` (written after the checkpoint, before a crash) are redone, so
    they are dropped, as is a last row cut short by ``kill -9`` (no line end). The file is
    rewritten atomically, or removed when no row is left.

    Returns:
        The kept last row's ``seconds`` (the column goes on from it; 0 without one) and the
        file's columns (None when there is no file left).
    """
    if not path.is_file():
        return 0.0, None
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the run's progress ({first_line(e)})") from None
    lines = text.splitlines(keepends=True)
    cut = bool(lines) and not lines[-1].endswith("\n")
    if cut:
        lines.pop()  # A row cut short.
    rows = list(csv.reader(lines))
    if not rows:  # Empty, or a header cut short: nothing to keep.
        path.unlink()
        return 0.0, None
    if rows[0][:1] != ["iteration"]:
        raise InputError(
            f"{path}: not a progress file (its header does not start with 'iteration'); "
            "move it away to resume"
        )
    header = rows[0]

    def iteration(r: list[str]) -> int | None:
        try:
            return int(r[0]) if len(r) == len(header) else None
        except ValueError:
            return None

    kept = [r for r in rows[1:] if (i := iteration(r)) is not None and i <= done]
    if not kept:
        path.unlink()
        return 0.0, None
    if cut or len(kept) != len(rows) - 1 or len(lines) != len(rows):
        out = io.StringIO()
        csv.writer(out, lineterminator="\n").writerows([header, *kept])
        atomic_write_text(path, out.getvalue())
    seconds = 0.0
    if "seconds" in header:
        try:
            seconds = float(kept[-1][header.index("seconds")])
        except ValueError:
            seconds = 0.0
        seconds = seconds if math.isfinite(seconds) else 0.0
    return seconds, header
