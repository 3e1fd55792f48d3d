"""``humimic train``: PPO on the tracking environment, with a run folder that survives crashes.

A run folder holds ``config.yaml`` (everything resolved: the settings, the task, the PPO dict),
``progress.csv`` (one row per iteration), ``checkpoints/model_<iterations done>.pt`` (written
atomically: a crash, even ``kill -9``, never leaves a half checkpoint that looks whole) and
``tensorboard/``. ``--resume`` continues from the newest checkpoint that loads; what was
learned before it is kept, what came after it is redone. Training that produces NaN stops with
a clear error and leaves the last good checkpoint.
"""

from __future__ import annotations

import copy
import csv
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import yaml

from humimic.configs.runs import TrainSettings
from humimic.errors import HumimicError, InputError
from humimic.io import atomic_write_text, check_writable
from humimic.motion import Motion, load_motion, motion_from_qpos
from humimic.tracking import distributed
from humimic.tracking.config import (
    DR_PROFILES,
    DomainRandomization,
    TrackingConfig,
    load_dr_profile,
    tracking_task,
)
from humimic.tracking.distributed import Ranks, agree, parameter_spread
from humimic.tracking.rsl import PpoConfig, make_runner, tracking_ppo, train_cfg

if TYPE_CHECKING:
    from humimic.tracking.env import TrackingEnv


class TrainingDiverged(HumimicError):
    """Training produced NaN or infinite values."""


class _TimeUp(Exception):
    """The run's wall-time budget is spent (a checkpoint has been written)."""


_MUST_MATCH_ON_RESUME = (
    "motion",
    "robot",
    "num_envs",
    "dr",
    "physics",
    "variant",
    "seed",
    "num_steps_per_env",
)


def resolve_dr(dr: str) -> DomainRandomization:
    """A DR profile by name, or from a YAML file."""
    if dr in DR_PROFILES:
        return DR_PROFILES[dr]()
    path = Path(dr)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(
            f"--dr {dr!r}: choose a profile ({', '.join(DR_PROFILES)}) or a .yaml file"
        )
    return load_dr_profile(path)


def task_config(robot: str, dr: str, seed: int, physics: str | None = None) -> TrackingConfig:
    """The registered tracking task of a robot (:func:`tracking_task`) with a DR profile and,
    if given, a physics file (or a shipped one's name)."""
    from humimic.tracking.physics import load_physics

    task = replace(tracking_task(robot, resolve_dr(dr)), seed=seed)
    return task if physics is None else replace(task, physics=load_physics(physics))


def _slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-6
    s = np.sin(np.where(small, 1.0, theta))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / s)
    w1 = np.where(small, u, np.sin(u * theta) / s)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def load_reference(path: Path, robot: str, fps: float) -> Motion:
    """The motion file at the policy rate (resampled by interpolating ``qpos`` if needed)."""
    from humimic.robots import get_robot, nominal_model

    motion = load_motion(path)
    if motion.robot != robot:
        raise InputError(f"{path}: the motion is for robot {motion.robot!r}, not {robot!r}")
    if abs(motion.fps - fps) < 1e-6:
        return motion
    T = motion.num_frames
    duration = (T - 1) / motion.fps
    n = max(2, math.floor(duration * fps + 1e-9) + 1)
    x = np.arange(n) / fps * motion.fps
    i0 = np.clip(np.floor(x).astype(int), 0, T - 2)
    u = (x - i0)[:, None]
    q0, q1 = motion.qpos[i0], motion.qpos[i0 + 1]
    qpos = (1 - u) * q0 + u * q1
    qpos[:, 3:7] = _slerp(q0[:, 3:7], q1[:, 3:7], u)
    model = nominal_model(get_robot(robot))
    info = dict(motion.info or {})
    info["resampled_from_fps"] = motion.fps
    return motion_from_qpos(model, qpos, fps, robot, info=info)


