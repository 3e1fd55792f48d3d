"""The one boundary module to rsl_rl (pinned: rsl-rl-lib 5.5.1): no other module imports it
(``tests/test_architecture.py``); the env, the RMA actor and the distillation take rsl_rl's
classes from here.

:func:`train_cfg` turns a :class:`~humimic.configs.runs.PpoConfig` (mjlab's G1 tracking values
where they fit a CPU, ``humimic train --ppo.*``) into the dict ``OnPolicyRunner`` reads.
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from rsl_rl.algorithms import Distillation as Distillation
from rsl_rl.env import VecEnv as VecEnv
from rsl_rl.models import MLPModel as MLPModel
from rsl_rl.modules import MLP as MLP
from rsl_rl.modules import EmpiricalNormalization as EmpiricalNormalization

from humimic.configs.runs import PpoConfig
from humimic.errors import InputError
from humimic.io import atomic_write
from humimic.tracking.distributed import Ranks

RSL_RL_VERSION = "5.5.1"


VARIANT_OBS_GROUPS: dict[str, dict[str, tuple[str, ...]]] = {
    "beyondmimic": {"actor": ("policy",), "critic": ("critic",)},
    "robust": {"actor": ("policy",), "critic": ("policy",)},
    "asymmetric": {"actor": ("policy", "proprio_history"), "critic": ("critic",)},
    "teacher": {"actor": ("policy", "physics"), "critic": ("critic",)},
    "rma": {"actor": ("policy", "physics"), "critic": ("critic",)},
}
"""Training variants: the observation groups (:class:`~humimic.tracking.env.TrackingEnv`) of
rsl_rl's actor and critic."""

VARIANT_ENCODER_GROUPS: dict[str, tuple[str, ...]] = {"rma": ("physics",)}
"""Variants whose actor encodes some of its groups into a latent first
(:class:`~humimic.tracking.rma.RmaActor`): those groups."""

RMA_ACTOR = "humimic.tracking.rma:RmaActor"
"""rsl_rl's ``class_name`` of the ``rma`` variant's actor."""


def tracking_ppo(variant: str = "beyondmimic", base: PpoConfig | None = None) -> PpoConfig:
    """PPO for whole-body tracking for a training variant (:data:`VARIANT_OBS_GROUPS`): the
    settings of ``base`` (default: :class:`~humimic.configs.runs.PpoConfig`'s), the variant's
    observation groups and encoded groups (:data:`VARIANT_ENCODER_GROUPS`)."""
    if variant not in VARIANT_OBS_GROUPS:
        raise InputError(f"variant {variant!r}: expected one of {', '.join(VARIANT_OBS_GROUPS)}")
    return replace(
        base or PpoConfig(),
        obs_groups=dict(VARIANT_OBS_GROUPS[variant]),
        encoder_groups=VARIANT_ENCODER_GROUPS.get(variant, ()),
    )


def train_cfg(cfg: PpoConfig) -> dict[str, Any]:
    """The ``train_cfg`` dict of ``rsl_rl.runners.OnPolicyRunner`` (a new deep copy each call:
    the runner mutates it). With ``encoder_groups`` the actor is an
    :class:`~humimic.tracking.rma.RmaActor` (the ``rma`` variant)."""
    out: dict[str, Any] = {
        "num_steps_per_env": cfg.num_steps_per_env,
        "save_interval": cfg.save_interval,
        "obs_groups": {k: list(v) for k, v in cfg.obs_groups.items()},
        "logger": cfg.logger,
        "run_name": cfg.run_name,
        "check_for_nan": cfg.check_for_nan,
        "critic_warmup_iterations": cfg.critic_warmup_iterations,
        "algorithm": {
            "class_name": "PPO",
            "learning_rate": cfg.learning_rate,
            "schedule": cfg.schedule,
            "desired_kl": cfg.desired_kl,
            "entropy_coef": cfg.entropy_coef,
            "value_loss_coef": cfg.value_loss_coef,
            "use_clipped_value_loss": cfg.use_clipped_value_loss,
            "clip_param": cfg.clip_param,
            "num_learning_epochs": cfg.num_learning_epochs,
            "num_mini_batches": cfg.num_mini_batches,
            "gamma": cfg.gamma,
            "lam": cfg.lam,
            "max_grad_norm": cfg.max_grad_norm,
        },
        "actor": {
            "class_name": "MLPModel",
            "hidden_dims": list(cfg.actor_hidden_dims),
            "activation": cfg.activation,
            "obs_normalization": cfg.obs_normalization,
            "distribution_cfg": {
                "class_name": "GaussianDistribution",
                "init_std": cfg.init_std,
                "std_type": "scalar",
            },
        },
        "critic": {
            "class_name": "MLPModel",
            "hidden_dims": list(cfg.critic_hidden_dims),
            "activation": cfg.activation,
            "obs_normalization": cfg.obs_normalization,
        },
    }
    if cfg.encoder_groups:
        out["actor"].update(
            class_name=RMA_ACTOR,
            encoder_groups=list(cfg.encoder_groups),
            latent_dim=cfg.rma_latent_dim,
            encoder_hidden_dims=list(cfg.rma_encoder_hidden_dims),
        )
    return copy.deepcopy(out)


