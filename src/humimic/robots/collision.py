"""The robot's self-collision pairs, derived from its model's own collision geometry."""

from __future__ import annotations

import mujoco
import numpy as np

DEFAULT_POSE_CONTACT = 0.01
"""Pairs closer than this [m] in a default pose (``qpos0`` or a keyframe) touch by design: the
links of one mechanism around its joints (the G1's torso and shoulder-roll links, 9.7 mm apart
standing). It equals the IK's default ``collision_margin``, which such a pair would violate in
every frame."""

MECHANISM_JOINTS = 2
"""Bodies whose relative pose is set by this many joints or fewer are one mechanism (a 2-DoF
hip, a 3-DoF wrist): their coarse collision geoms overlap inside the joint ranges by design
(the G1's pelvis and hip-roll link by 24.5 mm at the hip's roll and pitch limits, its wrist-roll
and wrist-yaw links by 3.7 mm; the T1's trunk and head by 16.7 mm), and the joint ranges, which
the report checks, are what keeps them apart."""


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


def joints_between(model: mujoco.MjModel, body_a: int, body_b: int) -> list[int]:
    """The hinge and slide joints on the kinematic path between two bodies: those that move
    one relative to the other (the floating base's free joint moves both alike)."""
    bodies = tree_path(model, body_a, body_b)
    free = mujoco.mjtJoint.mjJNT_FREE
    return [
        j
        for b in bodies
        for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        if model.jnt_type[j] != free
    ]


def self_collision_pairs(model: mujoco.MjModel, root_body: str) -> np.ndarray:
    """Every pair of the robot's collision geoms that must not interpenetrate.

    All pairs of :func:`robot_geoms` except those MuJoCo never collides whatever the
    contact bitmasks (the same body, a parent and its child, the model's ``<exclude>``
    pairs), the links of one mechanism (at most :data:`MECHANISM_JOINTS` joints between
    them), and those closer than :data:`DEFAULT_POSE_CONTACT` in the model's default pose or
    any of its keyframes (geoms that touch by design). The contact bitmasks are not used:
    models often disable self-collision in simulation, but a wrist inside a hip is a bad
    motion all the same.

    Returns:
        Geom ids, each row ``(a, b)`` with ``a < b``. Shape: (P, 2).
    """
    geoms = robot_geoms(model, root_body)
    parent = model.body_parentid
    excluded = {
        frozenset(divmod(int(sig), 1 << 16)) for sig in model.exclude_signature[: model.nexclude]
    }
    candidates = []
    for i, a in enumerate(geoms):
        ba = int(model.geom_bodyid[a])
        for b in geoms[i + 1 :]:
            bb = int(model.geom_bodyid[b])
            if ba == bb or parent[ba] == bb or parent[bb] == ba:
                continue
            if len(joints_between(model, ba, bb)) <= MECHANISM_JOINTS:
                continue
            if frozenset((ba, bb)) in excluded:
                continue
            candidates.append((a, b))
    if not candidates:
        return np.zeros((0, 2), dtype=int)
    keep = np.ones(len(candidates), dtype=bool)
    data = mujoco.MjData(model)
    fromto = np.zeros(6)
    for key in range(-1, model.nkey):
        if key < 0:
            mujoco.mj_resetData(model, data)
        else:
            mujoco.mj_resetDataKeyframe(model, data, key)
        mujoco.mj_kinematics(model, data)
        for k, (a, b) in enumerate(candidates):
            if keep[k]:
                d = mujoco.mj_geomDistance(model, data, a, b, DEFAULT_POSE_CONTACT, fromto)
                keep[k] = d >= DEFAULT_POSE_CONTACT
    return np.array(candidates, dtype=int)[keep]
