"""``humimic train``: PPO on the tracking environment, in a run folder (:mod:`.runs`).

Checkpoints are written atomically, ``--resume`` continues from the newest one that loads, and
training that produces NaN stops with a clear error and leaves the last good checkpoint.
"""

from __future__ import annotations

import contextlib
import csv
import math
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import yaml

from humimic.configs.runs import TIMED_ITERATIONS, PpoConfig, TrainSettings
from humimic.errors import HumimicError, InputError, first_line
from humimic.io import check_not_input, check_writable
from humimic.motion import Motion
from humimic.sim.randomization import DR_PROFILES
from humimic.tracking import distributed
from humimic.tracking.config import TrackingConfig
from humimic.tracking.distributed import Ranks, agree, parameter_spread
from humimic.tracking.rsl import make_runner, scale_actor_output, train_cfg
from humimic.tracking.runs import (
    REFERENCE_FILE,
    REFERENCE_LIBRARY,
    checkpoint_files,
    latest_checkpoint,
    load_weights,
    ppo_for,
    read_checkpoint,
    read_run_settings,
    recorded_motion,
    resolve_checkpoint,
    resolved_settings,
    run_config,
    run_files,
    run_folder_lock,
    run_rsl_cfg,
    settings_differences,
    trim_progress,
    write_run_config,
)
from humimic.tracking.task import load_reference, load_references, task_config

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
    "task",
    "ppo",
)


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
    seconds_before: float = 0.0
    """Training seconds of the run before this process (a resumed run's ``seconds`` go on)."""
    columns: list[str] | None = None
    """progress.csv's header (None: the file is new; its header is the first row's keys)."""

    def __call__(self, *, it: int, loss_dict: dict, learning_rate: float, action_std: torch.Tensor,
                 collect_time: float, learn_time: float, **_: Any) -> None:  # fmt: skip
        ranks = self.ranks
        done = it + 1
        elapsed = time.perf_counter() - self.started  # This process's: --max-minutes.
        row = self._row(done, elapsed, loss_dict, learning_rate, action_std,
                        collect_time + learn_time)  # fmt: skip
        bad = [k for k, v in row.items() if k.startswith(("loss_", "action_std")) and
               not math.isfinite(v)]  # fmt: skip
        params = list(self.runner.alg.get_policy().parameters())
        finite = all(bool(torch.isfinite(p).all()) for p in params)
        diverged = bool(bad) or not finite
        time_up = self.max_seconds is not None and elapsed > self.max_seconds
        if ranks.distributed:  # Every rank stops, or none: rank 0's clock decides time-ups.
            row["rank_param_spread"] = parameter_spread(params)
            flags = agree([int(diverged), int(time_up and ranks.main)], self.runner.device)
            diverged, time_up = bool(flags[0]), bool(flags[1])
        if diverged:
            what = ", ".join(bad) or (
                "policy parameters" if not finite else "values on another rank"
            )
            last = checkpoint_files(self.run)
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
        self._record(row, done, elapsed, time_up)
        if time_up:
            raise _TimeUp

    def _row(
        self,
        done: int,
        elapsed: float,
        loss_dict: dict,
        learning_rate: float,
        action_std: torch.Tensor,
        seconds: float,
    ) -> dict[str, float]:
        """The iteration's progress row: counts, speed, rewards, the update's statistics,
        losses, and the episodes' logged means (rsl_rl's extras, cleared here)."""
        lg = self.runner.logger
        batch = self.num_envs * self.steps_per_env * self.ranks.world_size  # Over all ranks.
        row: dict[str, float] = {
            "iteration": done,
            "env_steps": done * batch,
            "seconds": self.seconds_before + elapsed,
            "steps_per_second": batch / max(seconds, 1e-9),
            "mean_reward": float(np.mean(lg.rewbuffer)) if len(lg.rewbuffer) else math.nan,
            "mean_episode_length": float(np.mean(lg.lenbuffer)) if len(lg.lenbuffer) else math.nan,
            "learning_rate": float(learning_rate),
            **(self.runner.update_stats or {}),
            "action_std": float(action_std.detach().mean()),
            **{f"loss_{k}": float(v) for k, v in loss_dict.items()},
        }
        keys = dict.fromkeys(k for ep in lg.ep_extras for k in ep)
        for key in keys:
            vals = [torch.as_tensor(ep[key], dtype=torch.float32).flatten()
                    for ep in lg.ep_extras if key in ep]  # fmt: skip
            row[key] = float(torch.cat(vals).mean()) if vals else math.nan
        lg.ep_extras.clear()
        return row

    def _record(self, row: dict[str, float], done: int, elapsed: float, time_up: bool) -> None:
        """Rank 0's record of an iteration: TensorBoard, progress.csv (the header's columns,
        in its order), the progress bar, and a checkpoint every ``every`` iterations, at the
        last and when the time is up."""
        lg = self.runner.logger
        if lg.writer is not None:
            for k, v in row.items():
                if k != "iteration":
                    lg.writer.add_scalar(f"humimic/{k}", v, done)
        csv_path = self.run / "progress.csv"
        columns = self.columns if csv_path.exists() else None
        new = columns is None
        if columns is None:
            columns = self.columns = list(row)
        with open(csv_path, "w" if new else "a", newline="") as f:
            # The header's columns, in its order: every row lines up with it.
            w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(row)
        if self.bar is not None:
            self.bar.update(1)
            post = {"reward": f"{row['mean_reward']:.3g}",
                    "ep_len": f"{row['mean_episode_length']:.0f}",
                    "sps": f"{row['steps_per_second']:.0f}"}  # fmt: skip
            if self.max_seconds is not None:
                post["left"] = f"{max(0.0, self.max_seconds - elapsed) / 60:.1f} min"
            self.bar.set_postfix(post)
        if done % self.every == 0 or done == self.total or time_up:
            path = self.run / "checkpoints" / f"model_{done:06d}.pt"
            self.runner.save_checkpoint(path, done)


