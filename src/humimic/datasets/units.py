"""File units to metres, shared by the readers of human motion (BVH, FBX, joint positions):
:func:`metres_per_unit` for a unit given by name or factor, :func:`auto_units` to find one from
a skeleton's rest pose.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from humimic.errors import InputError

UNIT_FACTORS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254}
"""Metres per file unit for the named units, in the order ``units="auto"`` tries them."""

AUTO_HEIGHT_RANGE_M: tuple[float, float] = (1.0, 2.3)
"""A rest-pose height (metres) in this range accepts a named unit under ``units="auto"``."""

AUTO_LEG_LENGTH_M = 0.9
"""Leg length (metres) the skeleton is scaled to when no named unit gives a plausible height."""


def metres_per_unit(units: str | float, where: object = None) -> float:
    """Metres per file unit for a unit name or an explicit positive factor.

    Args:
        units: A key of :data:`UNIT_FACTORS` or a positive finite number (metres per file unit).
        where: The file the units are for; its path prefixes the error message.

    Returns:
        The factor.

    Raises:
        InputError: Unknown unit name or a factor that is not a positive finite number.
    """
    prefix = "" if where is None else f"{where}: "
    if isinstance(units, str):
        if units not in UNIT_FACTORS:
            raise InputError(
                f"{prefix}unknown units {units!r}; expected one of {', '.join(UNIT_FACTORS)} or a "
                "positive number of metres per file unit"
            )
        return UNIT_FACTORS[units]
    try:
        factor = float(units)
    except (TypeError, ValueError, OverflowError):
        factor = math.nan
    if not math.isfinite(factor) or factor <= 0:
        raise InputError(
            f"{prefix}units must be a positive number of metres per file unit, got {units!r}"
        )
    return factor


def rest_leg_length(rest: np.ndarray, parents: tuple[int, ...]) -> float:
    """Leg length of a rest pose: the height of the root above the lowest joint below it.

    Walks from each lowest joint (ties within 1e-6 of the range) up to the root and sums the
    vertical (z) extent of each bone on the way, keeping the longest such path. For a leg that
    hangs straight down this is the sum of its bone lengths; horizontal bones (a foot pointing
    forward, an ``End Site`` past the toes) add nothing, so they do not shrink the scale.

    Args:
        rest: Rest-pose joint positions, z up. Shape: (J, 3).
        parents: Parent index per joint, -1 for roots. Shape: (J,).

    Returns:
        The leg length in the units of ``rest``.
    """
    z = rest[:, 2]
    tol = 1e-6 * max(float(z.max() - z.min()), 1e-12)
    best = 0.0
    for j in np.flatnonzero(z <= z.min() + tol):
        length, k = 0.0, int(j)
        while parents[k] >= 0:
            length += abs(float(z[k] - z[parents[k]]))
            k = parents[k]
        best = max(best, length)
    return best


def auto_units(
    path: Path, rest: np.ndarray, parents: tuple[int, ...], rest_height: float
) -> tuple[float, str]:
    """Metres per file unit for ``units="auto"``, and how it was found (for a clip's
    ``meta["units"]``): the first of :data:`UNIT_FACTORS` that makes the rest-pose height
    (z up, ``rest_height`` file units) a person's (:data:`AUTO_HEIGHT_RANGE_M`), else the
    factor that makes the leg (:func:`rest_leg_length`) :data:`AUTO_LEG_LENGTH_M` long.

    Raises:
        InputError: The rest pose has no height to size it by.
    """
    lo, hi = AUTO_HEIGHT_RANGE_M
    for name, f in UNIT_FACTORS.items():
        if lo <= rest_height * f <= hi:
            return f, f"auto: {name} (rest-pose height {rest_height * f:.3f} m)"
    leg = rest_leg_length(rest, parents)
    # A leg of 1e-320 units is as unusable as none: 0.9 / leg overflows to inf.
    if leg <= 0 or not math.isfinite(AUTO_LEG_LENGTH_M / leg):
        raise InputError(
            f"{path}: units='auto' cannot size this skeleton (its rest pose has no height); "
            "pass units= explicitly"
        )
    f = AUTO_LEG_LENGTH_M / leg
    return f, f"auto: leg scaled to {AUTO_LEG_LENGTH_M} m ({f:.4f} m per unit)"
