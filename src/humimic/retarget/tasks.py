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
        self._jr = np.zeros((3, model.nv))

    def set_costs(self, costs: np.ndarray) -> None:
        """Per-body costs [1/rad]. Shape: (B,)."""
        self.cost = np.repeat(np.asarray(costs, dtype=np.float64), 3)

    def _rotations(self, data: mujoco.MjData) -> np.ndarray:
        return data.xmat[self.body_ids].reshape(-1, 3, 3)

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        r = self._rotations(configuration.data)
        rel = np.einsum("nji,njk->nik", self.targets, r)
        e = rotation_log(rel).ravel()
        self.last_error = e
        return e

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        return self._error_and_jacobian(configuration)[1]

    def _error_and_jacobian(
        self, configuration: mink.Configuration
    ) -> tuple[np.ndarray, np.ndarray]:
        data = configuration.data
        r = self._rotations(data)
        rel = np.einsum("nji,njk->nik", self.targets, r)
        phi = rotation_log(rel)
        jinv = so3_right_jacobian_inverse(phi)
        out = np.zeros((3 * len(self.body_ids), self.model.nv))
        for i, b in enumerate(self.body_ids):
            mujoco.mj_jacBody(self.model, data, None, self._jr, int(b))
            out[3 * i : 3 * i + 3] = jinv[i] @ (r[i].T @ self._jr)
        self.last_error = phi.ravel()
        return self.last_error, out

    def compute_qp_objective(self, configuration: mink.Configuration) -> mink.Objective:
        """The objective from one evaluation of the error and the Jacobian (one log each)."""
        e, jac = self._error_and_jacobian(configuration)
        return self._assemble_qp(e, jac, configuration._eye_nv)