def train(
    settings: TrainSettings, ppo: PpoConfig | None = None, *, started: float | None = None
) -> dict:
    """Train (or resume) a tracking policy. Returns the last progress row.

    ``started`` (a ``time.perf_counter()`` value) is when ``--max-minutes`` began to count
    (default: when training starts), so that work before it (refining the motion) counts.

    A crash, even ``kill -9``, never leaves a half checkpoint that looks whole; ``--resume``
    keeps what was learned up to the newest checkpoint that loads and redoes what came after
    it (progress.csv drops its rows past the checkpoint).

    Under torchrun (``WORLD_SIZE`` > 1) every process trains data-parallel with the others
    (:mod:`humimic.tracking.distributed`); ``--num-envs`` is each process's.
    """
    s = settings.sized()
    assert s.num_envs is not None and s.max_iterations is not None  # sized() set them.
    run = s.out
    ranks = Ranks.from_env()
    has_run = check_run_settings(s)
    if s.resume:
        _check_resume(s)
    if not s.motion.exists():
        raise InputError(f"--motion {s.motion}: no such file or folder")
    ppo = ppo or ppo_for(s)
    cfg = train_cfg(ppo)
    check_batch(cfg, s.num_envs)
    _check_train_outputs(s, has_run)
    seed = s.seed + ranks.rank  # Each rank collects its own experience.
    task = replace(
        task_config(s.robot, s.dr, seed, s.physics, s.task),
        torch_compile=s.compile,
        backend=s.backend,
    )
    motion = load_references(s.motion, s.robot, 1.0 / task.step_dt)
    init = None if has_run else _init_checkpoint(s, task.action_base)
    device = s.device
    if ranks.distributed:
        device = distributed.start(ranks, s.device)
        agree([0], device)  # Every rank has checked the run folder before rank 0 writes it.
    created = not run.exists() and ranks.main
    hold = contextlib.ExitStack()  # The run folder's lock, from its creation to the end.
    try:
        if ranks.main:
            check_writable(run / "config.yaml", create=True)
            hold.enter_context(run_folder_lock(run, has_run))
        torch.manual_seed(seed)
        env = run_env(task, motion, s, created, device=device)
        try:
            log_dir = run / "tensorboard" if ranks.main else None
            runner = make_runner(env, cfg, log_dir=log_dir, device=device, ranks=ranks)
            if init is not None:
                try:
                    _start_from(runner, init, s, ppo)
                except InputError:
                    if created:  # Leave nothing behind for a run that never started.
                        shutil.rmtree(run, ignore_errors=True)
                    raise
            else:
                scale_actor_output(runner, ppo.actor_output_gain)  # A resume loads weights.
            if ranks.main:
                (run / "checkpoints").mkdir(parents=True, exist_ok=True)
                if not has_run:
                    write_run_config(run, s, task, cfg)
            steps = int(cfg["num_steps_per_env"])
            return fit(runner, run, s, steps_per_env=steps, ranks=ranks, started=started)
        finally:
            env.close()
    finally:
        hold.close()
        distributed.stop()


def _check_resume(s: TrainSettings) -> None:
    """``--resume`` goes on as the run began: the settings that must match do (compared with
    the paths resolved: ./walk.npz and /abs/walk.npz are the same motion), and the motion is
    unchanged since."""
    recorded = run_config(s.out)
    old, new = recorded[1], resolved_settings(s)
    diff = settings_differences(old, new, _MUST_MATCH_ON_RESUME)
    if diff:
        names = [d.split("=", 1)[0] for d in diff]
        verb = "differs" if len(diff) == 1 else "differ"
        raise InputError(f"--resume: {', '.join(names)} {verb} from the run's ({', '.join(diff)})")
    recorded_motion(s.out, recorded, "a resumed run goes on with the motion it began on")


