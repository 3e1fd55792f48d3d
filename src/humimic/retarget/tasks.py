"""Stacked IK tasks in mink's task contract (``compute_error``, ``compute_jacobian``).

One task for all key-point positions and one for all body orientations: the same objective as
one ``mink.FrameTask`` per point, with one Python call per iteration instead of dozens. Each
task keeps the error of its last evaluation so the solver loop can stop when the error stops
improving without evaluating it twice.
"""

from __future__ import annotations

import mink
import mujoco
import numpy as np
from mink.limits.collision_avoidance_limit import compute_contact_normal_jacobian

from humimic.retarget.interaction_mesh import InteractionMesh
from humimic.transforms import matrix_to_quat, quat_to_rotvec


def _skew(v: np.ndarray) -> np.ndarray:
    """Batched skew matrices. Shape: (N, 3) -> (N, 3, 3)."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def so3_right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3) at rotation vectors ``phi``. Shape: (N, 3) -> (N, 3, 3)."""
    theta = np.linalg.norm(phi, axis=-1)
    k = _skew(phi)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    coef = np.where(small, 1.0 / 12.0, 1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th)))
    return np.eye(3) + 0.5 * k + coef[:, None, None] * (k @ k)


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices. Shape: (N, 3, 3) -> (N, 3).

    Closed form from the trace and the skew part; near 180 degrees, through quaternions.
    """
    cos = np.clip((r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2] - 1.0) * 0.5, -1.0, 1.0)
    theta = np.arccos(cos)
    w = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
    sin = np.sin(theta)
    scale = np.where(
        theta < 1e-6, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(sin > 0, sin, 1.0))
    )
    out = w * scale[:, None]
    near_pi = theta > np.pi - 1e-3
    if near_pi.any():
        out[near_pi] = quat_to_rotvec(matrix_to_quat(r[near_pi]))
    return out


class KeypointsTask(mink.Task):
    """Positions of many sites: ``e = p_site(q) - p_target``. Error shape: (3K,).

    Attributes:
        targets: Target positions. Shape: (K, 3).
        last_error: Error at the last ``compute_error`` call.
    """

    def __init__(self, model: mujoco.MjModel, sites: list[str]) -> None:
        self.model = model
        self.site_ids = np.array([model.site(s).id for s in sites], dtype=int)
        k = len(sites)
        super().__init__(cost=np.ones(3 * k))
        self.targets = np.zeros((k, 3))
        self.last_error = np.zeros(3 * k)
        self._jac = np.zeros((3 * k, model.nv))

    def set_costs(self, costs: np.ndarray) -> None:
        """Per-site costs [1/m]. Shape: (K,)."""
        self.cost = np.repeat(np.asarray(costs, dtype=np.float64), 3)

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        e = (configuration.data.site_xpos[self.site_ids] - self.targets).ravel()
        self.last_error = e
        return e

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        data = configuration.data
        for i, s in enumerate(self.site_ids):
            mujoco.mj_jacSite(self.model, data, self._jac[3 * i : 3 * i + 3], None, int(s))
        return self._jac.copy()


class OrientationsTask(mink.Task):
    """Orientations of many bodies: ``e = log(R_target^T R_body(q))`` (body frame).

    Error shape: (3B,). The Jacobian is ``Jr^{-1}(e) R^T J_w``, exact for any error size.

    Attributes:
        targets: Target rotation matrices. Shape: (B, 3, 3).
    """

    def __init__(self, model: mujoco.MjModel, bodies: list[str]) -> None:
        self.model = model
        self.body_ids = np.array([model.body(b).id for b in bodies], dtype=int)
        n = len(bodies)
        super().__init__(cost=np.ones(3 * n))
        self.targets = np.tile(np.eye(3), (n, 1, 1))
        self.last_error = np.zeros(3 * n)
        self._jr = np.zeros((n, 3, model.nv))
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def set_costs(self, costs: np.ndarray) -> None:
        """Per-body costs [1/rad]. Shape: (B,)."""
        self.cost = np.repeat(np.asarray(costs, dtype=np.float64), 3)

    def _rotations(self, data: mujoco.MjData) -> np.ndarray:
        return data.xmat[self.body_ids].reshape(-1, 3, 3)

    def _log(self, configuration: mink.Configuration) -> tuple[np.ndarray, np.ndarray]:
        """The bodies' rotations (B, 3, 3) and their errors as rotation vectors (B, 3), kept
        for the configuration and targets they were computed at (the solver asks for the
        error after a step, then for the objective at the same configuration)."""
        q = configuration.data.qpos
        c = self._cache
        if c is not None and np.array_equal(c[0], q) and np.array_equal(c[3], self.targets):
            return c[1], c[2]
        r = self._rotations(configuration.data)
        rel = np.einsum("nji,njk->nik", self.targets, r)
        phi = rotation_log(rel)
        self._cache = (q.copy(), r, phi, np.array(self.targets, dtype=float))
        return r, phi

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        e = self._log(configuration)[1].ravel()
        self.last_error = e
        return e

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        return self._error_and_jacobian(configuration)[1]

    def _error_and_jacobian(
        self, configuration: mink.Configuration
    ) -> tuple[np.ndarray, np.ndarray]:
        data = configuration.data
        r, phi = self._log(configuration)
        jinv = so3_right_jacobian_inverse(phi)
        jr = self._jr
        for i, b in enumerate(self.body_ids):
            mujoco.mj_jacBody(self.model, data, None, jr[i], int(b))
        out = jinv @ (r.transpose(0, 2, 1) @ jr)
        self.last_error = phi.ravel()
        return self.last_error, out.reshape(-1, self.model.nv)

    def compute_qp_objective(self, configuration: mink.Configuration) -> mink.Objective:
        """The objective from one evaluation of the error and the Jacobian (one log each)."""
        e, jac = self._error_and_jacobian(configuration)
        return self._assemble_qp(e, jac, configuration._eye_nv)


class PostureTask(mink.PostureTask):
    """mink's posture task with its objective assembled as what it is, diagonal: the Jacobian
    is the identity with the floating base's columns zeroed, so ``H = diag(w^2)`` and
    ``c = w^2 gain e`` on the joints (the same numbers as mink's dense products, without
    two nv x nv matrix products per call)."""

    def __init__(self, model: mujoco.MjModel, cost: float) -> None:
        super().__init__(model, cost=cost)
        self._mask = np.ones(model.nv)
        if self._v_ids is not None:
            self._mask[self._v_ids] = 0.0

    def compute_qp_objective(self, configuration: mink.Configuration) -> mink.Objective:
        if self.lm_damping > 0.0:
            return super().compute_qp_objective(configuration)
        e = self.compute_error(configuration)  # zero on the floating base
        w = self.cost * self._mask
        return mink.Objective(np.diag(w * w), -(self.cost * (-self.gain * e)) * w)


class InteractionMeshTask(mink.Task):
    """Deformation of an interaction mesh: ``e = L [P_sites(q); P_scene] - delta*``.

    The mesh (:class:`~humimic.retarget.interaction_mesh.InteractionMesh`) holds the operator
    ``L`` built from the human side, the target Laplacian coordinates and the fixed scene
    points; its first ``K`` vertices are this task's sites, in order. Error shape: (3N,) for a
    mesh of N vertices; the Jacobian is ``(L_k kron I_3) J_sites``, exact (``L`` is fixed).
    Set a new mesh every frame with :meth:`set_mesh`.
    """

    def __init__(self, model: mujoco.MjModel, sites: list[str], cost: float = 1.0) -> None:
        self.model = model
        self.site_ids = np.array([model.site(s).id for s in sites], dtype=int)
        super().__init__(cost=np.ones(3))
        self.weight = float(cost)
        self.mesh: InteractionMesh | None = None
        self._op_k = np.zeros((0, len(sites)))
        self._jac = np.zeros((3 * len(sites), model.nv))
        self.last_error = np.zeros(0)

    def set_mesh(self, mesh: InteractionMesh) -> None:
        """The mesh of the frame being solved (its first K vertices are the task's sites)."""
        if mesh.num_keypoints != len(self.site_ids):
            raise ValueError(
                f"the mesh has {mesh.num_keypoints} key points, the task {len(self.site_ids)} sites"
            )
        self.mesh = mesh
        self._op_k = mesh.op_keypoints.toarray()
        self.cost = np.full(3 * mesh.target.shape[0], self.weight)

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        if self.mesh is None:
            raise ValueError("InteractionMeshTask: no mesh set")
        e = self.mesh.residual(configuration.data.site_xpos[self.site_ids]).ravel()
        self.last_error = e
        return e

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        data, nv = configuration.data, self.model.nv
        for i, s in enumerate(self.site_ids):
            mujoco.mj_jacSite(self.model, data, self._jac[3 * i : 3 * i + 3], None, int(s))
        k = len(self.site_ids)
        out = self._op_k @ self._jac.reshape(k, 3 * nv)  # (N, 3 nv)
        return out.reshape(-1, nv)


class SceneContactTask(mink.Task):
    """Bodies onto scene surfaces: ``e_i = d_i(q)``, the signed distance between a body (the
    nearest of its geoms) and a scene object, for each contact the human makes in this frame.

    The Jacobian is the contact normal's (as in mink's collision avoidance), so the task and
    the non-penetration limit act along the same direction: the body is drawn onto the
    surface, the limit keeps it out of the object.
    """

    def __init__(
        self, model: mujoco.MjModel, body_geoms: list[list[int]], cost: float, reach: float = 0.3
    ) -> None:
        self.model = model
        self.body_geoms = body_geoms
        self.weight = float(cost)
        self.reach = float(reach)
        super().__init__(cost=np.ones(1))
        self.pairs: list[tuple[int, int]] = []
        self.gap = 0.0
        self._fromto = np.zeros(6)
        self._normal = np.zeros(3)
        self._jac1 = np.zeros((3, model.nv))
        self._jac2 = np.zeros((3, model.nv))

    def set_contacts(
        self, pairs: list[tuple[int, int]], firmness: np.ndarray | None = None
    ) -> None:
        """(body index into ``body_geoms``, scene geom id) of each contact to keep, and how
        firmly each holds (a factor on the cost, default 1)."""
        self.pairs = list(pairs)
        f = np.ones(len(self.pairs)) if firmness is None else np.asarray(firmness, dtype=float)
        self.cost = self.weight * f

    def _nearest(self, data: mujoco.MjData, k: int, obj: int) -> tuple[float, int]:
        best, best_g = np.inf, -1
        for g in self.body_geoms[k]:
            d = mujoco.mj_geomDistance(self.model, data, g, obj, self.reach, self._fromto)
            if d < best:
                best, best_g = d, g
        return best, best_g

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        data = configuration.data
        return np.array([self._nearest(data, k, o)[0] for k, o in self.pairs]) - self.gap

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        data = configuration.data
        out = np.zeros((len(self.pairs), self.model.nv))
        for i, (k, o) in enumerate(self.pairs):
            d, g = self._nearest(data, k, o)
            if g < 0 or d >= self.reach:
                continue  # Out of reach: no gradient (the key-point anchors bring it near).
            mujoco.mj_geomDistance(self.model, data, g, o, self.reach, self._fromto)
            row = compute_contact_normal_jacobian(
                self.model, data, g, o, self._fromto, self._normal, self._jac1, self._jac2
            )
            out[i] = row if d >= 0 else -row  # The witness normal flips inside.
        return out