def _plain(value: Any) -> Any:
    """A config as YAML-able data (functions by their import path)."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if callable(value):
        return f"{value.__module__}:{getattr(value, '__qualname__', repr(value))}"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _checkpoints(run: Path) -> list[Path]:
    folder = run / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(folder.glob("model_*.pt"), key=lambda p: int(p.stem.split("_")[1]))


def latest_checkpoint(run: Path) -> tuple[Path, dict] | None:
    """The newest checkpoint of a run that loads (a damaged one is skipped, and said so)."""
    for path in reversed(_checkpoints(run)):
        try:
            return path, torch.load(path, weights_only=True, map_location="cpu")
        except Exception as e:
            print(f"humimic: skipping unreadable checkpoint {path}: {e}")
    return None


def resolve_checkpoint(run: Path, checkpoint: Path | None) -> tuple[Path, dict]:
    """The given checkpoint file, or the run's newest that loads."""
    if checkpoint is not None:
        if not checkpoint.is_file():
            raise InputError(f"--checkpoint {checkpoint}: no such file")
        return checkpoint, torch.load(checkpoint, weights_only=True, map_location="cpu")
    found = latest_checkpoint(run)
    if found is None:
        raise InputError(f"{run}: the run has no checkpoint yet")
    return found


@dataclass
class _Progress:
    """Called by the runner after every iteration: logs, checks, checkpoints."""

    runner: Any
    run: Path
    every: int
    total: int
    bar: Any
    started: float
    num_envs: int
    steps_per_env: int
    max_seconds: float | None = None
    ranks: Ranks = field(default_factory=Ranks)
    last: dict[str, float] | None = None

    def __call__(self, *, it: int, loss_dict: dict, learning_rate: float, action_std: torch.Tensor,
                 collect_time: float, learn_time: float, **_: Any) -> None:  # fmt: skip
        lg, ranks = self.runner.logger, self.ranks
        done = it + 1
        batch = self.num_envs * self.steps_per_env * ranks.world_size  # Over all ranks.
        row: dict[str, float] = {
            "iteration": done,
            "env_steps": done * batch,
            "seconds": time.perf_counter() - self.started,
            "steps_per_second": batch / max(collect_time + learn_time, 1e-9),
            "mean_reward": float(np.mean(lg.rewbuffer)) if len(lg.rewbuffer) else math.nan,
            "mean_episode_length": float(np.mean(lg.lenbuffer)) if len(lg.lenbuffer) else math.nan,
            "learning_rate": float(learning_rate),
            "action_std": float(action_std.detach().mean()),
            **{f"loss_{k}": float(v) for k, v in loss_dict.items()},
        }
        keys = dict.fromkeys(k for ep in lg.ep_extras for k in ep)
        for key in keys:
            vals = [torch.as_tensor(ep[key], dtype=torch.float32).flatten()
                    for ep in lg.ep_extras if key in ep]  # fmt: skip
            row[key] = float(torch.cat(vals).mean()) if vals else math.nan
        lg.ep_extras.clear()
        bad = [k for k, v in row.items() if k.startswith(("loss_", "action_std")) and
               not math.isfinite(v)]  # fmt: skip
        params = list(self.runner.alg.get_policy().parameters())
        finite = all(bool(torch.isfinite(p).all()) for p in params)
        diverged = bool(bad) or not finite
        time_up = self.max_seconds is not None and row["seconds"] > self.max_seconds
        if ranks.distributed:  # Every rank stops, or none: rank 0's clock decides time-ups.
            row["rank_param_spread"] = parameter_spread(params)
            flags = agree([int(diverged), int(time_up and ranks.main)], self.runner.device)
            diverged, time_up = bool(flags[0]), bool(flags[1])
        if diverged:
            what = ", ".join(bad) or (
                "policy parameters" if not finite else "values on another rank"
            )
            last = _checkpoints(self.run)
            raise TrainingDiverged(
                f"training diverged at iteration {done}: non-finite {what}; the last good "
                f"checkpoint is {last[-1] if last else 'none'}"
            )
        if row.get("rank_param_spread", 0.0) != 0.0:
            raise HumimicError(
                f"iteration {done}: the ranks' policies differ by up to "
                f"{row['rank_param_spread']:.3g}; data-parallel training must keep them equal"
            )
        self.last = row
        if not ranks.main:  # Rank 0 alone writes the run folder and shows progress.
            if time_up:
                raise _TimeUp
            return
        if lg.writer is not None:
            for k, v in row.items():
                if k != "iteration":
                    lg.writer.add_scalar(f"humimic/{k}", v, done)
        csv_path = self.run / "progress.csv"
        new = not csv_path.exists()
        with open(csv_path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(row), extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(row)
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(reward=f"{row['mean_reward']:.3g}",
                                 ep_len=f"{row['mean_episode_length']:.0f}",
                                 sps=f"{row['steps_per_second']:.0f}")  # fmt: skip
        if done % self.every == 0 or done == self.total or time_up:
            path = self.run / "checkpoints" / f"model_{done:06d}.pt"
            self.runner.save_checkpoint(path, done)
        if time_up:
            raise _TimeUp


def _write_config(run: Path, settings: TrainSettings, task: TrackingConfig, ppo: dict) -> None:
    blob = {"settings": _plain(asdict(settings)), "tracking": _plain(task), "ppo": _plain(ppo)}
    atomic_write_text(run / "config.yaml", yaml.safe_dump(blob, sort_keys=False))


def _run_config(run: Path) -> tuple[dict[str, Any], TrainSettings]:
    """A run's config.yaml and the training settings in it (a student's: its teacher's)."""
    path = run / "config.yaml"
    if not path.is_file():
        raise InputError(f"{run}: not a humimic run folder (no config.yaml)")
    try:
        config = yaml.safe_load(path.read_text())
        data = dict(config["settings"])
        data["motion"], data["out"] = Path(data["motion"]), Path(data["out"])
        if data.get("init_from") is not None:
            data["init_from"] = Path(data["init_from"])
        return config, TrainSettings(**data)
    except (yaml.YAMLError, KeyError, TypeError) as e:
        raise InputError(f"{path}: not a humimic run configuration ({e})") from None


def read_run_settings(run: Path) -> TrainSettings:
    """The settings a run was started with."""
    return _run_config(run)[1]


def run_rsl_cfg(run: Path) -> dict[str, Any]:
    """The rsl_rl ``train_cfg`` of a run: a PPO run's from its settings, a student's
    (``humimic distill``) as stored in its config.yaml."""
    config, settings = _run_config(run)
    if config.get("kind") != "student":
        return train_cfg(ppo_for(settings))
    if "rsl" not in config:
        raise InputError(f"{run}/config.yaml: a student run without its 'rsl' section")
    return copy.deepcopy(config["rsl"])


def ppo_for(settings: TrainSettings) -> PpoConfig:
    """The PPO configuration of a run."""
    ppo = tracking_ppo(settings.variant)
    if settings.num_steps_per_env is not None:
        ppo = replace(ppo, num_steps_per_env=settings.num_steps_per_env)
    return ppo


def train(settings: TrainSettings, ppo: PpoConfig | None = None) -> dict:
    """Train (or resume) a tracking policy. Returns the last progress row.

    Under torchrun (``WORLD_SIZE`` > 1) every process trains data-parallel with the others
    (:mod:`humimic.tracking.distributed`); ``--num-envs`` is each process's.
    """
    s = settings
    run = s.out
    ranks = Ranks.from_env()
    has_run = check_run_settings(s)
    if s.resume:
        old = read_run_settings(run)
        diff = [n for n in _MUST_MATCH_ON_RESUME if getattr(old, n) != getattr(s, n)]
        if diff:
            raise InputError(
                f"--resume: {', '.join(diff)} differ from the run's ({', '.join(f'{n}={getattr(old, n)!r}' for n in diff)})"
            )
    if not s.motion.is_file():
        raise InputError(f"--motion {s.motion}: no such file")
    seed = s.seed + ranks.rank  # Each rank collects its own experience.
    task = replace(
        task_config(s.robot, s.dr, seed, s.physics), torch_compile=s.compile, backend=s.backend
    )
    motion = load_reference(s.motion, s.robot, 1.0 / task.step_dt)
    cfg = train_cfg(ppo or ppo_for(s))
    init = None
    if s.init_from is not None and not has_run:
        if not s.init_from.exists():
            raise InputError(f"--init-from {s.init_from}: no such run or checkpoint")
        file = s.init_from if s.init_from.is_file() else None
        init = resolve_checkpoint(s.init_from, file)
    device = s.device
    if ranks.distributed:
        device = distributed.start(ranks, s.device)
        agree([0], device)  # Every rank has checked the run folder before rank 0 writes it.
    created = not run.exists() and ranks.main
    try:
        if ranks.main:
            check_writable(run / "config.yaml")
        torch.manual_seed(seed)
        env = run_env(task, motion, s, created, device=device)
        try:
            log_dir = run / "tensorboard" if ranks.main else None
            runner = make_runner(env, cfg, log_dir=log_dir, device=device, ranks=ranks)
            if init is not None:
                try:
                    runner.load_checkpoint(init[1])
                except (RuntimeError, KeyError) as e:
                    if created:  # Leave nothing behind for a run that never started.
                        shutil.rmtree(run, ignore_errors=True)
                    raise InputError(
                        f"--init-from {init[0]}: its networks do not fit this run's (variant "
                        f"{s.variant!r}, task of {s.robot!r}): {str(e).splitlines()[0]}"
                    ) from None
                runner.current_learning_iteration = 0
            if ranks.main:
                (run / "checkpoints").mkdir(parents=True, exist_ok=True)
                if not has_run:
                    _write_config(run, s, task, cfg)
            steps = int(cfg["num_steps_per_env"])
            return fit(runner, run, s, steps_per_env=steps, ranks=ranks)
        finally:
            env.close()
    finally:
        distributed.stop()


def run_env(
    task: TrackingConfig, motion: Motion, s: Any, created: bool, device: str | None = None
) -> TrackingEnv:
    """The env of a run command (``s``: its settings; on ``device``, default ``s.device``); if
    it cannot be built (a bad task, a failing ``--compile``), the run folder this command
    ``created`` is removed again."""
    from humimic.tracking.env import TrackingEnv

    try:
        return TrackingEnv(task, motion, s.num_envs, device=device or s.device)
    except BaseException:
        if created:
            shutil.rmtree(s.out, ignore_errors=True)
        raise


def check_run_settings(s: Any) -> bool:
    """Check the settings every run command shares (``TrainSettings``, ``DistillSettings``);
    returns whether ``s.out`` holds a run already (allowed only with ``s.resume``)."""
    for name in ("num_envs", "max_iterations", "checkpoint_every"):
        if getattr(s, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} {getattr(s, name)}: must be at least 1")
    if s.max_minutes is not None and not s.max_minutes > 0:
        raise InputError(f"--max-minutes {s.max_minutes}: must be positive")
    if s.device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"--device {s.device}: CUDA is not available on this machine")
    if s.out.exists() and not s.out.is_dir():
        raise InputError(f"--out {s.out}: exists and is not a folder")
    has_run = (s.out / "config.yaml").exists()
    if has_run and not s.resume:
        raise InputError(f"--out {s.out}: holds a run already; pass --resume to continue it")
    return has_run


