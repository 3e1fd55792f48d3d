"""Interaction meshes and their Laplacian coordinates (pure math: numpy and scipy only):
:func:`build_mesh` makes one frame's :class:`InteractionMesh`; :func:`point_triangle_distance`
measures points against scene triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import Delaunay, QhullError

from humimic.errors import InputError, RetargetError

WEIGHTINGS = ("uniform", "inverse_distance")
MAX_MESH_POINTS = 20_000
"""Most vertices of one frame's mesh (key points and scene points): checked before Qhull runs,
whose memory grows with them."""


def tetra_neighbors(points: np.ndarray) -> list[np.ndarray]:
    """Neighbours of every point in the Delaunay tetrahedralization of ``points``.

    The mesh is the Delaunay tetrahedralization of the points of one frame (scipy, Qhull;
    ``QJ`` joggles degenerate inputs such as coplanar surface samples); neighbours are the
    vertices sharing a tetrahedron edge.

    Args:
        points: Shape: (N, 3), N >= 5.

    Returns:
        One sorted index array per point (the points sharing a tetrahedron edge with it).

    Raises:
        InputError: More than :data:`MAX_MESH_POINTS` points (``--mesh.max_scene_points``).
        RetargetError: Fewer than 5 points, NaN or inf, or Qhull fails even with joggling.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 5:
        raise RetargetError(
            f"an interaction mesh needs at least 5 points in 3D, got {points.shape}"
        )
    if points.shape[0] > MAX_MESH_POINTS:
        raise InputError(
            f"--mesh.max_scene_points: an interaction mesh of {points.shape[0]} points, at "
            f"most {MAX_MESH_POINTS}: lower it"
        )
    if not np.isfinite(points).all():
        raise RetargetError("interaction mesh: the points hold NaN or inf")
    try:
        tri = Delaunay(points, qhull_options="QJ Qbb")
    except QhullError as e:
        raise RetargetError(f"interaction mesh: Delaunay tetrahedralization failed ({e})") from None
    indptr, indices = tri.vertex_neighbor_vertices
    return [np.sort(indices[indptr[i] : indptr[i + 1]]) for i in range(points.shape[0])]


def laplacian_operator(
    points: np.ndarray, neighbors: list[np.ndarray], weighting: str = "uniform"
) -> sp.csr_matrix:
    """``L = I - W`` of the mesh, so that ``delta = L P`` (:class:`InteractionMesh`).

    Weights (a documented choice):

    - ``"uniform"``: ``w_ij = 1 / |N(i)|`` (OmniRetarget's choice);
    - ``"inverse_distance"``: ``w_ij`` proportional to ``1 / |p_i - p_j|`` over the
      neighbours, measured on the points the operator is built from (the human's): near
      neighbours count more.

    Args:
        points: The points the weights are measured on. Shape: (N, 3).
        neighbors: From :func:`tetra_neighbors`; a point without neighbours gets ``L_i = 0``.
        weighting: One of :data:`WEIGHTINGS`.

    Returns:
        Sparse, Shape: (N, N).
    """
    if weighting not in WEIGHTINGS:
        raise RetargetError(f"weighting {weighting!r}: expected one of {', '.join(WEIGHTINGS)}")
    n = len(neighbors)
    rows, cols, vals = [], [], []
    for i, nb in enumerate(neighbors):
        if nb.size == 0:
            continue
        if weighting == "uniform":
            w = np.full(nb.size, 1.0 / nb.size)
        else:
            d = np.linalg.norm(points[nb] - points[i], axis=1)
            w = 1.0 / np.maximum(d, 1e-6)
            w /= w.sum()
        rows += [i] * (nb.size + 1)
        cols += [i, *nb.tolist()]
        vals += [1.0, *(-w).tolist()]
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


def laplacian_coordinates(op: sp.csr_matrix, points: np.ndarray) -> np.ndarray:
    """``delta = L P``. Shapes: (N, N), (N, 3) -> (N, 3)."""
    return np.asarray(op @ np.asarray(points, dtype=np.float64))


