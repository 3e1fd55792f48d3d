"""The bounds of the run settings (``humimic train``, ``distill``, ``eval``, ``export``,
``loop``, ``imitate``) and the checks their ``validate()`` methods share: each names the flag
it refuses."""

from __future__ import annotations

import math

from humimic.errors import InputError

MAX_SEED = 2**32 - 1
"""The largest ``--seed`` (numpy's and torch's generators take any seed up to it)."""


MAX_NUM_ENVS = 65_536
"""The most parallel environments (``--num-envs``, ``--episodes``) one process simulates:
their states are allocated at once, and more than this exhausts a machine's memory."""

GPU_NUM_ENVS = 4096
"""``--num-envs`` by default on a GPU (BeyondMimic's)."""

CPU_NUM_ENVS = 128
"""``--num-envs`` by default on the CPU: enough samples per PPO iteration at the ~6k env steps/s
of a 2-core machine that an iteration takes about a second (BENCHMARKS.md, issue 25)."""


def default_num_envs(device: str) -> int:
    """The default number of parallel envs on ``device`` (:data:`GPU_NUM_ENVS` on a GPU,
    :data:`CPU_NUM_ENVS` on the CPU)."""
    return CPU_NUM_ENVS if device.split(":")[0] == "cpu" else GPU_NUM_ENVS


DEFAULT_ITERATIONS = 1000
"""``--max-iterations`` by default without ``--max-minutes``."""

TIMED_ITERATIONS = 10**9
"""``--max-iterations`` by default with ``--max-minutes``: the time decides."""

MAX_STEPS_PER_ENV = 1000
"""The longest ``--num-steps-per-env`` (the PPO rollout buffer holds every env's steps)."""

MAX_HISTORY = 100
"""The longest ``--task.history-length`` (every env keeps that many observations)."""

MAX_HIDDEN = 8192
"""The widest hidden layer of ``--ppo.actor-hidden-dims`` and ``--ppo.critic-hidden-dims``."""

MAX_EPOCHS = 1000
"""The most ``--ppo.num-learning-epochs`` and ``--ppo.num-mini-batches``."""

MAX_WEIGHT = 1e6
"""The largest ``--task.reward-weights`` magnitude."""


def flag_name(name: str) -> str:
    """The command-line flag of a settings field."""
    return "--" + name.replace("_", "-")


def at_least(s: object, names: tuple[str, ...], minimum: int = 1) -> None:
    """Each named integer field of ``s`` that is set must be ``>= minimum`` (names the flag)."""
    for name in names:
        v = getattr(s, name)
        if v is not None and v < minimum:
            raise InputError(f"{flag_name(name)} {v}: must be at least {minimum}")


def at_most(s: object, limits: dict[str, int]) -> None:
    """Each named integer field of ``s`` that is set must be ``<=`` its limit (names the flag)."""
    for name, limit in limits.items():
        v = getattr(s, name)
        if v is not None and v > limit:
            raise InputError(f"{flag_name(name)} {v}: must be at most {limit}")


def check_seed(seed: int) -> None:
    """``--seed`` within what numpy and torch take."""
    if not 0 <= seed <= MAX_SEED:
        raise InputError(f"--seed {seed}: must be in 0 to {MAX_SEED}")


def check_minutes(minutes: float | None) -> None:
    """``--max-minutes`` unset or a positive number."""
    if minutes is not None and not minutes > 0:  # NaN fails too.
        raise InputError(f"--max-minutes {minutes}: must be a positive number of minutes")


def check_reals(s: object, prefix: str, names: tuple[str, ...], *, positive: bool) -> None:
    """Each named field of ``s`` that is set must be a finite number > 0 (``positive``) or
    >= 0; :class:`InputError` names the flag ``--<prefix>.<field>``."""
    for name in names:
        v = getattr(s, name)
        if v is None:
            continue
        ok = math.isfinite(v) and (v > 0 if positive else v >= 0)
        if not ok:
            what = "a positive number" if positive else "a number >= 0"
            raise InputError(f"--{prefix}.{name.replace('_', '-')} {v}: must be {what}")


def check_device(device: str, flag: str = "--device") -> None:
    """Fail before any work when ``device`` is not a torch device this machine has.

    Accepts ``cpu`` and ``cuda`` (``cuda:N``: an existing GPU). Raises :class:`InputError`
    naming ``flag``.
    """
    import torch

    try:
        d = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise InputError(
            f"{flag} {device!r}: not a torch device (expected cpu, cuda or cuda:N)"
        ) from None
    if d.type == "cpu":
        return
    if d.type != "cuda":
        raise InputError(f"{flag} {device}: humimic runs on cpu or cuda, not {d.type}")
    if not torch.cuda.is_available():
        raise InputError(f"{flag} {device}: CUDA is not available on this machine")
    count = torch.cuda.device_count()
    if d.index is not None and d.index >= count:
        raise InputError(f"{flag} {device}: this machine has {count} CUDA device(s)")