def fit(runner: Any, run: Path, s: Any, *, steps_per_env: int, ranks: Ranks | None = None) -> dict:
    """Run a runner's learning loop for a run folder: resume from its newest checkpoint if
    ``s.resume``, progress bar, CSV, checks, periodic atomic checkpoints, time budget.

    Args:
        runner: From :func:`~humimic.tracking.rsl.make_runner`, its initial weights loaded.
        run: The run folder.
        s: Settings with ``resume``, ``max_iterations``, ``checkpoint_every``, ``quiet``,
            ``num_envs`` and ``max_minutes`` (:class:`TrainSettings`, ``DistillSettings``).
        steps_per_env: Rollout length per iteration.
        ranks: This process's place in a data-parallel run (default: a single process).

    Returns:
        The last progress row.
    """
    start = 0
    if s.resume:
        found = latest_checkpoint(run)
        if found is not None:
            path, blob = found
            runner.load_checkpoint(blob)
            start = int(blob["iter"])
            print(f"resuming {run} from {path.name} ({start} iterations done)")
    if start >= s.max_iterations:
        print(f"{run}: {start} iterations done already (--max-iterations {s.max_iterations})")
        return {"iteration": start}
    ranks = ranks or Ranks()
    bar = None
    if not s.quiet and ranks.main:
        from tqdm import tqdm

        bar = tqdm(total=s.max_iterations, initial=start, unit="it", desc=run.name or "train")
    progress = _Progress(runner=runner, run=run, every=s.checkpoint_every,
                         total=s.max_iterations, bar=bar, started=time.perf_counter(),
                         num_envs=s.num_envs, steps_per_env=steps_per_env,
                         max_seconds=None if s.max_minutes is None else 60 * s.max_minutes,
                         ranks=ranks)  # fmt: skip
    runner.logger.log = progress  # Our progress row, bar, checks and checkpoints.
    try:
        runner.learn(s.max_iterations - start, init_at_random_ep_len=start == 0)
    except _TimeUp:
        if ranks.main:
            print(f"{run}: --max-minutes {s.max_minutes} reached; resume to continue")
    except ValueError as e:  # rsl_rl's NaN check on observations and rewards.
        if "NaN" in str(e):
            raise TrainingDiverged(f"training diverged: {e}") from None
        raise
    finally:
        if bar is not None:
            bar.close()
    return progress.last or {}


__all__ = [
    "TrainSettings",
    "TrainingDiverged",
    "check_run_settings",
    "fit",
    "latest_checkpoint",
    "load_reference",
    "read_run_settings",
    "resolve_dr",
    "run_rsl_cfg",
    "task_config",
    "train",
]