@dataclass(frozen=True, kw_only=True)
class InteractionMesh:
    """One frame's mesh over ``K`` body key points (the first rows) and ``S`` scene points.

    An interaction mesh (Ho, Komura and Tai, "Spatial Relationship Preserving Character Motion
    Adaptation", SIGGRAPH 2010; used for humanoid retargeting by OmniRetarget, Yang et al.
    2025) is a volumetric mesh (:func:`tetra_neighbors`) over the body's key points and points
    on the objects and terrain the body interacts with. Each vertex's Laplacian coordinate is
    its offset from a weighted mean of its mesh neighbours (:func:`laplacian_operator`)::

        delta_i = p_i - sum_j w_ij p_j,   sum_j w_ij = 1,

    so ``delta = L P`` with ``L = I - W`` linear in the points. Retargeting keeps the robot's
    Laplacian coordinates close to the human's: a hand that touches a box top keeps its offset
    from the surrounding box points, whatever the change of body size.

    The operator is built once per frame from the source (human and scene) points and then
    held fixed, so the deformation energy ``sum_i c_i |L_i P(q) - delta*_i|^2`` is a linear
    least-squares term in the robot's point positions.

    Attributes:
        op: ``L``, Shape: (K + S, K + S).
        target: The source's Laplacian coordinates ``delta*``. Shape: (K + S, 3).
        scene_points: The robot-side scene points (fixed). Shape: (S, 3).
        num_keypoints: K.
    """

    op: sp.csr_matrix
    target: np.ndarray
    scene_points: np.ndarray
    num_keypoints: int

    @property
    def op_keypoints(self) -> sp.csr_matrix:
        """The columns of ``L`` that multiply the key points. Shape: (K + S, K)."""
        return self.op[:, : self.num_keypoints]

    def residual(self, keypoints: np.ndarray) -> np.ndarray:
        """``L [P_k; P_s] - delta*`` for robot key points ``keypoints`` (K, 3).
        Shape: (K + S, 3)."""
        pts = np.concatenate([np.asarray(keypoints, dtype=np.float64), self.scene_points])
        return laplacian_coordinates(self.op, pts) - self.target

    def energy(self, keypoints: np.ndarray) -> float:
        """``sum_i |residual_i|^2``."""
        return float(np.sum(self.residual(keypoints) ** 2))


def build_mesh(
    source_keypoints: np.ndarray,
    source_scene: np.ndarray,
    robot_scene: np.ndarray | None = None,
    weighting: str = "uniform",
) -> InteractionMesh:
    """The interaction mesh of one frame.

    Args:
        source_keypoints: The (scaled) human's key points. Shape: (K, 3).
        source_scene: Scene points on the human's side. Shape: (S, 3).
        robot_scene: The same scene points on the robot's side (default: the same points;
            they differ when the scene is not mapped with the body). Shape: (S, 3).
        weighting: One of :data:`WEIGHTINGS`.
    """
    src = np.concatenate([source_keypoints, source_scene]).astype(np.float64)
    op = laplacian_operator(src, tetra_neighbors(src), weighting)
    return InteractionMesh(
        op=op,
        target=laplacian_coordinates(op, src),
        scene_points=np.asarray(source_scene if robot_scene is None else robot_scene, float),
        num_keypoints=int(source_keypoints.shape[0]),
    )


__all__ = [
    "MAX_MESH_POINTS",
    "WEIGHTINGS",
    "InteractionMesh",
    "build_mesh",
    "laplacian_coordinates",
    "laplacian_operator",
    "tetra_neighbors",
]


def point_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance from every point to every triangle (closest point on the triangle, after
    Ericson, "Real-Time Collision Detection", 5.1.5).

    Args:
        points: Shape: (N, 3).
        tris: Triangle corners. Shape: (F, 3, 3).

    Returns:
        Shape: (N, F).
    """
    p = np.asarray(points, dtype=np.float64)[:, None, :]  # (N, 1, 3)
    a, b, c = tris[None, :, 0], tris[None, :, 1], tris[None, :, 2]  # (1, F, 3)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        closest = a + v[..., None] * ab + w[..., None] * ac  # Inside the face.
        # Edge and vertex regions, later assignments taking precedence as in Ericson's order.
        t_bc = np.clip((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0, 1)
        on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        closest = np.where(on_bc[..., None], b + t_bc[..., None] * (c - b), closest)
        t_ac = np.clip(d2 / (d2 - d6), 0, 1)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        closest = np.where(on_ac[..., None], a + t_ac[..., None] * ac, closest)
        t_ab = np.clip(d1 / (d1 - d3), 0, 1)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        closest = np.where(on_ab[..., None], a + t_ab[..., None] * ab, closest)
    closest = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, closest)
    closest = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, closest)
    closest = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, closest)
    return np.linalg.norm(p - closest, axis=-1)
