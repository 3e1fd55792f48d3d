"""``humimic distill``: a privileged teacher distilled into a proprioceptive student.

:func:`distill` runs it; :func:`distill_cfg` builds rsl_rl's ``Distillation`` config.
"""

from __future__ import annotations

import copy
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch
import yaml
from tensordict import TensorDict

from humimic.configs.runs import DistillSettings, PpoConfig
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable
from humimic.tracking.rsl import RMA_ACTOR, MLPModel, VecEnv, make_runner

STUDENT_OBS: dict[str, tuple[str, ...]] = {
    "mlp-history": ("policy", "proprio_history"),
    "mlp-velocity": ("policy", "proprio_history", "base_lin_vel"),
    "gru": ("policy",),
    "rma": ("policy", "proprio_history"),
}
"""Observation groups of each student kind: only deployable groups.

* ``mlp-history``: an MLP on ``policy`` and ``proprio_history``;
* ``mlp-velocity``: the same plus the base's linear velocity (a robot's state estimate, as
  BeyondMimic's policy reads it; the LQR of a ``feedback`` teacher feeds it back);
* ``gru``: a GRU on ``policy``;
* ``rma``: an ``rma`` teacher's base policy on ``policy`` and the latent that an adaptation
  module estimates from ``policy`` and ``proprio_history``
  (:class:`~humimic.tracking.rma.RmaStudent`).
"""

RMA_STUDENT = "humimic.tracking.rma:RmaStudent"
RMA_DISTILLATION = "humimic.tracking.rma:RmaDistillation"


TEACHER_PREFIX = "teacher_"
"""Observation groups a :class:`StudentView` adds: ``teacher_<group>``, the teacher's view of
a group, and ``teacher_offset``, the teacher's base minus the student's in action units."""


class ExpertTeacher(MLPModel):
    """A trained actor that labels the states of a student acting around another action base:
    the actor reads ``teacher_<group>`` where the env gives one (:class:`StudentView`; else the
    group itself) and its action is moved by ``teacher_offset`` into the student's base. Its
    weights are the trained actor's exactly."""

    def get_latent(
        self, obs: TensorDict, masks: torch.Tensor | None = None, hidden_state: Any = None
    ) -> torch.Tensor:
        latent = torch.cat([obs.get(TEACHER_PREFIX + g, obs[g]) for g in self.obs_groups], dim=-1)
        return self.obs_normalizer(latent)

    def forward(
        self,
        obs: TensorDict,
        masks: torch.Tensor | None = None,
        hidden_state: Any = None,
        stochastic_output: bool = False,
    ) -> torch.Tensor:
        out = super().forward(obs, masks, hidden_state, stochastic_output)
        offset = obs.get(TEACHER_PREFIX + "offset", None)
        return out if offset is None else out + offset


class StudentView(VecEnv):
    """A tracking env whose actions are a student's around ``student base + scale * action``,
    seen also as the teacher saw its own: what DAgger needs when the student acts around a
    different base than its teacher (a ``feedforward`` student, which needs neither the
    simulator's state nor an LQR, under a ``feedback`` teacher).

    The env runs the student's base. The teacher's action that would send the same PD
    targets is ``a - offset``, ``offset = (teacher base - student base) / scale`` at the
    step's state; the observations gain ``teacher_policy`` and ``teacher_proprio_history``
    (the last action in them the teacher's) and ``teacher_offset`` (:class:`ExpertTeacher`
    adds it to the teacher's action: the student's label).
    """

    def __init__(self, env: Any, teacher_base: str) -> None:
        self.env = env
        self.teacher_base = teacher_base
        self.num_envs = env.num_envs
        self.num_actions = env.num_actions
        self.max_episode_length = env.max_episode_length
        self.device = env.device
        self.cfg = env.cfg
        n, j = env.num_envs, env.num_actions
        self._history_length = int(env.cfg.history_length)
        # The teacher's view of the last actions, newest last (zero at an episode's start).
        self._actions = torch.zeros(n, self._history_length + 1, j, device=env.device)
        self._offset = self._compute_offset()

    @property
    def episode_length_buf(self) -> torch.Tensor:  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.env.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:  # pyright: ignore[reportIncompatibleVariableOverride]
        self.env.episode_length_buf = value

    def _compute_offset(self) -> torch.Tensor:
        e = self.env
        own = e.base_targets(e.cfg.action_base)
        return (e.base_targets(self.teacher_base) - own) / e.action_scale

    def _view(self, obs: TensorDict) -> TensorDict:
        j, h = self.num_actions, self._history_length
        policy = obs["policy"].clone()
        policy[:, -j:] = self._actions[:, -1]
        hist = obs["proprio_history"].reshape(self.num_envs, h, -1).clone()
        hist[:, :, -j:] = self._actions[:, 1:]
        obs[TEACHER_PREFIX + "policy"] = policy
        obs[TEACHER_PREFIX + "proprio_history"] = hist.reshape(self.num_envs, -1)
        obs[TEACHER_PREFIX + "offset"] = self._offset.clone()
        return obs

    def get_observations(self) -> TensorDict:
        return self._view(self.env.get_observations())

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        a = actions.detach().to(self.device, torch.float32)
        teacher_action = a - self._offset  # Sends the student's PD targets in teacher terms.
        obs, rew, dones, extras = self.env.step(a)
        self._actions[:, :-1] = self._actions[:, 1:].clone()
        self._actions[:, -1] = teacher_action
        self._actions[dones.to(self.device).bool()] = 0.0  # A new episode: no action yet.
        self._offset = self._compute_offset()
        return self._view(obs), rew, dones, extras

    def close(self) -> None:
        self.env.close()


