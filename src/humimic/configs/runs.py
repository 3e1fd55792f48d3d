"""Settings of tracking runs (``humimic train``, ``distill``), of the task a run changes and of
PPO: light to import. Each has ``validate()``, which the command calls before any work. The
commands that use a trained run have theirs in :mod:`humimic.configs.jobs`, the bounds and
checks they share are :mod:`humimic.configs.limits`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from humimic.configs.choices import ActionBaseName, DrChoice, PhysicsChoice, RobotName
from humimic.configs.limits import (
    CPU_NUM_ENVS,
    DEFAULT_ITERATIONS,
    GPU_NUM_ENVS,
    MAX_EPOCHS,
    MAX_HIDDEN,
    MAX_HISTORY,
    MAX_NUM_ENVS,
    MAX_SEED,
    MAX_STEPS_PER_ENV,
    MAX_WEIGHT,
    TIMED_ITERATIONS,
    at_least,
    at_most,
    check_device,
    check_minutes,
    check_reals,
    check_seed,
    default_num_envs,
    flag_name,
)
from humimic.errors import InputError

_TASKS = tyro.conf.arg(help_behavior_hint="(default: the robot's task's)")


@dataclass(frozen=True, kw_only=True)
class TaskSettings:
    """Settings of the tracking task a run changes (``--task.*``); each one unset keeps the
    value of the robot's registered task (:func:`humimic.tracking.config.tracking_task`)."""

    episode_length_s: Annotated[float | None, _TASKS] = None
    """Episode length [s]; the clip's end also ends an episode."""
    action_base: Annotated[ActionBaseName | None, _TASKS] = None
    """What the scaled action is added to: ``default`` (the default pose, BeyondMimic's),
    ``reference`` (the next frame's reference joint positions), ``feedforward`` (the PD
    targets ``humimic refine`` stores) or ``feedback`` (those plus time-varying LQR feedback
    around the refined trajectory); for the last two train refines a kinematic motion
    first."""
    action_scale: Annotated[float | None, _TASKS] = None
    """PD target = base + action_scale * effort limit / kp * action, per joint
    (BeyondMimic's scaling)."""
    soft_limit_factor: Annotated[float | None, _TASKS] = None
    """Soft joint limits, as a fraction of each joint's range (centred; 0 to 1)."""
    history_length: Annotated[int | None, _TASKS] = None
    """Policy observations stacked in the proprioceptive history (what the ``asymmetric``
    variant's actor reads)."""
    reward_weights: Annotated[
        dict[str, float], tyro.conf.arg(help_behavior_hint="(default: the task's weights)")
    ] = field(default_factory=dict)
    """New weights of reward terms, by name: ``--task.reward-weights body_pos 2.0
    action_rate_l2 -0.05`` (the terms: docs/tracking.md)."""
    reward_stds: Annotated[
        dict[str, float], tyro.conf.arg(help_behavior_hint="(default: the task's stds)")
    ] = field(default_factory=dict)
    """New widths of the tracking terms ``exp(-err / std**2)``, by name:
    ``--task.reward-stds anchor_pos 0.3`` (mjlab's; the terms with a std: docs/tracking.md)."""
    feedback_root_cost: Annotated[float | None, _TASKS] = None
    """The ``feedback`` base's LQR cost of the root's world position [1/m^2] (the task's
    default holds the robot to the clip's place in the world; 10 was the default before
    2026-12-02)."""
    feedback_delay: Annotated[int | None, _TASKS] = None
    """Policy steps (20 ms each on the G1) of command latency the ``feedback`` base's LQR is
    designed for: it issues the stored target of the step its command will act on and feeds
    back the commands still in flight (0: none, the default)."""
    dr_replay: Annotated[float | None, _TASKS] = None
    """Share of episode resets that replay the domain-randomization draw of a recently
    failed episode instead of a fresh one, so that training visits the physics the policy
    falls on more often (0: none; below 1)."""

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the flag."""
        check_reals(
            self, "task", ("episode_length_s", "action_scale", "feedback_root_cost"), positive=True
        )
        if self.dr_replay is not None and not (
            math.isfinite(self.dr_replay) and 0 <= self.dr_replay < 1
        ):
            raise InputError(f"--task.dr-replay {self.dr_replay}: expected a share in [0, 1)")
        if self.feedback_delay is not None and not 0 <= self.feedback_delay <= 10:
            raise InputError(
                f"--task.feedback-delay {self.feedback_delay}: expected 0-10 policy steps"
            )
        if self.feedback_delay and self.action_base not in (None, "feedback"):
            raise InputError(
                f"--task.feedback-delay {self.feedback_delay}: only the 'feedback' action base "
                f"has an LQR to design for a delay (--task.action-base {self.action_base})"
            )
        for name, v in self.reward_stds.items():
            if not (math.isfinite(v) and 0 < v <= MAX_WEIGHT):
                raise InputError(
                    f"--task.reward-stds {name} {v}: must be a positive number of at most "
                    f"{MAX_WEIGHT:g}"
                )
        if self.soft_limit_factor is not None and not 0 < self.soft_limit_factor <= 1:
            raise InputError(
                f"--task.soft-limit-factor {self.soft_limit_factor}: must be in (0, 1]"
            )
        if self.history_length is not None and not 1 <= self.history_length <= MAX_HISTORY:
            raise InputError(
                f"--task.history-length {self.history_length}: must be in 1 to {MAX_HISTORY}"
            )
        for name, w in self.reward_weights.items():
            if not (math.isfinite(w) and abs(w) <= MAX_WEIGHT):
                raise InputError(
                    f"--task.reward-weights {name} {w}: must be a number of magnitude at most "
                    f"{MAX_WEIGHT:g}"
                )


@dataclass(frozen=True, kw_only=True)
class PpoConfig:
    """PPO and its actor-critic networks (``--ppo.*``): BeyondMimic's / mjlab's G1 tracking
    values (``mjlab/tasks/tracking/config/g1/rl_cfg.py``), except where a residual policy
    starts (``init_std`` 0.3 instead of 1.0 and ``actor_output_gain`` 0.01: the policy
    starts at its action base) and where the update's cost per sample counts on a CPU
    (networks of 256-128-64 instead of 512-256-128 and 3 epochs instead of 5: the update
    took ~40 % of an iteration, and the walk's policy under DR got better with the 40-75 %
    more env steps that fit in 30 minutes; BENCHMARKS.md, issue 25). Turned into rsl_rl's
    config dict by :func:`humimic.tracking.rsl.train_cfg`.

    Attributes:
        actor_hidden_dims: Hidden layer sizes of the actor MLP.
        critic_hidden_dims: Hidden layer sizes of the critic MLP.
        activation: Activation of both MLPs.
        obs_normalization: Empirical observation normalization in both models.
        init_std: Initial action noise standard deviation (scalar parameterization).
        actor_output_gain: The actor's last layer's initial weights times this, its bias
            zero (1: PyTorch's initialization): a small gain starts a residual policy (action
            base ``reference`` or ``feedforward``) at its base.
        critic_warmup_iterations: For this many first iterations, PPO's updates train the
            critic alone, at a fixed learning rate: the actor (a residual policy that starts
            at its action base) keeps its initial weights until the critic's advantages mean
            something (residual RL's critic burn-in; BENCHMARKS.md, issue 25).
        rma_latent_dim: The ``rma`` variant's latent size: its actor's encoder turns the
            physics parameters e into z = mu(e) of this size (RMA's: 8).
        rma_encoder_hidden_dims: Hidden layer sizes of the ``rma`` variant's encoder mu.
        learning_rate: Adam learning rate (adapted to ``desired_kl``).
        schedule: ``adaptive`` or ``fixed``.
        desired_kl: Target KL divergence of the adaptive schedule.
        entropy_coef: Entropy bonus.
        value_loss_coef: Value loss weight.
        use_clipped_value_loss: Clip the value loss like the policy loss.
        clip_param: PPO clipping.
        num_learning_epochs: Epochs per update.
        num_mini_batches: Mini-batches per epoch.
        gamma: Discount.
        lam: GAE lambda.
        max_grad_norm: Gradient clipping.
        num_steps_per_env: Rollout length per env and iteration (``--num-steps-per-env``).
        save_interval: Iterations between checkpoints (``--checkpoint-every``).
        obs_groups: Observation sets -> env observation groups (``--variant``).
        encoder_groups: The actor's groups that an encoder turns into a latent before its
            MLP (``--variant rma``: ``physics``); empty: a plain MLP actor.
        logger: rsl_rl log writer (``tensorboard``).
        run_name: Suffix of the run folder.
        check_for_nan: Check observations and rewards for NaN every step.
    """

    actor_hidden_dims: tuple[int, ...] = (256, 128, 64)
    critic_hidden_dims: tuple[int, ...] = (256, 128, 64)
    activation: tyro.conf.Suppress[str] = "elu"
    obs_normalization: bool = True
    init_std: float = 0.3
    actor_output_gain: float = 0.01
    critic_warmup_iterations: int = 0
    rma_latent_dim: int = 8
    rma_encoder_hidden_dims: tuple[int, ...] = (256, 128)
    learning_rate: float = 1e-3
    schedule: Literal["adaptive", "fixed"] = "adaptive"
    desired_kl: float = 0.01
    entropy_coef: float = 0.005
    value_loss_coef: float = 1.0
    use_clipped_value_loss: bool = True
    clip_param: float = 0.2
    num_learning_epochs: int = 3
    num_mini_batches: int = 4
    gamma: float = 0.99
    lam: float = 0.95
    max_grad_norm: float = 1.0
    num_steps_per_env: tyro.conf.Suppress[int] = 24
    save_interval: tyro.conf.Suppress[int] = 500
    obs_groups: tyro.conf.Suppress[dict[str, tuple[str, ...]]] = field(
        default_factory=lambda: {"actor": ("policy",), "critic": ("critic",)}
    )
    encoder_groups: tyro.conf.Suppress[tuple[str, ...]] = ()
    logger: tyro.conf.Suppress[str] = "tensorboard"
    run_name: tyro.conf.Suppress[str] = ""
    check_for_nan: tyro.conf.Suppress[bool] = True

    def validate(self) -> None:
        """Check the values; :class:`InputError` names the flag (``--ppo.<field>``)."""
        positive = ("init_std", "learning_rate", "desired_kl", "clip_param", "max_grad_norm")
        check_reals(self, "ppo", positive, positive=True)
        check_reals(
            self, "ppo", ("entropy_coef", "value_loss_coef", "actor_output_gain"), positive=False
        )
        for name in ("gamma", "lam"):
            v = getattr(self, name)
            if not 0 < v <= 1:  # NaN fails too.
                raise InputError(f"--ppo.{name} {v}: must be in (0, 1]")
        w = self.critic_warmup_iterations
        if isinstance(w, bool) or not isinstance(w, int) or w < 0:
            raise InputError(f"--ppo.critic-warmup-iterations {w}: must be a whole number >= 0")
        for name in ("num_learning_epochs", "num_mini_batches"):
            v = getattr(self, name)
            if not 1 <= v <= MAX_EPOCHS:
                raise InputError(f"--ppo.{flag_name(name)[2:]} {v}: must be in 1 to {MAX_EPOCHS}")
        if not 1 <= self.rma_latent_dim <= MAX_HIDDEN:
            raise InputError(
                f"--ppo.rma-latent-dim {self.rma_latent_dim}: must be in 1 to {MAX_HIDDEN}"
            )
        for name in ("actor_hidden_dims", "critic_hidden_dims", "rma_encoder_hidden_dims"):
            dims = getattr(self, name)
            if not dims or not all(1 <= d <= MAX_HIDDEN for d in dims):
                raise InputError(
                    f"--ppo.{flag_name(name)[2:]} {' '.join(map(str, dims)) or '(none)'}: one or "
                    f"more layer sizes, each 1 to {MAX_HIDDEN}"
                )


@dataclass(frozen=True, kw_only=True)
class TrainSettings:
    """Train a tracking policy with PPO on a reference motion; the run folder survives crashes
    (``--resume`` continues it)."""

    motion: Path
    """Reference motion file (``.npz`` from ``humimic retarget``), or a library of clips for
    one policy: a folder of ``.npz`` files or a ``.yaml`` list of them (docs/tracking.md)."""
    out: Path
    """Run folder (config.yaml, progress.csv, checkpoints/, tensorboard/)."""
    robot: RobotName = "g1"
    """Registry name; must match the motion's."""
    num_envs: int | None = None
    """Parallel environments (under torchrun: each process's); default: 128 on the CPU, 4096
    on a GPU."""
    max_iterations: int | None = None
    """Total PPO iterations of the run (a resumed run continues up to it); default: 1000, or
    with ``--max-minutes`` as many as the time allows."""
    device: str = "cpu"
    """Torch device of the learner (``cpu``, ``cuda`` or ``cuda:N``). Under torchrun each
    process takes the GPU of its local rank."""
    backend: Literal["cpu", "warp"] = "cpu"
    """The simulator: ``cpu`` (MuJoCo on the CPU) or ``warp`` (MuJoCo Warp on ``--device``:
    GPU throughput; needs ``humimic[gpu]``)."""
    dr: DrChoice = "default"
    """Domain randomization: a profile name (``none``, ``default``) or a YAML file."""
    physics: PhysicsChoice | None = None
    """Train on a fixed model: a physics file (docs/tracking.md, "Physics files"), e.g. the
    correction ``humimic sysid diagnose`` found; DR acts on top of it."""
    init_from: Path | None = None
    """Start from another run's weights (its newest checkpoint, or a checkpoint file):
    fine-tuning. Actor and critic must have the same inputs (same variant and task)."""
    variant: Literal["beyondmimic", "robust", "asymmetric", "teacher", "rma"] = "beyondmimic"
    """What actor and critic observe (docs/tracking.md, "Variants"): ``beyondmimic`` (actor:
    deployable observations; critic: privileged), ``robust`` (both deployable only),
    ``asymmetric`` (actor: deployable plus the proprioceptive history; critic: privileged),
    ``teacher`` (actor: deployable plus the physics parameters e; critic: privileged; distill
    it with ``humimic distill``), ``rma`` (Rapid Motor Adaptation's phase 1: actor pi(deployable,
    z) with z = mu(e) a small latent of the physics parameters, ``--ppo.rma-latent-dim``;
    critic: privileged; distill it with ``humimic distill --student rma``)."""
    resume: bool = False
    """Continue the run in ``--out`` from its newest checkpoint."""
    seed: int = 0
    """Seed of torch and of the environment."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (the last one is always written)."""
    num_steps_per_env: int | None = None
    """Rollout length per env and iteration (default: the PPO config's, 24)."""
    max_minutes: float | None = None
    """Stop (with a checkpoint) after the iteration that passes this wall time."""
    compile: bool = False
    """Compile the env's tensor math with ``torch.compile`` (on the CPU: needs a C++ compiler,
    seconds at the start; cuts the env's own cost per step, BENCHMARKS.md)."""
    quiet: bool = False
    """No progress bar."""
    task: TaskSettings = field(default_factory=TaskSettings)
    """The tracking task's settings."""
    ppo: PpoConfig = field(default_factory=PpoConfig)
    """PPO's settings."""

    def sized(self) -> TrainSettings:
        """The settings with the defaults that depend on others filled in: ``num_envs`` for
        the device, ``max_iterations`` for the time budget."""
        limit = self.max_iterations
        if limit is None:
            limit = DEFAULT_ITERATIONS if self.max_minutes is None else TIMED_ITERATIONS
        envs = self.num_envs if self.num_envs is not None else default_num_envs(self.device)
        return replace(self, num_envs=envs, max_iterations=limit)

    def validate(self) -> None:
        """Check the numbers and the device; :class:`InputError` names the flag."""
        at_least(self, ("num_envs", "max_iterations", "checkpoint_every", "num_steps_per_env"))
        at_most(self, {"num_envs": MAX_NUM_ENVS, "num_steps_per_env": MAX_STEPS_PER_ENV})
        check_minutes(self.max_minutes)
        check_seed(self.seed)
        self.task.validate()
        self.ppo.validate()
        check_device(self.device)


@dataclass(frozen=True, kw_only=True)
class DistillSettings:
    """Distill a teacher run into a proprioceptive student, DAgger-style (rsl_rl's
    Distillation: the student acts, the teacher labels every visited state)."""

    teacher: Path
    """Run folder of ``humimic train`` (any variant; ``teacher`` is the usual one, ``rma``
    for ``--student rma``)."""
    out: Path
    """The student's run folder."""
    student: Literal["mlp-history", "mlp-velocity", "gru", "rma"] = "mlp-history"
    """``mlp-history`` (an MLP on the policy observations and their history),
    ``mlp-velocity`` (the same plus the base's linear velocity, which a robot estimates),
    ``gru`` (a recurrent network on the policy observations) or ``rma`` (RMA's phase 2, for
    a ``--variant rma`` teacher: the teacher's base policy, frozen, with an adaptation module
    that estimates the teacher's latent z from the policy observations and their history,
    trained on the latent's MSE)."""
    student_base: ActionBaseName | None = None
    """The action base the student acts around (default: the teacher's). ``feedforward``
    under a ``feedback`` teacher gives a student that needs no LQR and no simulator state:
    it learns the teacher's residual plus its base's LQR correction."""
    teacher_checkpoint: Path | None = None
    """The teacher's checkpoint (default: its newest)."""
    num_envs: int | None = None
    """Parallel environments; default: 128 on the CPU, 4096 on a GPU."""
    max_iterations: int = 300
    """Total distillation iterations (a resumed run continues up to it)."""
    device: str = "cpu"
    """Torch device (``cpu``, ``cuda`` or ``cuda:N``)."""
    dr: DrChoice | None = None
    """Domain randomization: a profile name or a YAML file (default: the teacher's)."""
    resume: bool = False
    """Continue the run in ``--out`` from its newest checkpoint."""
    seed: int = 0
    """Seed of torch and of the environment."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (the last one is always written)."""
    max_minutes: float | None = None
    """Stop (with a checkpoint) after the iteration that passes this wall time."""
    compile: bool = False
    """Compile the env's tensor math with ``torch.compile`` (on the CPU: needs a C++ compiler,
    seconds at the start; cuts the env's own cost per step, BENCHMARKS.md)."""
    quiet: bool = False
    """No progress bar."""

    def sized(self) -> DistillSettings:
        """The settings with the device's default for ``num_envs`` when it is unset."""
        return (
            self
            if self.num_envs is not None
            else replace(self, num_envs=default_num_envs(self.device))
        )

    def validate(self) -> None:
        """Check the numbers and the device; :class:`InputError` names the flag."""
        at_least(self, ("num_envs", "max_iterations", "checkpoint_every"))
        at_most(self, {"num_envs": MAX_NUM_ENVS})
        check_minutes(self.max_minutes)
        check_seed(self.seed)
        check_device(self.device)


__all__ = [
    "CPU_NUM_ENVS",
    "GPU_NUM_ENVS",
    "MAX_HIDDEN",
    "MAX_HISTORY",
    "MAX_NUM_ENVS",
    "MAX_SEED",
    "MAX_STEPS_PER_ENV",
    "TIMED_ITERATIONS",
    "DistillSettings",
    "PpoConfig",
    "TaskSettings",
    "TrainSettings",
    "check_device",
    "default_num_envs",
]
