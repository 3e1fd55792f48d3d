"""Foot contact detection on human key-point trajectories. Pure numpy."""

from __future__ import annotations

import numpy as np


def detect_contacts(
    heights: np.ndarray,
    xy: np.ndarray,
    fps: float,
    *,
    max_height: float,
    max_speed: float,
    min_frames: int = 2,
) -> np.ndarray:
    """Frames in which a point rests on the ground: low and (horizontally) slow.

    Args:
        heights: Height of the point above the ground [m]. Shape: (T,).
        xy: Horizontal position [m]. Shape: (T, 2).
        fps: Frames per second.
        max_height: Contact needs a height below this.
        max_speed: ...and a horizontal speed below this [m/s].
        min_frames: Runs shorter than this are dropped; gaps of one frame inside a contact are
            filled.

    Returns:
        Contact flags. Shape: (T,), dtype bool.
    """
    n = heights.shape[0]
    if n < 2:
        return heights < max_height
    speed = np.linalg.norm(np.gradient(xy, axis=0), axis=-1) * fps
    c = (heights < max_height) & (speed < max_speed)
    # Fill one-frame holes, then drop short runs.
    hole = ~c[1:-1] & c[:-2] & c[2:]
    c[1:-1] |= hole
    for start, stop in runs(c):
        if stop - start < min_frames:
            c[start:stop] = False
    return c


def step_speed(xy: np.ndarray, fps: float) -> np.ndarray:
    """Speed of points from the previous frame to each frame, 0 at frame 0.

    Args:
        xy: Positions (horizontal ones for a horizontal speed). Shape: (T, ..., D).
        fps: Frames per second.

    Returns:
        Speeds. Shape: (T, ...).
    """
    v = np.zeros(xy.shape[:-1])
    v[1:] = np.linalg.norm(np.diff(xy, axis=0), axis=-1) * fps
    return v


def runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` index pairs of the runs of True in a boolean array."""
    f = np.concatenate([[False], np.asarray(flags, dtype=bool), [False]])
    d = np.diff(f.astype(np.int8))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def plant_segments(flags: np.ndarray, xy: np.ndarray, radius: float) -> list[tuple[int, int]]:
    """Split contact runs into plants: a plant ends where the point drifts further than
    ``radius`` from where it landed, and a new one starts there.

    Args:
        flags: Contact flags. Shape: (T,).
        xy: Horizontal positions. Shape: (T, 2).
        radius: Largest drift inside one plant [m].

    Returns:
        ``[start, stop)`` index pairs.
    """
    out: list[tuple[int, int]] = []
    for start, stop in runs(flags):
        anchor = start
        for t in range(start + 1, stop):
            if np.linalg.norm(xy[t] - xy[anchor]) > radius:
                out.append((anchor, t))
                anchor = t
        out.append((anchor, stop))
    return out