@dataclass(frozen=True, kw_only=True)
class DistillConfig:
    """Distillation hyperparameters (rsl_rl ``Distillation`` and the student network).

    Attributes:
        num_learning_epochs: Passes over each rollout.
        gradient_length: Policy steps of the rollout per optimizer step (rsl_rl's
            ``gradient_length``; each step's batch is every env's sample of it). None: the
            whole rollout (one optimizer step per epoch; what a recurrent student needs to
            backpropagate through time).
        learning_rate: Adam step size.
        max_grad_norm: Gradient clipping.
        loss_type: ``mse`` or ``huber``.
        hidden_dims: Student MLP layers (an ``rma`` student's: its adaptation module's); by
            default a PPO actor's (:class:`~humimic.configs.runs.PpoConfig`), so that PPO can
            start from the student (``humimic train --init-from``).
        activation: Student activation (an ``rma`` student's adaptation module's; its base
            policy's is the teacher's).
        init_std: Std of the student's exploration noise during rollouts.
        rnn_hidden_dim: GRU width (``gru`` students).
    """

    num_learning_epochs: int = 2
    gradient_length: int | None = None
    learning_rate: float = 1e-3
    max_grad_norm: float = 1.0
    loss_type: str = "mse"
    hidden_dims: tuple[int, ...] = PpoConfig.actor_hidden_dims
    activation: str = "elu"
    init_std: float = 0.05
    rnn_hidden_dim: int = 256


def distill_cfg(teacher_cfg: dict[str, Any], student: str, d: DistillConfig) -> dict[str, Any]:
    """The rsl_rl ``train_cfg`` of a distillation run from the teacher run's PPO ``train_cfg``.

    The gradient length is ``d.gradient_length`` steps (default: the whole rollout, each
    epoch backpropagating once through it); it must divide the rollout length. Two requirements of rsl_rl 5.x
    are met here: the student needs a ``distribution_cfg`` (it acts stochastically during
    rollouts; a small fixed std), and the teacher's model config must be the trained actor's
    exactly (it is copied from the teacher run, with the actor's observation groups as the
    ``teacher`` set).

    An ``rma`` student (:class:`~humimic.tracking.rma.RmaStudent`) takes the teacher's base
    policy configuration (its weights: :meth:`~humimic.tracking.rma.RmaDistillation.load`)
    and an adaptation module of ``d.hidden_dims``; the algorithm is
    :class:`~humimic.tracking.rma.RmaDistillation` (the latent's regression).
    """
    if student not in STUDENT_OBS:
        raise InputError(f"--student {student!r}: expected one of {', '.join(STUDENT_OBS)}")
    actor = teacher_cfg["actor"]
    rma = student == "rma"
    if rma and actor.get("class_name") != RMA_ACTOR:
        raise InputError(
            "--student rma: the teacher's actor has no latent to estimate; an RMA student "
            "needs a teacher trained with --variant rma"
        )
    steps = int(teacher_cfg["num_steps_per_env"])
    gl = d.gradient_length
    if gl is not None and (gl < 1 or steps % gl):
        raise InputError(f"gradient_length {gl}: expected a divisor of the rollout's {steps} steps")
    model: dict[str, Any] = {
        "class_name": "RNNModel" if student == "gru" else "MLPModel",
        "hidden_dims": list(d.hidden_dims),
        "activation": d.activation,
        "obs_normalization": True,
        "distribution_cfg": {
            "class_name": "GaussianDistribution",
            "init_std": d.init_std,
            "std_type": "scalar",
        },
    }
    if student == "gru":
        model.update(rnn_type="gru", rnn_hidden_dim=d.rnn_hidden_dim, rnn_num_layers=1)
    if rma:
        encoded = actor["encoder_groups"]
        model.update(
            class_name=RMA_STUDENT,
            hidden_dims=list(actor["hidden_dims"]),
            activation=actor["activation"],
            obs_normalization=actor["obs_normalization"],
            base_groups=[g for g in teacher_cfg["obs_groups"]["actor"] if g not in encoded],
            latent_dim=actor["latent_dim"],
            adapter_hidden_dims=list(d.hidden_dims),
            adapter_activation=d.activation,
        )
    return copy.deepcopy(
        {
            "num_steps_per_env": steps,
            "save_interval": teacher_cfg["save_interval"],
            "obs_groups": {
                "student": list(STUDENT_OBS[student]),
                "teacher": list(teacher_cfg["obs_groups"]["actor"]),
            },
            "logger": teacher_cfg["logger"],
            "run_name": "",
            "check_for_nan": True,
            "algorithm": {
                "class_name": RMA_DISTILLATION if rma else "Distillation",
                "num_learning_epochs": d.num_learning_epochs,
                "gradient_length": d.gradient_length or steps,
                "learning_rate": d.learning_rate,
                "max_grad_norm": d.max_grad_norm,
                "loss_type": d.loss_type,
            },
            "student": model,
            "teacher": actor,
        }
    )


