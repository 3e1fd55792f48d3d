"""Rapid Motor Adaptation: an actor that reads the physics through a latent (``humimic train
--variant rma``) and a student that estimates the latent from its history (``humimic distill
--student rma``)."""

from __future__ import annotations

import copy
from typing import Any

import torch
from tensordict import TensorDict
from torch import nn

from humimic.tracking.rsl import MLP, Distillation, EmpiricalNormalization, MLPModel


def _group_dim(obs: TensorDict, groups: list[str]) -> int:
    return sum(int(obs[g].shape[-1]) for g in groups)


class RmaActor(MLPModel):
    """RMA's phase-1 policy ``a = pi(x, z)``, ``z = mu(e)``: the base policy ``pi`` (an MLP)
    reads the deployable observations ``x`` (normalized) and a latent ``z``, which the
    environment factor encoder ``mu`` (an MLP) computes from the privileged groups ``e`` (the
    ``physics`` group: already in [-1, 1], not normalized). The action depends on ``e`` only
    through ``z``; PPO trains ``pi`` and ``mu`` end to end.

    Kumar, Fu, Pathak and Malik, "RMA: Rapid Motor Adaptation for Legged Robots", RSS 2021.

    Args (besides :class:`~rsl_rl.models.MLPModel`'s, which are the base policy's):
        encoder_groups: The observation groups of ``obs_groups[obs_set]`` that ``mu`` encodes;
            the others are ``x``.
        latent_dim: Size of ``z``.
        encoder_hidden_dims: Hidden layers of ``mu``.
    """

    def __init__(
        self,
        obs: TensorDict,
        obs_groups: dict[str, list[str]],
        obs_set: str,
        output_dim: int,
        hidden_dims: tuple[int, ...] | list[int] = (256, 256, 256),
        activation: str = "elu",
        obs_normalization: bool = False,
        distribution_cfg: dict | None = None,
        *,
        encoder_groups: tuple[str, ...] | list[str],
        latent_dim: int = 8,
        encoder_hidden_dims: tuple[int, ...] | list[int] = (256, 128),
    ) -> None:
        groups = list(obs_groups[obs_set])
        encoded = list(encoder_groups)
        missing = [g for g in encoded if g not in groups]
        if missing or len(encoded) == len(groups):
            raise ValueError(
                f"encoder_groups {encoded}: must be some, not all, of the {obs_set!r} groups "
                f"{groups}"
            )
        self.latent_dim = int(latent_dim)  # _get_latent_dim() reads it inside super().__init__.
        base = {obs_set: [g for g in groups if g not in encoded]}
        super().__init__(obs, base, obs_set, output_dim, hidden_dims, activation,
                         obs_normalization, distribution_cfg)  # fmt: skip
        self.encoder_groups = encoded
        self.encoder = MLP(_group_dim(obs, encoded), self.latent_dim, encoder_hidden_dims,
                           activation)  # fmt: skip

    def _get_latent_dim(self) -> int:
        return self.obs_dim + self.latent_dim

    def encode(self, obs: TensorDict) -> torch.Tensor:
        """``z = mu(e)``. Shape: (batch, latent_dim)."""
        return self.encoder(torch.cat([obs[g] for g in self.encoder_groups], dim=-1))

    def get_latent(
        self, obs: TensorDict, masks: torch.Tensor | None = None, hidden_state: Any = None
    ) -> torch.Tensor:
        """The base policy's input: the normalized ``x`` and ``z``."""
        return torch.cat([super().get_latent(obs, masks, hidden_state), self.encode(obs)], dim=-1)

    def as_jit(self) -> nn.Module:
        raise TypeError("an rma actor reads simulator parameters: distill it (--student rma)")

    def as_onnx(self, verbose: bool) -> nn.Module:
        raise TypeError("an rma actor reads simulator parameters: distill it (--student rma)")