def scale_actor_output(runner: Any, gain: float) -> None:
    """Multiply the initial weights of the actor's last linear layer by ``gain`` and zero its
    bias (:attr:`PpoConfig.actor_output_gain`); a gain of 1 changes nothing."""
    if gain == 1.0:
        return
    layers = [m for m in runner.alg.actor.mlp.modules() if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        layers[-1].weight.mul_(gain)
        layers[-1].bias.zero_()


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run torch's CPU operations on ``n`` threads inside the block.

    Rollouts on the CPU use one torch thread (see :class:`_Runner`): the env's tensors are
    small, and torch's OpenMP workers keep spinning after each parallel operation, taking
    cores from the MuJoCo threads that step next (measured: 64 envs step 19% faster).
    """
    old = torch.get_num_threads()
    torch.set_num_threads(max(1, n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


class UpdateProbe:
    """The learning rates and KL divergences of one PPO update, mini-batch by mini-batch.

    rsl_rl's adaptive schedule changes the rate after every mini-batch (up while the KL from
    the rollout's policy is under half the desired one, down once it passes twice that); its
    log and ``progress.csv``'s ``learning_rate`` hold only the rate the update ended at, which
    is usually the lowest of the iteration (the KL is largest at the end). Inside the block the
    optimizer's steps and the actor's KL computations are recorded; :meth:`summary` gives
    ``lr_mean``, ``lr_max`` (over the update's optimizer steps) and ``kl`` (the last
    mini-batch's KL from the rollout's policy: how far the update moved it; NaN where the
    schedule computes none)."""

    def __init__(self, alg: Any) -> None:
        self.alg = alg
        self.rates: list[float] = []
        self.last_kl: torch.Tensor | None = None  # Read once, in summary(): no sync per batch.

    def __enter__(self) -> UpdateProbe:
        opt, actor = self.alg.optimizer, getattr(self.alg, "actor", None)
        step = opt.step

        def step_(*args: Any, **kwargs: Any) -> Any:
            self.rates.append(float(opt.param_groups[0]["lr"]))
            return step(*args, **kwargs)

        opt.step = step_
        if actor is not None and hasattr(actor, "get_kl_divergence"):
            kl = actor.get_kl_divergence

            def kl_(old: Any, new: Any) -> torch.Tensor:
                v = kl(old, new)
                self.last_kl = v.detach().mean()
                return v

            actor.get_kl_divergence = kl_
        return self

    def __exit__(self, *exc: object) -> None:
        # The wrappers are instance attributes: removing them restores the methods.
        self.alg.optimizer.__dict__.pop("step", None)
        actor = getattr(self.alg, "actor", None)
        if actor is not None:
            actor.__dict__.pop("get_kl_divergence", None)

    def summary(self) -> dict[str, float]:
        nan = math.nan
        return {
            "lr_mean": sum(self.rates) / len(self.rates) if self.rates else nan,
            "lr_max": max(self.rates, default=nan),
            "kl": float(self.last_kl) if self.last_kl is not None else nan,
        }


@contextlib.contextmanager
def _critic_only(alg: Any) -> Iterator[None]:
    """Inside the block, PPO's update leaves the actor (its weights and its noise) as it is
    and keeps its learning rate: the actor's parameters take no gradient, and the adaptive
    schedule, which reads the actor's KL divergence (zero here), is off."""
    params = [p for p in alg.actor.parameters() if p.requires_grad]
    schedule = alg.schedule
    for p in params:
        p.requires_grad_(False)
    alg.schedule = "fixed"
    try:
        yield
    finally:
        alg.schedule = schedule
        for p in params:
            p.requires_grad_(True)


class _RunnerMixin:
    """rsl_rl's runner, except for checkpoints: rsl_rl writes ``model_<it>.pt`` with a plain
    ``torch.save`` inside ``learn`` (a crash mid-write leaves a damaged file that looks
    whole) and names it by the iteration in progress. humimic writes them atomically, named
    by iterations done, and loads them with ``weights_only=True``."""

    ranks: Ranks | None = None
    """The process group to train data-parallel with (None: a single process)."""
    # rsl_rl's runner's, which the class this is mixed into has.
    alg: Any
    cfg: dict[str, Any]
    device: str
    current_learning_iteration: int
    gpu_world_size: int
    gpu_local_rank: int
    gpu_global_rank: int
    is_distributed: bool

    critic_warmup = 0
    """Iterations whose updates train the critic alone (:attr:`PpoConfig.critic_warmup_iterations`)."""
    update_stats: dict[str, float] | None = None
    """The last update's :meth:`UpdateProbe.summary` (None before the first)."""

    def learn(self, num_learning_iterations: int, init_at_random_ep_len: bool = False) -> None:
        """rsl_rl's loop; on the CPU, rollouts run torch on one thread and the PPO update
        on all of them (see :func:`torch_threads`). The first :attr:`critic_warmup`
        iterations (counted from the run's start, so a resume after them has none)
        update the critic alone."""
        cpu = torch.device(self.device).type == "cpu"
        full, update = torch.get_num_threads(), self.alg.update
        done = [self.current_learning_iteration]

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            warm = done[0] < self.critic_warmup
            done[0] += 1
            probe = UpdateProbe(self.alg)
            with torch_threads(full) if cpu else contextlib.nullcontext(), probe:
                if not warm:
                    out = update(*args, **kwargs)
                else:
                    with _critic_only(self.alg):
                        out = update(*args, **kwargs)
            self.update_stats = probe.summary()
            return out

        self.alg.update = wrapped
        try:
            with torch_threads(1) if cpu else contextlib.nullcontext():
                return super().learn(num_learning_iterations, init_at_random_ep_len)  # pyright: ignore[reportAttributeAccessIssue]
        finally:
            self.alg.update = update

    def _configure_multi_gpu(self) -> None:
        """rsl_rl's, except that the process group is humimic's (gloo on the CPU, NCCL
        on GPUs; rsl_rl's own allows NCCL alone) and that only ``ranks`` enables it."""
        ranks = self.ranks
        if ranks is None or not ranks.distributed:
            self.gpu_world_size, self.is_distributed = 1, False
            self.gpu_local_rank = self.gpu_global_rank = 0
            self.cfg["multi_gpu"] = None
            return
        self.gpu_world_size, self.is_distributed = ranks.world_size, True
        self.gpu_local_rank, self.gpu_global_rank = ranks.local_rank, ranks.rank
        self.cfg["multi_gpu"] = {
            "global_rank": ranks.rank,
            "local_rank": ranks.local_rank,
            "world_size": ranks.world_size,
        }

    def save(self, path: str, infos: dict | None = None) -> None:
        del path, infos  # Checkpoints are written by save_checkpoint.

    def save_checkpoint(self, path: Path, iterations_done: int) -> None:
        blob = self.alg.save()
        blob["iter"] = iterations_done
        blob["infos"] = None
        with atomic_write(path) as f:
            torch.save(blob, f)

    def load_checkpoint(self, blob: dict[str, Any]) -> None:
        self.alg.load(blob, None, True)
        self.current_learning_iteration = int(blob["iter"])


def make_runner(
    env: Any,
    cfg: dict[str, Any],
    *,
    log_dir: Path | None,
    device: str,
    ranks: Ranks | None = None,
) -> Any:
    """An rsl_rl runner whose checkpoints humimic writes (see :class:`_RunnerMixin`):
    ``OnPolicyRunner`` for PPO, ``DistillationRunner`` for ``Distillation``.

    Args:
        env: The env. cfg: rsl_rl's ``train_cfg``. log_dir: TensorBoard folder, or None.
        device: The learner's device.
        ranks: Train data-parallel with the other ranks of a process group this process has
            joined (:func:`humimic.tracking.distributed.start`). Default: a single process,
            whatever torchrun's variables say.
    """
    from rsl_rl.runners import DistillationRunner, OnPolicyRunner

    distill = cfg["algorithm"]["class_name"] == "Distillation"
    base: type[OnPolicyRunner] = DistillationRunner if distill else OnPolicyRunner
    # The group is known before rsl_rl's __init__ configures it (_configure_multi_gpu).
    runner_class: Any = type("_Runner", (_RunnerMixin, base), {"ranks": ranks})
    with contextlib.redirect_stdout(io.StringIO()):  # rsl_rl prints its networks.
        runner = runner_class(
            env, cfg, log_dir=None if log_dir is None else str(log_dir), device=device
        )
    runner.critic_warmup = int(cfg.get("critic_warmup_iterations", 0))
    return runner
