"""One in-memory type for a human motion clip, whatever file it came from."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np

from humimic.errors import MotionDataError, UnknownNameError
from humimic.transforms import quat_slerp

MAX_RESAMPLED_FRAMES = 100_000_000
"""Most frames :meth:`HumanClip.resample` makes (over 9 days at 120 fps): a rate or a duration
far out of range would otherwise ask for terabytes."""


@dataclass(frozen=True, kw_only=True)
class HumanClip:
    """Global joint positions (and orientations where known) of a human skeleton over time.

    World frame: z up, metres. Quaternions wxyz.

    Attributes:
        names: Joint names. Shape: (J,).
        parents: Parent index of each joint, -1 for the root. Shape: (J,).
        positions_w: Global joint positions. Shape: (T, J, 3).
        quats_w: Global joint orientations where the source has them, else None. Shape: (T, J, 4).
        fps: Frames per second.
        source: Where the clip came from (a path), for reports and errors.
        skeleton: Name of the skeleton convention (``cmu``, ``holosoma``...), used to pick the
            human-to-robot map.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    positions_w: np.ndarray
    quats_w: np.ndarray | None = None
    fps: float
    source: str = "<memory>"
    skeleton: str = "unknown"
    meta: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_positions(self.positions_w, len(self.names), self.source)
        if len(self.parents) != len(self.names):
            raise MotionDataError(
                f"{self.source}: {len(self.parents)} parents for {len(self.names)} joints"
            )
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise MotionDataError(f"{self.source}: fps must be a positive number, got {self.fps}")
        if not np.isfinite(self.duration):  # A tiny fps such as 1e-320.
            raise MotionDataError(
                f"{self.source}: fps {self.fps:g} is too small: {self.num_frames} frames last "
                "longer than a float can hold"
            )
        if self.quats_w is not None:
            if self.quats_w.shape != (*self.positions_w.shape[:2], 4):
                raise MotionDataError(
                    f"{self.source}: quats_w has shape {self.quats_w.shape}, expected "
                    f"{(*self.positions_w.shape[:2], 4)}"
                )
            if not np.all(np.isfinite(self.quats_w)):
                raise MotionDataError(f"{self.source}: orientations contain NaN or inf")

    @property
    def num_frames(self) -> int:
        return int(self.positions_w.shape[0])

    @property
    def duration(self) -> float:
        """Seconds between the first and the last frame."""
        return (self.num_frames - 1) / self.fps

    def num_frames_at(self, fps: float) -> int:
        """Frames :meth:`resample` gives at ``fps``."""
        if abs(fps - self.fps) < 1e-9 or self.num_frames == 1:
            return self.num_frames
        return int(np.floor(self.duration * fps + 1e-9)) + 1

    def index(self, name: str) -> int:
        """Index of a joint by name; :class:`UnknownNameError` lists the known names."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownNameError(
                f"{self.source}: no joint named {name!r}; the clip has: {', '.join(self.names)}"
            ) from None

    def position(self, name: str) -> np.ndarray:
        """Trajectory of one joint. Shape: (T, 3)."""
        return self.positions_w[:, self.index(name)]

    def slice(self, start: int, stop: int | None = None) -> HumanClip:
        """Frames ``start:stop``; ``meta["start_frame"]`` keeps the first frame's source index."""
        sl = slice(start, stop)
        q = None if self.quats_w is None else self.quats_w[sl]
        first = range(self.num_frames)[sl].start
        meta = {**self.meta, "start_frame": str(int(self.meta.get("start_frame", 0)) + first)}
        return replace(self, positions_w=self.positions_w[sl], quats_w=q, meta=meta)

    def resample(self, fps: float) -> HumanClip:
        """Resample to ``fps`` over the same duration: linear for positions, slerp for rotations."""
        if fps <= 0 or not np.isfinite(fps):
            raise MotionDataError(f"{self.source}: target fps must be a positive number, got {fps}")
        if abs(fps - self.fps) < 1e-9 or self.num_frames == 1:
            return replace(self, fps=float(fps))
        n = self.num_frames_at(fps)
        if n > MAX_RESAMPLED_FRAMES:
            raise MotionDataError(
                f"{self.source}: resampling {self.duration:g} s to {fps:g} fps gives {n} frames, "
                f"more than {MAX_RESAMPLED_FRAMES}"
            )
        t = np.arange(n) / fps * self.fps  # Fractional source frame indices.
        i0 = np.clip(np.floor(t).astype(int), 0, self.num_frames - 1)
        i1 = np.clip(i0 + 1, 0, self.num_frames - 1)
        a = (t - i0)[:, None, None]
        pos = (1.0 - a) * self.positions_w[i0] + a * self.positions_w[i1]
        quats = None
        if self.quats_w is not None:
            quats = quat_slerp(self.quats_w[i0], self.quats_w[i1], (t - i0)[:, None])
        return replace(self, positions_w=pos, quats_w=quats, fps=float(fps))


def validate_positions(positions: np.ndarray, num_joints: int, source: str) -> None:
    """Check a (T, J, 3) array of positions: shape, frames, finiteness (names the bad frame)."""
    if positions.ndim != 3 or positions.shape[1:] != (num_joints, 3):
        raise MotionDataError(
            f"{source}: positions have shape {positions.shape}, expected (T, {num_joints}, 3)"
        )
    if positions.shape[0] == 0:
        raise MotionDataError(f"{source}: zero frames")
    bad = ~np.isfinite(positions)
    if bad.any():
        t, j, _ = np.argwhere(bad)[0]
        raise MotionDataError(
            f"{source}: NaN or inf at frame {t}, joint index {j} ({int(bad.any(axis=(1, 2)).sum())} "
            "bad frames in all)"
        )


def estimate_height(clip: HumanClip, chains: dict[str, list[str]] | None = None) -> float:
    """Estimate the performer's standing height in metres from bone lengths.

    Sums the median lengths of the bones from the foot to the head along the skeleton tree
    (robust to poses that are never upright, such as running or climbing), then adds a fixed
    allowance for the sole and the top of the head.

    Args:
        clip: The clip.
        chains: Optional explicit chains ``{"leg": [...], "spine": [...]}`` of joint names,
            ordered from the bottom up. By default the longest leg path from a foot to the root
            and from the root to the head are found from the tree, using the joint lowest in
            the first frame as the foot and the highest as the head.

    Returns:
        Height in metres.
    """
    pos = clip.positions_w
    if chains is None:
        first = pos[0]
        foot = int(np.argmin(first[:, 2]))
        head = int(np.argmax(first[:, 2]))
        leg = _path_to_root(clip.parents, foot)
        spine = _path_to_root(clip.parents, head)
        idx_chains = [leg, spine]
    else:
        idx_chains = [[clip.index(n) for n in c] for c in chains.values()]
    total = 0.0
    for chain in idx_chains:
        for a, b in itertools.pairwise(chain):
            total += float(np.median(np.linalg.norm(pos[:, a] - pos[:, b], axis=-1)))
    # The foot joint sits above the sole and the head joint below the crown.
    return total + 0.06 + 0.10


def _path_to_root(parents: tuple[int, ...], j: int) -> list[int]:
    path = [j]
    while parents[path[-1]] >= 0:
        path.append(parents[path[-1]])
    return path