class RmaStudent(MLPModel):
    """RMA's phase-2 policy ``a = pi(x, z_hat)``, ``z_hat = phi(h)``: the teacher's base
    policy ``pi`` and its observation normalizer, copied from an :class:`RmaActor` and frozen
    (:meth:`copy_base`), with the adaptation module ``phi`` (an MLP on the normalized
    deployable groups ``h``, here ``policy`` and ``proprio_history``) in place of the encoder.
    :class:`RmaDistillation` trains ``phi`` alone, on ``|z_hat - mu(e)|^2``.

    Kumar, Fu, Pathak and Malik, "RMA: Rapid Motor Adaptation for Legged Robots", RSS 2021.

    Args (besides :class:`~rsl_rl.models.MLPModel`'s, which are the base policy's and must be
    the teacher's; ``distribution_cfg`` is the student's rollout noise):
        base_groups: The groups ``x`` of the base policy (the teacher's actor's groups less the
            encoded ones); each must be one of the student's.
        latent_dim: Size of ``z`` (the teacher's).
        adapter_hidden_dims: Hidden layers of ``phi``.
        adapter_activation: Activation of ``phi``.
    """

    def __init__(
        self,
        obs: TensorDict,
        obs_groups: dict[str, list[str]],
        obs_set: str,
        output_dim: int,
        hidden_dims: tuple[int, ...] | list[int] = (256, 256, 256),
        activation: str = "elu",
        obs_normalization: bool = False,
        distribution_cfg: dict | None = None,
        *,
        base_groups: tuple[str, ...] | list[str],
        latent_dim: int = 8,
        adapter_hidden_dims: tuple[int, ...] | list[int] = (512, 256, 128),
        adapter_activation: str = "elu",
    ) -> None:
        groups = list(obs_groups[obs_set])
        base = list(base_groups)
        if not base or any(g not in groups for g in base):
            raise ValueError(f"base_groups {base}: must be some of the {obs_set!r} groups {groups}")
        self.latent_dim = int(latent_dim)  # _get_latent_dim() reads it inside super().__init__.
        super().__init__(obs, {obs_set: base}, obs_set, output_dim, hidden_dims, activation,
                         obs_normalization, distribution_cfg)  # fmt: skip
        self.adapter_groups = groups
        dim = self.adapter_dim = _group_dim(obs, groups)
        # Where each base group lies in the adaptation module's input (ONNX: one input).
        starts = [_group_dim(obs, groups[:i]) for i in range(len(groups))]
        self.base_slices = [
            (starts[groups.index(g)], starts[groups.index(g)] + int(obs[g].shape[-1])) for g in base
        ]
        self.adapter_normalizer: nn.Module = (
            EmpiricalNormalization(dim) if obs_normalization else nn.Identity()
        )
        self.adapter = MLP(dim, self.latent_dim, adapter_hidden_dims, adapter_activation)
        for p in self.base_parameters():
            p.requires_grad_(False)

    def _get_latent_dim(self) -> int:
        return self.obs_dim + self.latent_dim

    def base_parameters(self) -> list[nn.Parameter]:
        """The frozen parameters: the base policy's and the rollout noise's."""
        modules = [self.mlp] + ([self.distribution] if self.distribution is not None else [])
        return [p for m in modules for p in m.parameters()]

    def copy_base(self, teacher: RmaActor) -> None:
        """Make the base policy and its observation normalizer the teacher's, exactly."""
        with torch.no_grad():
            self.mlp.load_state_dict(teacher.mlp.state_dict())
            self.obs_normalizer.load_state_dict(teacher.obs_normalizer.state_dict())

    def adapt(self, obs: TensorDict) -> torch.Tensor:
        """``z_hat = phi(h)``. Shape: (batch, latent_dim)."""
        h = torch.cat([obs[g] for g in self.adapter_groups], dim=-1)
        return self.adapter(self.adapter_normalizer(h))

    def get_latent(
        self, obs: TensorDict, masks: torch.Tensor | None = None, hidden_state: Any = None
    ) -> torch.Tensor:
        """The base policy's input: the normalized ``x`` and ``z_hat``."""
        return torch.cat([super().get_latent(obs, masks, hidden_state), self.adapt(obs)], dim=-1)

    def update_normalization(self, obs: TensorDict) -> None:
        """Update the adaptation module's statistics; the base's stay the teacher's."""
        if isinstance(self.adapter_normalizer, EmpiricalNormalization):
            h = torch.cat([obs[g] for g in self.adapter_groups], dim=-1)
            self.adapter_normalizer.update(h)

    def as_jit(self) -> nn.Module:
        raise NotImplementedError("export an rma student with as_onnx")

    def as_onnx(self, verbose: bool) -> nn.Module:
        return _OnnxRmaStudent(self)