def distill(settings: DistillSettings, d: DistillConfig | None = None) -> dict:
    """Distill (or resume distilling) a teacher run into a student. Returns the last progress
    row (``loss_behavior`` is the student's imitation loss).

    DAgger-style, with rsl_rl's ``Distillation`` algorithm: the student acts in the
    environment, the teacher labels every state the student visits with its own
    (deterministic) action, and the student regresses onto those labels. The student observes
    only deployable groups (:data:`STUDENT_OBS`). The teacher's ``actor_state_dict`` is loaded
    into the teacher model.

    The student's run folder is a run like any other: ``humimic eval`` and ``humimic export``
    take it.

    ``--student rma`` (RMA's phase 2, for an ``rma`` teacher) regresses the student's
    estimated latent onto the teacher's ``z = mu(e)`` instead of its actions, with the
    teacher's base policy copied into the student and frozen
    (:class:`~humimic.tracking.rma.RmaDistillation`); ``progress.csv`` has ``loss_latent``
    (trained on) and ``loss_behavior`` (the actions' MSE, not trained on).
    """
    from humimic.tracking.runs import run_folder_lock
    from humimic.tracking.task import load_references
    from humimic.tracking.train import check_run_settings, fit, run_env

    s = settings.sized()
    assert s.num_envs is not None  # sized() set it.
    has_run = check_run_settings(s)
    _check_outputs(s)
    teacher, teacher_cfg, ckpt, teacher_blob = _teacher_run(s)
    task, teacher, teacher_base = _student_task(s, teacher)
    moved = task.action_base != teacher_base
    motion = load_references(teacher.motion, teacher.robot, 1.0 / task.step_dt)
    cfg = distill_cfg(teacher_cfg, s.student, d or DistillConfig())
    if moved:
        cfg["teacher"]["class_name"] = f"{__name__}:ExpertTeacher"
    run = s.out
    created = not run.exists()
    check_writable(run / "config.yaml", create=True)
    with run_folder_lock(run, has_run):  # Until the student's last checkpoint.
        torch.manual_seed(s.seed)
        env = run_env(task, motion, s, created)
        try:
            venv = StudentView(env, teacher_base) if moved else env
            runner = make_runner(venv, cfg, log_dir=run / "tensorboard", device=s.device)
            _load_teacher(runner, teacher_blob, ckpt, s, created)
            (run / "checkpoints").mkdir(parents=True, exist_ok=True)
            if not has_run:
                _write_student_config(s, ckpt, teacher, task, cfg)
            return fit(runner, run, s, steps_per_env=int(cfg["num_steps_per_env"]))
        finally:
            env.close()