def _init_checkpoint(s: TrainSettings, action_base: str) -> tuple[Path, dict] | None:
    """The checkpoint ``--init-from`` names (a run's newest, or a file) and its contents,
    checked against the run's action base; None without the flag."""
    if s.init_from is None:
        return None
    if not s.init_from.exists():
        raise InputError(f"--init-from {s.init_from}: no such run or checkpoint")
    file = s.init_from if s.init_from.is_file() else None
    init = resolve_checkpoint(s.init_from, file, "--init-from")
    _check_init_base(init[0], action_base)
    return init


def _check_init_base(checkpoint: Path, action_base: str) -> None:
    """A checkpoint's actor acts around its run's action base: ``--init-from`` one of another
    base would start from a policy that no longer does what it learned. Checked where the
    checkpoint's run folder (``<run>/checkpoints/<file>``) records its base."""
    config = checkpoint.parent.parent / "config.yaml"
    if checkpoint.parent.name != "checkpoints" or not config.is_file():
        return
    try:
        recorded = yaml.safe_load(config.read_text())["tracking"]["action_base"]
    except (yaml.YAMLError, KeyError, TypeError, OSError, UnicodeDecodeError):
        return  # An older or foreign run folder: the networks' shapes are still checked.
    if recorded != action_base:
        raise InputError(
            f"--init-from {checkpoint}: its policy acts around the {recorded!r} action base, "
            f"this run's is {action_base!r}; pass --task.action-base {recorded}"
        )


def _start_from(runner: Any, init: tuple[Path, dict], s: TrainSettings, ppo: PpoConfig) -> None:
    """Load ``--init-from``'s weights into a new run's runner (its iteration count restarts).

    A PPO checkpoint gives actor, critic and optimizer (its moments; the learning rate is
    this run's ``--ppo.learning-rate``, not the one the checkpoint's run ended at). A
    student's (``humimic distill``) gives the actor alone: the critic starts fresh
    (``--ppo.critic-warmup-iterations`` trains it before the actor moves), and the action noise
    starts at ``--ppo.init-std``: a student's std is the fixed rollout noise of its
    distillation, not something it learned.
    """
    path, blob = init
    student = "actor_state_dict" not in blob and "student_state_dict" in blob
    if student:
        blob = {"actor_state_dict": blob["student_state_dict"]}
    try:
        runner.alg.load(blob, {"actor": True} if student else None, True)
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as e:
        hint = (
            "; a student of kind mlp-history trains with --variant asymmetric (its actor "
            "observes the same groups)"
            if student
            else ""
        )
        raise InputError(
            f"--init-from {path}: its networks do not fit this run's (variant "
            f"{s.variant!r}, task of {s.robot!r}): {first_line(e)}{hint}"
        ) from None
    if student:
        with torch.no_grad():
            runner.alg.get_policy().distribution.std_param.fill_(ppo.init_std)
    # The optimizer's state carries the learning rate the checkpoint's run ended with (the
    # adaptive schedule's last value); this run's --ppo.learning-rate is the one it starts at.
    runner.alg.learning_rate = ppo.learning_rate
    optimizer = getattr(runner.alg, "optimizer", None)
    for group in optimizer.param_groups if optimizer is not None else []:
        group["lr"] = ppo.learning_rate
    runner.current_learning_iteration = 0


