"""The robot's self-collision pairs, derived from its model's own collision geometry."""

from __future__ import annotations

import mujoco
import numpy as np

MECHANISM_JOINTS = 2
"""Bodies whose relative pose is set by this many joints or fewer are one mechanism (a 2-DoF
hip, a wrist): their coarse collision geoms pass close to each other around the joints by
design (the G1's pelvis and hip-roll links could overlap by 24 mm within the hip's ranges)."""
MECHANISM_FLOOR = 0.003
"""The distance [m] a mechanism's pair may come down to (its rest distance where that is
smaller), rather than the IK's margin: a 10 mm margin there cut the hips' range so far that
the IK's limits conflicted in 100-170 QPs per climbing clip; 3 mm leaves none and keeps every
pair above the report's 1 mm (0 mm let 1.3 mm through in 7 frames). Chosen on the three
shared climbing clips; the CMU clips were not used for it."""


def robot_geoms(model: mujoco.MjModel, root_body: str) -> list[int]:
    """Collision geoms of the robot: on a body in ``root_body``'s tree, with a contact type or
    affinity (the floor, scene objects and visual-only geoms are left out)."""
    root = model.body(root_body).id
    return [
        g
        for g in range(model.ngeom)
        if model.body_rootid[model.geom_bodyid[g]] == root
        and (model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0)
    ]


def tree_path(model: mujoco.MjModel, body_a: int, body_b: int) -> list[int]:
    """The bodies on the kinematic tree's path between two bodies, their common ancestor left
    out: as many as there are edges between them."""

    def chain(b: int) -> list[int]:
        out = [b]
        while b != 0:
            b = int(model.body_parentid[b])
            out.append(b)
        return out

    ca, cb = chain(body_a), chain(body_b)
    common = next(b for b in ca if b in cb)
    return ca[: ca.index(common)] + cb[: cb.index(common)]


def self_collision_pairs(model: mujoco.MjModel, root_body: str) -> np.ndarray:
    """Every pair of the robot's collision geoms that MuJoCo's contact filter would test.

    All pairs of :func:`robot_geoms` except those MuJoCo never collides whatever the contact
    bitmasks: geoms of one body (or of bodies welded together), of a body and its parent (by
    their weld bodies, MuJoCo's ``filterparent``), and the model's ``<exclude>`` pairs. No
    pair is exempt for being close at rest or inside one mechanism: those are the pairs that
    collide in motion (:func:`self_collision_floors` gives each its floor instead). The contact
    bitmasks are not used: models often disable self-collision in simulation, but a wrist
    inside a hip is a bad motion all the same.

    Returns:
        Geom ids, each row ``(a, b)`` with ``a < b``. Shape: (P, 2).
    """
    geoms = robot_geoms(model, root_body)
    weld, parent = model.body_weldid, model.body_parentid
    excluded = {
        frozenset(divmod(int(sig), 1 << 16)) for sig in model.exclude_signature[: model.nexclude]
    }
    pairs = []
    for i, a in enumerate(geoms):
        ba = int(model.geom_bodyid[a])
        wa = int(weld[ba])
        for b in geoms[i + 1 :]:
            bb = int(model.geom_bodyid[b])
            wb = int(weld[bb])
            if wa == wb or wa == weld[parent[wb]] or wb == weld[parent[wa]]:
                continue
            if frozenset((ba, bb)) in excluded:
                continue
            pairs.append((a, b))
    return np.array(pairs, dtype=int).reshape(-1, 2)


def rest_distances(model: mujoco.MjModel, pairs: np.ndarray, cap: float) -> np.ndarray:
    """Each pair's smallest distance [m] over the model's rest poses (``qpos0`` and its
    keyframes), at most ``cap``: negative where the pair overlaps at rest.

    Args:
        model: The model.
        pairs: Geom-id pairs. Shape: (P, 2).
        cap: Distances beyond it are reported as ``cap`` (what callers care about).

    Returns:
        Shape: (P,).
    """
    data = mujoco.MjData(model)
    fromto = np.zeros(6)
    out = np.full(len(pairs), cap, dtype=float)
    for key in range(-1, model.nkey):
        if key < 0:
            mujoco.mj_resetData(model, data)
        else:
            mujoco.mj_resetDataKeyframe(model, data, key)
        mujoco.mj_kinematics(model, data)
        for k, (a, b) in enumerate(pairs):
            d = mujoco.mj_geomDistance(model, data, int(a), int(b), cap, fromto)
            out[k] = min(out[k], d)
    return out


def joints_between(model: mujoco.MjModel, body_a: int, body_b: int) -> int:
    """How many hinge and slide joints lie on the kinematic path between two bodies (the
    floating base's free joint moves both alike)."""
    free = mujoco.mjtJoint.mjJNT_FREE
    return sum(
        1
        for b in tree_path(model, body_a, body_b)
        for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        if model.jnt_type[j] != free
    )


def self_collision_floors(model: mujoco.MjModel, pairs: np.ndarray, margin: float) -> np.ndarray:
    """The distance [m] each pair may come down to in the IK: ``margin``, or
    :data:`MECHANISM_FLOOR` for the links of one mechanism (at most :data:`MECHANISM_JOINTS`
    joints apart), or the pair's distance at rest where that is smaller (it may not come
    closer than it is at rest). Shape: (P,)."""
    rest = rest_distances(model, pairs, margin)
    mechanism = np.array(
        [joints_between(model, int(model.geom_bodyid[a]), int(model.geom_bodyid[b]))
         <= MECHANISM_JOINTS for a, b in np.asarray(pairs, dtype=int).reshape(-1, 2)],
        dtype=bool,
    )  # fmt: skip
    return np.minimum(rest, np.where(mechanism, min(MECHANISM_FLOOR, margin), margin))