def _teacher_run(s: DistillSettings) -> tuple[Any, dict[str, Any], Path, dict]:
    """The teacher run's settings, its rsl_rl config, its checkpoint and that checkpoint's
    contents, checked: a PPO run (an ``rma`` one for an RMA student) whose files the student's
    folder does not overwrite, and whose motion is unchanged since it trained."""
    from humimic.tracking.runs import (
        recorded_motion,
        resolve_checkpoint,
        run_config,
        run_files,
        run_rsl_cfg,
    )

    recorded = run_config(s.teacher)
    teacher = recorded[1]
    teacher_cfg = run_rsl_cfg(s.teacher, recorded)
    if teacher_cfg["algorithm"]["class_name"] != "PPO":
        raise InputError(f"--teacher {s.teacher}: not a PPO run (a student cannot teach)")
    if s.student == "rma" and teacher.variant != "rma":
        raise InputError(
            f"--student rma: the teacher {s.teacher} was trained with --variant "
            f"{teacher.variant}; an RMA student estimates the latent of a --variant rma "
            "teacher's encoder"
        )
    inputs: dict[str, Any] = {**run_files(s.teacher), "the teacher's motion": teacher.motion}
    for name in ("config.yaml", "progress.csv"):
        check_not_input(s.out / name, inputs, "--out")
    ckpt, teacher_blob = resolve_checkpoint(s.teacher, s.teacher_checkpoint,
                                            "--teacher-checkpoint")  # fmt: skip
    recorded_motion(s.teacher, recorded)  # There, unchanged since the teacher trained on it.
    return teacher, teacher_cfg, ckpt, teacher_blob


def _student_task(s: DistillSettings, teacher: Any) -> tuple[Any, Any, str]:
    """The student's task (the teacher's, on the student's action base and DR), the teacher's
    settings as the student's run records them (its base moved with the student's: eval and
    export rebuild the student's env), and the teacher's action base."""
    from humimic.tracking.task import task_config

    task = task_config(teacher.robot, s.dr or teacher.dr, s.seed, teacher.physics, teacher.task)
    task = replace(task, torch_compile=s.compile)
    teacher_base = task.action_base
    student_base = s.student_base or teacher_base
    if student_base == teacher_base:
        return task, teacher, teacher_base
    if teacher.variant == "rma":
        raise InputError(
            f"--student-base {student_base}: an rma teacher labels states around its own "
            f"base ({teacher_base}) only; drop --student-base"
        )
    if task.feedback_delay:
        raise InputError(
            f"--student-base {student_base}: the teacher's feedback base is designed for "
            f"{task.feedback_delay} steps of latency; a student on another base learns from "
            "undelayed ones only"
        )
    task = replace(task, action_base=student_base)
    teacher = replace(teacher, task=replace(teacher.task, action_base=student_base))
    return task, teacher, teacher_base


def _load_teacher(runner: Any, blob: dict, ckpt: Path, s: DistillSettings, created: bool) -> None:
    """The teacher's actor into the teacher model, before anything is written: one that does
    not fit is refused naming the checkpoint, and a run folder made for it removed."""
    from humimic.errors import first_line

    try:
        runner.alg.load(blob, None, True)
    except (KeyError, RuntimeError, TypeError, ValueError, AttributeError) as e:
        if created:  # Leave nothing behind for a run that never started.
            shutil.rmtree(s.out, ignore_errors=True)
        flag = "--teacher-checkpoint" if s.teacher_checkpoint else "the teacher's checkpoint"
        raise InputError(
            f"{flag} {ckpt}: does not fit the teacher's actor ({first_line(e)})"
        ) from None


def _write_student_config(
    s: DistillSettings, ckpt: Path, teacher: Any, task: Any, cfg: dict[str, Any]
) -> None:
    """The student run's config.yaml: the teacher's settings, the distillation's (paths
    absolute, as a training run's config records them), the task and the rsl_rl config."""
    from humimic.sim.randomization import DR_PROFILES
    from humimic.tracking.runs import RUN_SCHEMA, resolved_source, yaml_ready

    recorded = replace(
        s,
        teacher=s.teacher.resolve(),
        out=s.out.resolve(),
        teacher_checkpoint=None if s.teacher_checkpoint is None else ckpt.resolve(),
        dr=resolved_source(s.dr, DR_PROFILES),
    )
    blob = {
        "schema": RUN_SCHEMA,
        "kind": "student",
        "settings": yaml_ready(asdict(teacher)),
        "distill": yaml_ready(asdict(recorded)),
        "tracking": yaml_ready(task),
        "rsl": yaml_ready(cfg),
    }
    atomic_write_text(s.out / "config.yaml", yaml.safe_dump(blob, sort_keys=False))


def _check_outputs(s: DistillSettings) -> None:
    """The student's run folder must not be the teacher's, nor hold the teacher checkpoint."""
    out = s.out.resolve()
    if out == s.teacher.resolve():
        raise InputError(f"--out {s.out}: is the teacher's run folder (--teacher); choose another")
    if s.teacher_checkpoint is not None and out in s.teacher_checkpoint.resolve().parents:
        raise InputError(
            f"--out {s.out}: holds --teacher-checkpoint {s.teacher_checkpoint}, which the "
            "student's checkpoints could overwrite; choose another --out"
        )


__all__ = ["STUDENT_OBS", "DistillConfig", "distill", "distill_cfg"]
