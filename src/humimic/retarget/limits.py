"""IK limits in mink's contract (``compute_qp_inequalities``)."""

from __future__ import annotations

from typing import Any

import mink
import mujoco
import numpy as np
from mink.limits.limit import Constraint

CONTACT_HEIGHT = 0.010
"""A foot contact point touches the ground when its lowest point is below this [m]."""


def foot_contact_points(
    model: mujoco.MjModel, bodies: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact points of the collision geoms of the given bodies.

    Spheres give their centre and radius; boxes their eight corners; capsules and cylinders
    the centres of their end caps with their radius.

    Returns:
        body ids (N,), points in the body frame (N, 3), radii (N,).
    """
    ids, pts, rad = [], [], []
    for name in bodies:
        b = model.body(name).id
        for g in range(model.ngeom):
            if model.geom_bodyid[g] != b or (
                model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0
            ):
                continue
            t = int(model.geom_type[g])
            size = model.geom_size[g]
            pos = model.geom_pos[g]
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, model.geom_quat[g])
            rot = rot.reshape(3, 3)
            if t == mujoco.mjtGeom.mjGEOM_SPHERE:
                local, r = [np.zeros(3)], size[0]
            elif t == mujoco.mjtGeom.mjGEOM_BOX:
                signs = np.array(
                    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
                )
                local, r = list(signs * size[:3]), 0.0
            elif t in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
                local, r = [np.array([0, 0, -size[1]]), np.array([0, 0, size[1]])], size[0]
            else:
                continue
            for p in local:
                ids.append(b)
                pts.append(pos + rot @ p)
                rad.append(r)
    if not ids:
        raise ValueError(f"bodies {bodies} have no sphere, box or capsule collision geoms")
    return np.array(ids), np.array(pts), np.array(rad)


def body_points(data: mujoco.MjData, ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """World positions of points given in their bodies' frames (after kinematics).

    Args:
        ids: Body of each point. Shape: (N,).
        pts: Each point in its body's frame. Shape: (N, 3).

    Returns:
        Shape: (N, 3).
    """
    return data.xpos[ids] + np.einsum("nij,nj->ni", data.xmat[ids].reshape(-1, 3, 3), pts)


def contact_point_heights(
    data: mujoco.MjData, ids: np.ndarray, pts: np.ndarray, rad: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World positions of contact points and the heights of their lowest points.

    Returns:
        positions (N, 3), bottom heights (N,).
    """
    world = body_points(data, ids, pts)
    return world, world[:, 2] - rad


def point_jacobians(
    model: mujoco.MjModel, data: mujoco.MjData, ids: np.ndarray, world: np.ndarray
) -> np.ndarray:
    """Translational Jacobians of world points fixed on bodies (after kinematics), ``mj_jac``
    at each point, into one array.

    Args:
        ids: Body of each point. Shape: (N,).
        world: The points' world positions. Shape: (N, 3).

    Returns:
        Shape: (N, 3, nv).
    """
    out = np.empty((len(ids), 3, model.nv))
    for i in range(len(ids)):
        mujoco.mj_jac(model, data, out[i], None, world[i], int(ids[i]))
    return out


def mesh_hull_points(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """A mesh geom's convex-hull vertices in its body's frame (all its vertices where MuJoCo
    kept no hull). Shape: (V, 3)."""
    mesh = int(model.geom_dataid[geom])
    adr, num = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
    verts = model.mesh_vert[adr : adr + num]
    graph = int(model.mesh_graphadr[mesh])
    if graph >= 0:
        nvert = int(model.mesh_graph[graph])
        verts = verts[model.mesh_graph[graph + 2 + nvert : graph + 2 + 2 * nvert]]
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.geom_quat[geom])
    return model.geom_pos[geom] + verts @ rot.reshape(3, 3).T


MESH_FLOOR_BAND = 0.02
"""A foot mesh's hull vertices within this height [m] of its lowest are kept above the floor
at each evaluation: the floor is a plane, so to first order the lowest point after a step is
one of them."""
MESH_FLOOR_POINTS = 32
"""At most this many of them per mesh, the lowest first."""


class FloorLimit(mink.Limit):
    """Keep the feet on or above the floor plane ``z = height``: a hard limit.

    The contact points of :func:`foot_contact_points` (spheres, boxes, capsules), and the
    lowest hull vertices of the feet's collision meshes (an added robot's foot is its mesh
    standing on a sole box: at toe-off the mesh's toe or heel is what reaches the floor).
    Linearized as ``z_i + J_z,i dq >= height`` for every point ``i``, i.e.
    ``-J_z,i dq <= z_i - height``, exact to first order.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        bodies: list[str],
        height: float = 0.0,
    ) -> None:
        self.model = model
        self.height = height
        self.ids, self.pts, self.rad = foot_contact_points(model, bodies)
        wanted = {model.body(name).id for name in bodies}
        self.meshes = [
            (int(model.geom_bodyid[g]), mesh_hull_points(model, g))
            for g in range(model.ngeom)
            if model.geom_bodyid[g] in wanted
            and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
            and (model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0)
        ]

    def points(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points constrained in ``data``'s configuration (after kinematics).

        Returns:
            body ids (N,), world positions (N, 3), bottom heights (N,).
        """
        first, low_first = contact_point_heights(data, self.ids, self.pts, self.rad)
        ids, world, bottom = [self.ids], [first], [low_first]
        for body, hull in self.meshes:
            p = body_points(data, np.full(len(hull), body), hull)
            low = np.argsort(p[:, 2])[:MESH_FLOOR_POINTS]
            low = low[p[low, 2] <= p[low[0], 2] + MESH_FLOOR_BAND]
            ids.append(np.full(len(low), body))
            world.append(p[low])
            bottom.append(p[low, 2])
        return np.concatenate(ids), np.concatenate(world), np.concatenate(bottom)

    def max_depth(self, data: mujoco.MjData) -> float:
        """How far [m] the lowest constrained point is under the floor (negative: above it)."""
        return self.height - float(np.min(self.points(data)[2]))

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float) -> Constraint:
        del dt  # A position limit.
        data = configuration.data
        ids, world, bottom = self.points(data)
        G = -point_jacobians(self.model, data, ids, world)[:, 2]
        return Constraint(G=G, h=bottom - self.height)