class _OnnxRmaStudent(nn.Module):
    """The deterministic path of an :class:`RmaStudent` on one input ``obs``: its groups
    concatenated in the order of ``obs_groups`` (Shape: (batch, D)); output ``actions``."""

    is_recurrent: bool = False

    def __init__(self, model: RmaStudent) -> None:
        super().__init__()
        self.adapter_normalizer = copy.deepcopy(model.adapter_normalizer)
        self.adapter = copy.deepcopy(model.adapter)
        self.obs_normalizer = copy.deepcopy(model.obs_normalizer)
        self.mlp = copy.deepcopy(model.mlp)
        dist = model.distribution
        self.deterministic_output = (
            dist.as_deterministic_output_module() if dist is not None else nn.Identity()
        )
        self.input_size = model.adapter_dim
        self.base_slices = list(model.base_slices)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.adapter(self.adapter_normalizer(x))
        base = torch.cat([x[:, a:b] for a, b in self.base_slices], dim=-1)
        out = self.mlp(torch.cat([self.obs_normalizer(base), z], dim=-1))
        return self.deterministic_output(out)

    def get_dummy_inputs(self) -> tuple[torch.Tensor]:
        return (torch.zeros(1, self.input_size),)

    @property
    def input_names(self) -> list[str]:
        return ["obs"]

    @property
    def output_names(self) -> list[str]:
        return ["actions"]


class RmaDistillation(Distillation):
    """DAgger for an :class:`RmaStudent` under an :class:`RmaActor` teacher (RMA's phase 2,
    with rsl_rl's ``Distillation``): the student acts with ``pi(x, phi(h))`` in the env and,
    on every state it visits, ``phi`` regresses onto the teacher's ``z = mu(e)`` (``loss_type``;
    RMA's is MSE). Only ``phi`` (and its normalizer) learns; ``pi`` stays the teacher's.

    Losses: ``latent``, the regression's (what the optimizer minimizes), and ``behavior``, the
    student's actions' MSE from the teacher's (a diagnostic, not trained on).
    """

    def __init__(self, student: RmaStudent, teacher: RmaActor, storage: Any, **kwargs: Any) -> None:
        super().__init__(student, teacher, storage, **kwargs)
        trainable = [p for p in student.parameters() if p.requires_grad]
        self.optimizer = type(self.optimizer)(trainable, **self.optimizer.defaults)

    def update(self) -> dict[str, float]:
        self.num_updates += 1
        student, teacher = self._models()
        latent_sum = behavior_sum = 0.0
        loss: torch.Tensor | float = 0.0
        cnt = 0
        for _ in range(self.num_learning_epochs):
            for batch in self.storage.generator():
                obs = batch.observations
                with torch.no_grad():
                    z = teacher.encode(obs)
                z_hat = student.adapt(obs)
                latent = self.loss_fn(z_hat, z)
                loss = loss + latent
                latent_sum += latent.item()
                with torch.no_grad():
                    assert batch.privileged_actions is not None
                    behavior = nn.functional.mse_loss(student(obs), batch.privileged_actions)
                behavior_sum += behavior.item()
                cnt += 1
                if cnt % self.gradient_length == 0:
                    assert isinstance(loss, torch.Tensor)
                    self.optimizer.zero_grad()
                    loss.backward()
                    if self.is_multi_gpu:
                        self.reduce_parameters()
                    if self.max_grad_norm:
                        params = [p for p in student.parameters() if p.requires_grad]
                        nn.utils.clip_grad_norm_(params, self.max_grad_norm)
                    self.optimizer.step()
                    loss = 0.0
        student.update_normalization(self.storage.observations.flatten(0, 1))
        self.storage.clear()
        return {"latent": latent_sum / cnt, "behavior": behavior_sum / cnt}

    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        """rsl_rl's; a PPO checkpoint (an rma run's: ``actor_state_dict``) loads the teacher
        and gives the student its base policy (:meth:`RmaStudent.copy_base`)."""
        out = super().load(loaded_dict, load_cfg, strict)
        if load_cfg is None and "actor_state_dict" in loaded_dict:
            student, teacher = self._models()
            student.copy_base(teacher)
        return out

    def _models(self) -> tuple[RmaStudent, RmaActor]:
        student, teacher = self._raw_student, self._raw_teacher
        assert isinstance(student, RmaStudent) and isinstance(teacher, RmaActor)
        return student, teacher


__all__ = ["RmaActor", "RmaDistillation", "RmaStudent"]
