"""Domain randomization: sample per-env physics parameters at reset and normalize them.

The normalized vector ``e`` (each parameter mapped to [-1, 1] over its range; log space for
scales; 0 where a range is a single value) goes to the critic, so that the value function
knows the physics the actor must cope with (asymmetric actor-critic).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from humimic.tracking.backend import PhysicsParams
from humimic.tracking.config import DomainRandomization


@dataclass(frozen=True, kw_only=True)
class DrSample:
    """Sampled parameters of n envs.

    Attributes:
        physics: What the backend applies.
        joint_offset: Offset of the default joint positions [rad]. Shape: (n, J).
        action_delay: Delay in policy steps. Shape: (n,), int.
    """

    physics: PhysicsParams
    joint_offset: np.ndarray
    action_delay: np.ndarray


def param_dim(num_bodies: int, num_joints: int) -> int:
    """Length of the normalized parameter vector ``e``."""
    return 1 + num_bodies + 3 + 4 * num_joints + 1


def _uniform(
    rng: np.random.Generator, r: tuple[float, float], shape: tuple[int, ...]
) -> np.ndarray:
    return rng.uniform(r[0], r[1], size=shape) if r[0] != r[1] else np.full(shape, float(r[0]))


def _log_uniform(
    rng: np.random.Generator, r: tuple[float, float], shape: tuple[int, ...]
) -> np.ndarray:
    if r[0] == r[1]:
        return np.full(shape, float(r[0]))
    return np.exp(rng.uniform(np.log(r[0]), np.log(r[1]), size=shape))


def sample(
    dr: DomainRandomization,
    n: int,
    *,
    num_bodies: int,
    num_joints: int,
    rng: np.random.Generator,
) -> DrSample:
    """Sample the parameters of ``n`` envs (uniform; log-uniform for scales)."""
    physics = PhysicsParams(
        friction=_uniform(rng, dr.friction, (n,)),
        mass_scale=_log_uniform(rng, dr.mass_scale, (n, num_bodies)),
        com_offset=np.stack([_uniform(rng, r, (n,)) for r in dr.com_offset], axis=-1),
        kp_scale=_log_uniform(rng, dr.kp_scale, (n, num_joints)),
        kd_scale=_log_uniform(rng, dr.kd_scale, (n, num_joints)),
        armature_scale=_log_uniform(rng, dr.armature_scale, (n, num_joints)),
    )
    lo, hi = int(dr.action_delay[0]), int(dr.action_delay[1])
    return DrSample(
        physics=physics,
        joint_offset=_uniform(rng, dr.joint_offset, (n, num_joints)),
        action_delay=rng.integers(lo, hi + 1, size=n),
    )


def _norm(x: np.ndarray, r: tuple[float, float], log: bool = False) -> np.ndarray:
    lo, hi = (np.log(r[0]), np.log(r[1])) if log else (float(r[0]), float(r[1]))
    if hi == lo:
        return np.zeros_like(x, dtype=np.float64)
    v = np.log(x) if log else x
    return (2.0 * v - (lo + hi)) / (hi - lo)


def normalize(dr: DomainRandomization, s: DrSample) -> np.ndarray:
    """The critic's parameter vector ``e`` in [-1, 1]. Shape: (n, :func:`param_dim`)."""
    p = s.physics
    parts = [
        _norm(p.friction, dr.friction)[:, None],
        _norm(p.mass_scale, dr.mass_scale, log=True),
        np.stack([_norm(p.com_offset[:, k], r) for k, r in enumerate(dr.com_offset)], axis=-1),
        _norm(p.kp_scale, dr.kp_scale, log=True),
        _norm(p.kd_scale, dr.kd_scale, log=True),
        _norm(p.armature_scale, dr.armature_scale, log=True),
        _norm(s.joint_offset, dr.joint_offset),
        _norm(
            s.action_delay.astype(np.float64),
            (float(dr.action_delay[0]), float(dr.action_delay[1])),
        )[:, None],
    ]
    return np.concatenate(parts, axis=-1)


class Blocks:
    """Rows of a batched random draw, served in blocks.

    A reset step resets a few envs; drawing for each such step costs dozens of small numpy
    calls whatever the number of envs. ``draw(k)`` returns arrays whose first axis has ``k``
    rows; this calls it for ``block`` rows at a time and hands out consecutive rows: the same
    distribution, independent rows, a fixed sequence for a given generator.
    """

    def __init__(self, draw: Callable[[int], tuple[np.ndarray, ...]], block: int = 256) -> None:
        self._draw, self._block = draw, block
        self._rows: tuple[np.ndarray, ...] = ()
        self._size = self._next = 0

    def take(self, n: int) -> tuple[np.ndarray, ...]:
        """The next ``n`` rows of every array."""
        if self._next + n > self._size:
            self._size, self._next = max(n, self._block), 0
            self._rows = self._draw(self._size)
        rows = slice(self._next, self._next + n)
        self._next += n
        return tuple(a[rows] for a in self._rows)


class SamplePool:
    """Draws of :func:`sample`, with their :func:`normalize` vectors, served in blocks
    (:class:`Blocks`)."""

    def __init__(
        self,
        dr: DomainRandomization,
        *,
        num_bodies: int,
        num_joints: int,
        rng: np.random.Generator,
        block: int = 256,
    ) -> None:
        self._fields = [f.name for f in fields(PhysicsParams)]

        def draw(n: int) -> tuple[np.ndarray, ...]:
            smp = sample(dr, n, num_bodies=num_bodies, num_joints=num_joints, rng=rng)
            physics = [getattr(smp.physics, f) for f in self._fields]
            return (*physics, smp.joint_offset, smp.action_delay, normalize(dr, smp))

        self._blocks = Blocks(draw, block)

    def take(self, n: int) -> tuple[DrSample, np.ndarray]:
        """The next ``n`` envs' parameters and their normalized vectors ``e``."""
        *physics, joint_offset, action_delay, e = self._blocks.take(n)
        params = PhysicsParams(**dict(zip(self._fields, physics, strict=True)))
        return DrSample(physics=params, joint_offset=joint_offset, action_delay=action_delay), e