class PointTravelLimit(mink.Limit):
    """Keep points of bodies within a horizontal distance of anchors: a hard limit.

    For an active point ``i`` at ``p_i`` with anchor ``a_i`` and radius ``r_i``, the horizontal
    displacement ``d = (p_i + J_i dq - a_i)_xy`` stays inside the regular octagon inscribed in
    the circle of radius ``r_i``: ``n_k . d <= r_i cos(pi / 8)`` for its eight edge normals
    ``n_k``, exact to first order. Points with an infinite radius are free.

    Args:
        model: The model.
        body_ids: The body of each point. Shape: (N,).
        points: Each point in its body's frame. Shape: (N, 3).
    """

    _NORMALS = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], 1)

    def __init__(self, model: mujoco.MjModel, body_ids: np.ndarray, points: np.ndarray) -> None:
        self.model = model
        self.body_ids = np.asarray(body_ids, dtype=int)
        self.points = np.asarray(points, dtype=float).reshape(-1, 3)
        self.anchors = np.zeros((len(self.body_ids), 3))
        self.radius = np.full(len(self.body_ids), np.inf)

    def positions(self, data: mujoco.MjData) -> np.ndarray:
        """World positions of the points in ``data`` (after kinematics). Shape: (N, 3)."""
        return body_points(data, self.body_ids, self.points)

    def set(self, anchors: np.ndarray, radius: np.ndarray) -> None:
        """Anchors (N, 3) [m] and radii (N,) [m]; ``inf`` frees a point."""
        self.anchors = np.asarray(anchors, dtype=float).reshape(len(self.body_ids), 3)
        self.radius = np.asarray(radius, dtype=float).reshape(len(self.body_ids))

    def max_excess(self, data: mujoco.MjData) -> float:
        """Largest horizontal distance of an active point from its anchor, as a fraction of
        its radius beyond it (0 inside; ``-inf`` with no active point)."""
        active = np.isfinite(self.radius)
        if not active.any():
            return -np.inf
        d = np.linalg.norm(self.positions(data)[active, :2] - self.anchors[active, :2], axis=1)
        return float(np.max(d / self.radius[active] - 1.0))

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float) -> Constraint:
        del dt  # A position limit.
        data = configuration.data
        active = np.flatnonzero(np.isfinite(self.radius))
        if not active.size:
            return Constraint()
        world = self.positions(data)[active]
        jac = point_jacobians(self.model, data, self.body_ids[active], world)[:, :2]  # (A,2,nv)
        G = np.einsum("kj,ajv->akv", self._NORMALS, jac).reshape(-1, self.model.nv)
        d = world[:, :2] - self.anchors[active, :2]  # (A, 2)
        h = self.radius[active, None] * np.cos(np.pi / 8) - d @ self._NORMALS.T  # (A, 8)
        return Constraint(G=G, h=h.ravel())


