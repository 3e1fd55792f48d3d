"""Several processes training one policy: ``torchrun --nproc-per-node N humimic train ...``.
:class:`Ranks` says where a process stands, :func:`start` / :func:`stop` join and leave the
process group, :func:`agree` takes decisions all ranks share.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as torch_dist

from humimic.errors import InputError


@dataclass(frozen=True)
class Ranks:
    """Where this process stands among the processes of a run (torchrun's variables).

    Each process (rank) simulates its own ``--num-envs`` envs on its own device (``cuda:<local
    rank>`` for ``--device cuda``, the CPU for ``--device cpu``) with its own seed (``seed +
    rank``), and rsl_rl averages the gradients over the ranks (``torch.distributed``: NCCL on
    GPUs, gloo on the CPU) after broadcasting rank 0's initial weights. Rank 0 alone
    (:attr:`main`) writes the run folder (config, progress, checkpoints) and shows progress;
    stop decisions (time budget, divergence) are agreed by all ranks (:func:`agree`) so none is
    left waiting in a collective.

    Attributes:
        rank: Global rank (``RANK``). local_rank: Rank on this machine (``LOCAL_RANK``).
        world_size: Number of processes (``WORLD_SIZE``).
    """

    rank: int = 0
    local_rank: int = 0
    world_size: int = 1

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def main(self) -> bool:
        """Whether this process writes the run folder (rank 0)."""
        return self.rank == 0

    @classmethod
    def from_env(cls) -> Ranks:
        """The ranks torchrun set; a single process without it.

        Raises:
            InputError: If the variables are malformed.
        """
        try:
            world = int(os.environ.get("WORLD_SIZE", "1"))
            if world <= 1:
                return cls()
            return cls(int(os.environ["RANK"]), int(os.environ["LOCAL_RANK"]), world)
        except (KeyError, ValueError) as e:
            raise InputError(
                f"WORLD_SIZE is set but RANK / LOCAL_RANK are missing or malformed ({e}): "
                "start several processes with torchrun"
            ) from None


def start(ranks: Ranks, device: str) -> str:
    """Join the process group (if not joined yet) and return this rank's torch device.

    Args:
        ranks: This process's ranks (``ranks.distributed``).
        device: The run's ``--device``: ``cpu`` (gloo), or ``cuda`` (NCCL; each rank takes the
            GPU of its local rank).

    Raises:
        InputError: If a rank has no GPU of its own.
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        count = torch.cuda.device_count()
        if ranks.local_rank >= count:
            raise InputError(
                f"rank {ranks.rank}: local rank {ranks.local_rank} but this machine has {count} "
                "GPU(s): start at most one process per GPU"
            )
        device = f"cuda:{ranks.local_rank}"
        torch.cuda.set_device(device)
    elif dev.type != "cpu":
        raise InputError(f"--device {device}: distributed training runs on 'cuda' or 'cpu'")
    if not torch_dist.is_initialized():
        torch_dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo")
    return device


def stop() -> None:
    """Leave the process group (if joined)."""
    if torch_dist.is_initialized():
        torch_dist.destroy_process_group()


def agree(codes: list[int], device: str | torch.device) -> list[int]:
    """Element-wise maximum of integer codes over all ranks (identity in a single process):
    every rank then takes the same decision."""
    if not torch_dist.is_initialized():
        return codes
    t = torch.tensor(codes, dtype=torch.int64, device=device)
    torch_dist.all_reduce(t, op=torch_dist.ReduceOp.MAX)
    return [int(v) for v in t.tolist()]


def parameter_spread(params: list[torch.Tensor]) -> float:
    """Largest difference between this rank's parameters and rank 0's, over all ranks (0.0 in
    a single process). Data-parallel training keeps it exactly 0; anything else means the
    ranks' policies have drifted apart."""
    if not torch_dist.is_initialized():
        return 0.0
    flat = torch.cat([p.detach().flatten() for p in params])
    ref = flat.clone()
    torch_dist.broadcast(ref, src=0)
    spread = (flat - ref).abs().max().reshape(1)
    torch_dist.all_reduce(spread, op=torch_dist.ReduceOp.MAX)
    return float(spread.item())


__all__ = ["Ranks", "agree", "parameter_spread", "start", "stop"]
