"""Which geoms of a body decide its contact with the floor (the ones contact effects change)."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from humimic.errors import InputError


def _planes(m: mujoco.MjModel) -> np.ndarray:
    return np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)


def floor_colliders(m: mujoco.MjModel, body: int) -> np.ndarray:
    """The geoms of ``body`` that touch the floor (they collide with the model's first plane)
    and whose contact parameters decide the floor's contact (a higher MuJoCo priority than
    the plane's, as the G1's feet have; else the two would be mixed). Empty when the body has
    none or the model no plane."""
    planes = _planes(m)
    if planes.size == 0:
        return np.zeros(0, dtype=np.int64)
    f = int(planes[0])
    g = np.flatnonzero(m.geom_bodyid == body)
    touch = (m.geom_contype[g] & m.geom_conaffinity[f]) | (
        m.geom_contype[f] & m.geom_conaffinity[g]
    )
    g = g[touch != 0]
    decides = np.all(m.geom_priority[g] > m.geom_priority[f])
    return g if g.size and decides else g[:0]


def soft_geoms(m: mujoco.MjModel, body: int) -> np.ndarray:
    """:func:`floor_colliders` with a contact time constant (a positive ``solref[0]``, not
    MuJoCo's direct stiffness-damping form). Empty when ``body`` has none."""
    g = floor_colliders(m, body)
    return g if np.all(m.geom_solref[g, 0] > 0) else g[:0]


def spec_geoms(
    spec: mujoco.MjSpec, target: str, select: Callable[[mujoco.MjModel, int], np.ndarray]
) -> list[mujoco.MjsGeom]:
    """The spec geoms of body ``target`` that ``select`` picks on its compiled model.

    Raises:
        InputError: No such body, or it has no such geom.
    """
    b = spec.body(target)
    if b is None:
        raise InputError(f"no body {target!r} in the robot")
    m = spec.copy().compile()
    ids = select(m, m.body(target).id)
    if ids.size == 0:
        raise InputError(
            f"body {target!r} has no geom that decides its contact with the floor (one "
            "colliding with the model's plane, at a higher geom priority than the plane's)"
        )
    names = {m.geom(int(g)).name for g in ids}
    geoms = [g for g in b.geoms if g.name in names] if all(names) else None
    if geoms is None or len(geoms) != ids.size:  # Unnamed geoms: by their order in the body.
        order = np.flatnonzero(m.geom_bodyid == m.body(target).id).tolist()
        geoms = [b.geoms[order.index(int(g))] for g in ids]
    return geoms
