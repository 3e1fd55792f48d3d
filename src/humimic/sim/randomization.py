"""Domain randomization: ranges of physics parameters, their profiles, and per-env draws.

:class:`DomainRandomization` holds the ranges (named profiles or a YAML file); :func:`sample`
draws :class:`~humimic.sim.params.PhysicsParams` for a batch of envs. The normalized vector
``e`` (each parameter mapped to [-1, 1] over its range; log space for scales; 0 where a range
is a single value) goes to the critic (asymmetric actor-critic).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from humimic.errors import InputError, UnknownNameError
from humimic.io import read_yaml
from humimic.sim.params import PhysicsParams

Range = tuple[float, float]


@dataclass(frozen=True, kw_only=True)
class ObservationNoise:
    """Uniform noise half-widths added to the policy observations (mjlab's tracking values).

    Attributes:
        anchor_pos: Reference anchor position in the robot anchor frame [m].
        anchor_ori: Its 6D rotation.
        projected_gravity: Gravity in the base frame.
        base_ang_vel: Base angular velocity [rad/s].
        joint_pos: [rad]. joint_vel: [rad/s].
        base_lin_vel: Base linear velocity [m/s] (the ``base_lin_vel`` group, which only a
            student that reads it sees: a robot estimates it).
    """

    anchor_pos: float = 0.25
    anchor_ori: float = 0.05
    projected_gravity: float = 0.05
    base_ang_vel: float = 0.2
    joint_pos: float = 0.01
    joint_vel: float = 0.5
    base_lin_vel: float = 0.5


@dataclass(frozen=True, kw_only=True)
class DomainRandomization:
    """Per-env physics randomization, sampled at every reset. Ranges are ``(low, high)``.

    Attributes:
        friction: Floor and collider sliding friction (uniform).
        mass_scale: Per-link mass (and inertia) multiplier (log-uniform).
        com_mass_scale: A further multiplier of the anchor body's mass and inertia
            (log-uniform), on top of ``mass_scale``: a payload carried on the torso (1.5:
            half the torso's mass again).
        com_offset: Anchor-body CoM offset per axis x, y, z [m] (uniform).
        kp_scale: Per-joint stiffness multiplier (log-uniform).
        kd_scale: Per-joint damping multiplier (log-uniform).
        armature_scale: Per-joint armature multiplier (log-uniform).
        joint_offset: Per-joint offset of the default joint position, i.e. of the PD targets,
            modelling encoder calibration error [rad] (uniform).
        action_delay: Delay of the actions in policy steps, integers inclusive (uniform).
        push_interval_s: Time between pushes [s]; ``None`` disables pushes.
        push_lin_vel: Base linear velocity change per axis x, y, z [m/s] (world frame).
        push_ang_vel: Base angular velocity change per axis [rad/s] (base frame).
        obs_noise: Policy observation noise; ``None`` disables it.
    """

    friction: Range = (1.0, 1.0)
    mass_scale: Range = (1.0, 1.0)
    com_mass_scale: Range = (1.0, 1.0)
    com_offset: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    kp_scale: Range = (1.0, 1.0)
    kd_scale: Range = (1.0, 1.0)
    armature_scale: Range = (1.0, 1.0)
    joint_offset: Range = (0.0, 0.0)
    action_delay: tuple[int, int] = (0, 0)
    push_interval_s: Range | None = None
    push_lin_vel: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    push_ang_vel: tuple[Range, Range, Range] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    obs_noise: ObservationNoise | None = None

    @property
    def randomizes_model(self) -> bool:
        """Whether any parameter of the physics model varies (needs per-env models)."""
        ranges = [self.friction, self.mass_scale, self.com_mass_scale, *self.com_offset]
        ranges += [self.kp_scale, self.kd_scale, self.armature_scale]
        return any(lo != hi for lo, hi in ranges)

    def validate(self, where: str = "dr") -> None:
        """Check every range; :class:`InputError` names the field."""

        def check(name: str, r: Any, positive: bool = False) -> None:
            ok = isinstance(r, tuple) and len(r) == 2
            ok = ok and all(isinstance(v, int | float) and math.isfinite(v) for v in r)
            if not ok or r[0] > r[1]:
                raise InputError(f"{where}.{name}: expected [low, high] numbers, got {r!r}")
            if positive and r[0] <= 0:
                raise InputError(f"{where}.{name}: scales must be positive, got {r!r}")

        check("friction", self.friction)
        if self.friction[0] < 0:
            raise InputError(f"{where}.friction: must not be negative, got {self.friction!r}")
        for name in ("mass_scale", "com_mass_scale", "kp_scale", "kd_scale", "armature_scale"):
            check(name, getattr(self, name), positive=True)
        check("joint_offset", self.joint_offset)
        check("action_delay", self.action_delay)
        if self.action_delay[0] < 0 or any(int(v) != v for v in self.action_delay):
            raise InputError(f"{where}.action_delay: expected whole policy steps >= 0")
        for name in ("com_offset", "push_lin_vel", "push_ang_vel"):
            axes = getattr(self, name)
            if not (isinstance(axes, tuple) and len(axes) == 3):
                raise InputError(f"{where}.{name}: expected three [low, high] ranges (x, y, z)")
            for axis, r in zip("xyz", axes, strict=True):
                check(f"{name}.{axis}", r)
        if self.push_interval_s is not None:
            check("push_interval_s", self.push_interval_s, positive=True)


def dr_none() -> DomainRandomization:
    """No randomization: nominal physics, no delay, no pushes, no observation noise."""
    return DomainRandomization()


def dr_default() -> DomainRandomization:
    """The default sim-to-real profile.

    mjlab's tracking values where it has them (friction 0.3-1.2, torso CoM offset
    +-0.025/0.05/0.05 m, default joint offset +-0.01 rad, pushes every 1-3 s with its velocity
    ranges, its observation noise); mass, gain and armature scales of +-10 % and 0-1 policy
    steps of action delay are humimic's choice.
    """
    return DomainRandomization(
        friction=(0.3, 1.2),
        mass_scale=(0.9, 1.1),
        com_offset=((-0.025, 0.025), (-0.05, 0.05), (-0.05, 0.05)),
        kp_scale=(0.9, 1.1),
        kd_scale=(0.9, 1.1),
        armature_scale=(0.9, 1.1),
        joint_offset=(-0.01, 0.01),
        action_delay=(0, 1),
        push_interval_s=(1.0, 3.0),
        push_lin_vel=((-0.5, 0.5), (-0.5, 0.5), (-0.2, 0.2)),
        push_ang_vel=((-0.52, 0.52), (-0.52, 0.52), (-0.78, 0.78)),
        obs_noise=ObservationNoise(),
    )


def dr_wide() -> DomainRandomization:
    """``default`` widened to the ranges legged-robot trainers use for a robot that differs
    from its model: a torso payload of -0.8 to +3.1 kg on the G1's 7.8 kg torso (mass x0.9-1.4;
    unitree_rl_gym randomizes the base's mass by -1 to +3 kg), the torso CoM +-5 cm on every
    axis (HOVER: +-10 cm; `default` has +-2.5 cm in x), floor friction down to 0.2 (unitree_rl_gym: 0.1, PBHC: 0.2) and
    0-2 policy steps (0-40 ms) of action delay. Every other range is ``default``'s.
    """
    return replace(
        dr_default(),
        friction=(0.2, 1.2),
        com_mass_scale=(0.9, 1.4),
        com_offset=((-0.05, 0.05), (-0.05, 0.05), (-0.05, 0.05)),
        action_delay=(0, 2),
    )


DR_PROFILES: dict[str, Callable[[], DomainRandomization]] = {
    "none": dr_none,
    "default": dr_default,
    "wide": dr_wide,
}
"""Named domain-randomization profiles: name -> factory."""


def dr_profile(name: str) -> DomainRandomization:
    """A named profile; :class:`UnknownNameError` lists the known ones."""
    try:
        return DR_PROFILES[name]()
    except KeyError:
        raise UnknownNameError(
            f"unknown domain-randomization profile {name!r}; known: {', '.join(DR_PROFILES)}"
        ) from None


def _as_range(value: Any, where: str) -> Any:
    if isinstance(value, list | tuple):
        if value and all(isinstance(v, list | tuple) for v in value):
            return tuple(_as_range(v, where) for v in value)
        return tuple(value)
    raise InputError(f"{where}: expected a [low, high] list, got {value!r}")


def load_dr_profile(path: str | os.PathLike[str]) -> DomainRandomization:
    """Read a domain-randomization profile from YAML.

    The file is a mapping of :class:`DomainRandomization` fields. ``base: <profile>`` starts
    from a named profile (default ``none``); ``obs_noise`` is a mapping of
    :class:`ObservationNoise` fields, ``true`` for the defaults, or ``null``.

    Example::

        base: default
        friction: [0.5, 1.0]
        action_delay: [0, 2]
        obs_noise: {joint_vel: 1.0}

    Raises:
        InputError: Naming the file and the field, for unknown keys and bad values.
    """
    p = Path(path)
    raw = read_yaml(p)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise InputError(f"{p}: expected a mapping of domain-randomization fields")
    raw = dict(raw)
    base_name = raw.pop("base", "none")
    try:
        base = dr_profile(str(base_name))
    except UnknownNameError as e:
        raise InputError(f"{p}: base: {e}") from None
    known = {f.name for f in fields(DomainRandomization)}
    updates: dict[str, Any] = {}
    for key, value in raw.items():
        if key not in known:
            raise InputError(
                f"{p}: unknown field {key!r}; expected one of: base, {', '.join(sorted(known))}"
            )
        where = f"{p}: {key}"
        if key == "obs_noise":
            updates[key] = _obs_noise(value, where)
        elif key == "push_interval_s" and value is None:
            updates[key] = None
        else:
            updates[key] = _as_range(value, where)
    dr = replace(base, **updates)
    dr.validate(where=str(p))
    return dr


def _obs_noise(value: Any, where: str) -> ObservationNoise | None:
    if value is None or value is False:
        return None
    if value is True:
        return ObservationNoise()
    if not isinstance(value, dict):
        raise InputError(f"{where}: expected a mapping, true or null, got {value!r}")
    known = {f.name for f in fields(ObservationNoise)}
    for key, v in value.items():
        if key not in known:
            raise InputError(
                f"{where}: unknown field {key!r}; expected one of: {', '.join(sorted(known))}"
            )
        if not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise InputError(f"{where}.{key}: expected a number >= 0, got {v!r}")
    return ObservationNoise(**{k: float(v) for k, v in value.items()})


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


def param_layout(num_bodies: int, num_joints: int) -> dict[str, slice]:
    """Where each randomized quantity lies in the normalized parameter vector ``e``
    (:func:`normalize`): ``friction``, ``mass_scale`` (one per body), ``com_offset`` (x, y,
    z), ``kp_scale``, ``kd_scale``, ``armature_scale``, ``joint_offset`` (one per joint each)
    and ``action_delay``, in that order."""
    sizes = {"friction": 1, "mass_scale": num_bodies, "com_offset": 3, "kp_scale": num_joints,
             "kd_scale": num_joints, "armature_scale": num_joints, "joint_offset": num_joints,
             "action_delay": 1}  # fmt: skip
    out, start = {}, 0
    for name, size in sizes.items():
        out[name] = slice(start, start + size)
        start += size
    return out


def param_dim(num_bodies: int, num_joints: int) -> int:
    """Length of the normalized parameter vector ``e``."""
    return param_layout(num_bodies, num_joints)["action_delay"].stop


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
    com_column: int = -1,
) -> DrSample:
    """Sample the parameters of ``n`` envs (uniform; log-uniform for scales).

    Args:
        com_column: The anchor body's column of ``mass_scale``
            (:attr:`~humimic.sim.params.ModelLayout.com_column`), which ``com_mass_scale``
            scales further.

    Raises:
        ValueError: ``com_mass_scale`` is not ``(1, 1)`` and no ``com_column`` is given.
    """
    mass_scale = _log_uniform(rng, dr.mass_scale, (n, num_bodies))
    if dr.com_mass_scale != (1.0, 1.0):
        if not 0 <= com_column < num_bodies:
            raise ValueError("com_mass_scale needs the anchor body's column (com_column)")
        mass_scale[:, com_column] *= _log_uniform(rng, dr.com_mass_scale, (n,))
    physics = PhysicsParams(
        friction=_uniform(rng, dr.friction, (n,)),
        mass_scale=mass_scale,
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


def normalize(dr: DomainRandomization, s: DrSample, com_column: int = -1) -> np.ndarray:
    """The critic's parameter vector ``e`` in [-1, 1]. Shape: (n, :func:`param_dim`); its
    layout: :func:`param_layout`. The anchor body's mass (``com_column``) is normalized over
    the product of its two ranges."""
    p = s.physics
    mass = _norm(p.mass_scale, dr.mass_scale, log=True)
    if dr.com_mass_scale != (1.0, 1.0) and 0 <= com_column < mass.shape[1]:
        (lo, hi), (clo, chi) = dr.mass_scale, dr.com_mass_scale
        mass[:, com_column] = _norm(p.mass_scale[:, com_column], (lo * clo, hi * chi), log=True)
    parts = [
        _norm(p.friction, dr.friction)[:, None],
        mass,
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
        com_column: int = -1,
    ) -> None:
        self._fields = [f.name for f in fields(PhysicsParams)]

        def draw(n: int) -> tuple[np.ndarray, ...]:
            smp = sample(dr, n, num_bodies=num_bodies, num_joints=num_joints, rng=rng,
                         com_column=com_column)  # fmt: skip
            physics = [getattr(smp.physics, f) for f in self._fields]
            return (*physics, smp.joint_offset, smp.action_delay,
                    normalize(dr, smp, com_column))  # fmt: skip

        self._blocks = Blocks(draw, block)

    def take(self, n: int) -> tuple[DrSample, np.ndarray]:
        """The next ``n`` envs' parameters and their normalized vectors ``e``."""
        return self.as_sample(self.take_rows(n))

    def take_rows(self, n: int) -> tuple[np.ndarray, ...]:
        """The next ``n`` draws as rows (first axis ``n``) of plain arrays, which
        :class:`FailedDraws` keeps and :meth:`as_sample` turns into parameters."""
        return self._blocks.take(n)

    def as_sample(self, rows: tuple[np.ndarray, ...]) -> tuple[DrSample, np.ndarray]:
        """The parameters of :meth:`take_rows`' rows and their normalized vectors ``e``."""
        *physics, joint_offset, action_delay, e = rows
        params = PhysicsParams(**dict(zip(self._fields, physics, strict=True)))
        return DrSample(physics=params, joint_offset=joint_offset, action_delay=action_delay), e


class FailedDraws:
    """The draws (:meth:`SamplePool.take_rows`) of recently failed episodes, replayed at a
    share of later resets: the domain-randomization analogue of BeyondMimic's adaptive
    start frames, which train more where the policy falls. A failure's draw stays until
    ``capacity`` newer failures have replaced it (a ring).

    Args:
        share: Probability that a reset takes a failed draw instead of a fresh one, while
            any is kept; 0 replays nothing and leaves the fresh draws untouched.
        capacity: Failed draws kept.
        rng: Chooses which resets replay and which draw; its own generator, so that the
            fresh draws' sequence does not depend on the share.
    """

    def __init__(self, share: float, capacity: int, rng: np.random.Generator) -> None:
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"share must be in [0, 1], got {share}")
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.share, self.capacity, self._rng = float(share), int(capacity), rng
        self._rows: list[np.ndarray] = []
        self._size = self._next = 0

    def __len__(self) -> int:
        return self._size

    def record(self, rows: tuple[np.ndarray, ...]) -> None:
        """Keep these draws (rows of a failed episode each)."""
        rows = tuple(a[-self.capacity :] for a in rows)  # Only the newest survive.
        n = len(rows[0])
        if n == 0:
            return
        if not self._rows:
            self._rows = [np.zeros((self.capacity, *a.shape[1:]), a.dtype) for a in rows]
        slots = (self._next + np.arange(n)) % self.capacity
        for buf, a in zip(self._rows, rows, strict=True):
            buf[slots] = a
        self._next = (self._next + n) % self.capacity
        self._size = min(self._size + n, self.capacity)

    def mix(self, rows: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
        """Fresh draws with a ``share`` of them replaced by kept failed draws (new arrays;
        the input is not changed). Without kept draws or share, the input itself."""
        if self.share == 0.0 or self._size == 0:
            return rows
        n = len(rows[0])
        pick = np.flatnonzero(self._rng.random(n) < self.share)
        if pick.size == 0:
            return rows
        src = self._rng.integers(0, self._size, size=pick.size)
        out = tuple(a.copy() for a in rows)
        for o, buf in zip(out, self._rows, strict=True):
            o[pick] = buf[src]
        return out