def run_env(
    task: TrackingConfig,
    motion: Motion | list[Motion],
    s: Any,
    created: bool,
    device: str | None = None,
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


def check_batch(cfg: dict[str, Any], num_envs: int) -> None:
    """A PPO rollout (``num_envs`` x ``num_steps_per_env`` samples) must fill every
    mini-batch: a smaller one gives empty mini-batches and NaN losses."""
    algorithm = cfg["algorithm"]
    if algorithm.get("class_name") != "PPO":
        return
    steps, minis = int(cfg["num_steps_per_env"]), int(algorithm["num_mini_batches"])
    if num_envs * steps < minis:
        raise InputError(
            f"--num-envs {num_envs} x --num-steps-per-env {steps}: a rollout of "
            f"{num_envs * steps} samples cannot fill PPO's {minis} mini-batches "
            "(--ppo.num-mini-batches); raise either"
        )


def _check_train_outputs(s: TrainSettings, has_run: bool) -> None:
    """The files a run writes in ``--out`` must not be one of its inputs."""
    inputs: dict[str, Any] = {"--motion": s.motion, "--init-from": s.init_from}
    for flag, value, names in (("--dr", s.dr, DR_PROFILES), ("--physics", s.physics, ())):
        if value is not None and value not in names and Path(value).is_file():
            inputs[flag] = value
    for name in ("config.yaml", "progress.csv"):
        check_not_input(s.out / name, inputs, "--out")
    if s.init_from is not None and not has_run:
        # A new run writes checkpoints/model_<it>.pt: a file there it starts from would go.
        out, init = s.out.resolve(), s.init_from.resolve()
        if init == out or out in init.parents:
            raise InputError(
                f"--out {s.out}: holds --init-from {s.init_from}, which the new run would "
                "overwrite; choose another --out"
            )


def check_run_settings(s: Any) -> bool:
    """Check the settings every run command shares (``TrainSettings``, ``DistillSettings``:
    their ``validate()`` and the run folder); returns whether ``s.out`` holds a run already
    (allowed only with ``s.resume``)."""
    s.validate()
    if s.out.exists() and not s.out.is_dir():
        raise InputError(f"--out {s.out}: exists and is not a folder")
    has_run = (s.out / "config.yaml").exists()
    if has_run and not s.resume:
        raise InputError(f"--out {s.out}: holds a run already; pass --resume to continue it")
    if s.resume and not has_run:
        what = "no such folder" if not s.out.exists() else "it holds no run (no config.yaml)"
        raise InputError(f"--resume --out {s.out}: {what}, nothing to continue; drop --resume "
                         "to start a new run")  # fmt: skip
    init = getattr(s, "init_from", None)  # One inside --out: _check_train_outputs says so.
    inside = init is not None and s.out.resolve() in (init.resolve(), *init.resolve().parents)
    # A refined reference written for this run before it starts is the run's own.
    if (
        not has_run
        and not inside
        and s.out.is_dir()
        and any(p.name not in (REFERENCE_FILE, REFERENCE_LIBRARY) for p in s.out.iterdir())
    ):
        # A run folder is a run's alone: its files beside others' would be mixed up, and
        # files of the names it writes overwritten.
        raise InputError(
            f"--out {s.out}: exists and is not empty (and holds no run); choose a new or empty "
            "folder"
        )
    return has_run


def fit(
    runner: Any,
    run: Path,
    s: Any,
    *,
    steps_per_env: int,
    ranks: Ranks | None = None,
    started: float | None = None,
) -> dict:
    """Run a runner's learning loop for a run folder: resume from its newest checkpoint if
    ``s.resume``, progress bar, CSV, checks, periodic atomic checkpoints, time budget.

    Args:
        runner: From :func:`~humimic.tracking.rsl.make_runner`, its initial weights loaded.
        run: The run folder.
        s: Settings with ``resume``, ``max_iterations``, ``checkpoint_every``, ``quiet``,
            ``num_envs`` and ``max_minutes`` (:class:`TrainSettings`, ``DistillSettings``).
        steps_per_env: Rollout length per iteration.
        ranks: This process's place in a data-parallel run (default: a single process).
        started: When ``max_minutes`` began to count (``time.perf_counter()``; default: now).

    Returns:
        The last progress row.
    """
    start = 0
    ranks = ranks or Ranks()
    if s.resume:
        found = latest_checkpoint(run, skip_damaged=True)
        if found is not None:
            path, blob = found
            load_weights(runner, blob, path, "--resume: checkpoint")
            start = int(blob["iter"])
            print(f"resuming {run} from {path.name} ({start} iterations done)")
    if start >= s.max_iterations:
        print(f"{run}: {start} iterations done already (--max-iterations {s.max_iterations})")
        return {"iteration": start}
    offset, columns = (0.0, None)
    if ranks.main:  # Rank 0 alone writes progress.csv.
        offset, columns = trim_progress(run / "progress.csv", start)
    bar = None
    if not s.quiet and ranks.main:
        from tqdm import tqdm

        # With a time budget and no iteration limit, the bar counts minutes.
        timed = s.max_minutes is not None and s.max_iterations >= TIMED_ITERATIONS
        bar = tqdm(total=None if timed else s.max_iterations, initial=start, unit="it",
                   desc=run.name or "train")  # fmt: skip
    progress = _Progress(runner=runner, run=run, every=s.checkpoint_every,
                         total=s.max_iterations, bar=bar,
                         started=time.perf_counter() if started is None else started,
                         num_envs=s.num_envs, steps_per_env=steps_per_env,
                         max_seconds=None if s.max_minutes is None else 60 * s.max_minutes,
                         ranks=ranks, seconds_before=offset, columns=columns)  # fmt: skip
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
    "check_batch",
    "check_run_settings",
    "fit",
    "latest_checkpoint",
    "load_reference",
    "load_weights",
    "read_checkpoint",
    "read_run_settings",
    "resolve_checkpoint",
    "resolved_settings",
    "run_files",
    "run_rsl_cfg",
    "task_config",
    "train",
    "trim_progress",
]