SELF_REPAIR_DEPTH = 5e-4
"""A self-collision pair this much deeper than its overlap at rest [m] is repaired after a
frame's last step: half the 1 mm the report counts."""

SELF_COUNTED_DEPTH = 1e-3
"""How much deeper than its overlap at rest [m] a pair must be for the report to count its
frame as a self-collision frame (:func:`humimic.retarget.metrics.evaluate`)."""


class SelfCollisionLimit(mink.CollisionAvoidanceLimit):
    """mink's collision avoidance on an exact list of geom pairs, each with its own floor,
    changed to also push penetrating pairs apart.

    The pairs are taken as given, in order (mink's own construction drops pairs by their
    contact bitmasks and reorders them): what the IK keeps apart is what the report measures.
    A pair may not come closer than its floor
    (:func:`~humimic.robots.collision.self_collision_floors`).

    mink lets a pair closer than the minimum distance keep its distance (bound 0), so the
    linearization error of successive iterations can accumulate into penetration. Here the
    bound stays ``gain * (d - floor)`` when negative: the QP must restore the floor.
    Called with ``dt = 1`` (displacements), the bound is in metres.

    Args:
        model: The model.
        pairs: Geom-id pairs. Shape: (P, 2).
        floors: Each pair's smallest allowed distance [m]. Shape: (P,).
        gain: As mink's.
        collision_detection_distance: Pairs farther apart than this are not constrained.

    Attributes:
        min_slack: Smallest ``distance - floor`` found by the last evaluation (inf if none
            near).
        counted_depth: Set by :meth:`repair_slack`.
    """

    min_slack: float = np.inf
    counted_depth: float = -np.inf

    def __init__(
        self,
        model: mujoco.MjModel,
        pairs: np.ndarray,
        floors: np.ndarray,
        *,
        gain: float,
        collision_detection_distance: float,
    ) -> None:
        self._given = [(int(a), int(b)) for a, b in np.asarray(pairs, dtype=int).reshape(-1, 2)]
        super().__init__(
            model,
            [([a], [b]) for a, b in self._given],  # type: ignore[arg-type]
            gain=gain,
            minimum_distance_from_collisions=float(np.max(floors, initial=0.0)),
            collision_detection_distance=collision_detection_distance,
        )
        self.floors = np.asarray(floors, dtype=float).reshape(len(self._given))
        g = np.array(self._given, dtype=int).reshape(-1, 2)
        self._g = g
        self._rbound = model.geom_rbound[g]  # (P, 2)

    def _construct_geom_id_pairs(self, geom_pairs: Any) -> list[tuple[int, int]]:
        del geom_pairs  # The given pairs, as given.
        return list(self._given)

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float) -> Constraint:
        model = self.model
        data = configuration.data
        h = np.full((self.max_num_contacts,), np.inf)
        G = np.zeros((self.max_num_contacts, model.nv))
        indices = (
            self._broadphase_survivors(data)
            if self.broadphase and self.max_num_contacts >= 16
            else range(self.max_num_contacts)
        )
        detection = self.collision_detection_distance
        candidates = np.asarray(indices, dtype=int)
        dists, ends = self._distances(data, candidates, detection)
        near = np.abs(dists - detection) >= 1e-12
        active = candidates[near]
        self.min_slack = np.inf
        if active.size:
            # The rows of mink's compute_contact_normal_jacobian, all pairs at once: the
            # normal (from the first witness point to the second) times the difference of the
            # two points' Jacobians.
            d = dists[near]
            ft = ends[near]  # (A, 6)
            bodies = model.geom_bodyid[self._g[active]]  # (A, 2)
            jac1 = point_jacobians(model, data, bodies[:, 0], ft[:, :3])
            jac2 = point_jacobians(model, data, bodies[:, 1], ft[:, 3:])
            normal = ft[:, 3:] - ft[:, :3]
            length = np.linalg.norm(normal, axis=1, keepdims=True)
            # mju_normalize3's answer for a zero vector.
            normal = np.where(length > 1e-15, normal / np.maximum(length, 1e-300), [1.0, 0, 0])
            rows = np.einsum("ak,akv->av", normal, jac2 - jac1)
            # For a penetrating pair the witness normal flips, hence the sign on G.
            G[active] = np.where(d >= 0, -1.0, 1.0)[:, None] * rows
            h[active] = self.gain * (d - self.floors[active]) / dt
            self.min_slack = float(np.min(d - self.floors[active]))
        return Constraint(G=G, h=h)

    def _distances(
        self, data: mujoco.MjData, idx: np.ndarray, distmax: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``mj_geomDistance`` of the pairs ``idx``, each capped at its ``distmax``, and their
        witness points (zeros where capped). Shapes: ``idx`` (K,); returns (K,) and (K, 6)."""
        cap = np.broadcast_to(np.asarray(distmax, dtype=float), idx.shape).tolist()
        dists, ends = np.empty(idx.size), np.zeros((idx.size, 6))
        model, given, distance = self.model, self._given, mujoco.mj_geomDistance
        for k, p in enumerate(idx.tolist()):
            g1, g2 = given[p]
            dists[k] = distance(model, data, g1, g2, cap[k], ends[k])
        return dists, ends

    def repair_slack(self, configuration: mink.Configuration, margin: float) -> float:
        """How far the worst pair is now inside its repair line [m] (negative: repair it;
        ``inf`` when no pair is near it). A pair needs repair when it is more than half the
        margin below its floor, or more than :data:`SELF_REPAIR_DEPTH` deeper than it overlaps at
        rest (under the 1 mm the report counts: a pair overlapping at rest, or one
        mechanism's, has its floor there).

        The final check after a frame's last QP step. Every pair, not only those near at the
        last evaluation: a pair farther than the detection distance there can still meet in
        one step of the trust region (0.3 rad of a hip moves a forearm 10 cm past a thigh).
        Pairs whose bounding spheres are farther apart than their line are skipped.

        Also sets :attr:`counted_depth`: how far the deepest pair is beyond the depth the
        report counts (:data:`SELF_COUNTED_DEPTH` past its overlap at rest; positive: this
        configuration is a self-collision frame; ``-inf`` when no pair is near its line).
        """
        floors = self.floors
        lines = np.maximum(floors - 0.5 * margin, np.minimum(floors, 0.0) - SELF_REPAIR_DEPTH)
        data = configuration.data
        diff = data.geom_xpos[self._g[:, 0]] - data.geom_xpos[self._g[:, 1]]
        reach = np.maximum(self._rbound.sum(axis=1) + lines, 0.0)
        near = np.flatnonzero(np.einsum("ij,ij->i", diff, diff) <= reach * reach)
        d, _ = self._distances(data, near, np.maximum(lines[near], 0.0) + 1e-3)
        counted = np.minimum(floors[near], 0.0) - SELF_COUNTED_DEPTH - d
        self.counted_depth = float(np.max(counted, initial=-np.inf))
        return float(np.min(d - lines[near], initial=np.inf))
