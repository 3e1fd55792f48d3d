"""``mj_setConst``'s inertial constants of many randomized models at once, in torch:
:class:`InertiaConstants`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from humimic.errors import InputError

_MINVAL = mujoco.mjMINVAL


def _skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices of vectors. Shape: (..., 3) -> (..., 3, 3)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)],
        -2,
    )


class InertiaConstants:
    """The constants of ``mj_setConst`` that depend on the inertial fields, for batches of
    models that differ from ``model`` in ``body_mass``, ``body_inertia``, ``body_ipos`` and
    ``dof_armature`` only.

    Domain randomization changes masses, inertias, centres of mass and armatures; MuJoCo
    derives from them constants the solver reads: ``body_subtreemass``, ``dof_invweight0`` and
    ``body_invweight0`` (the regularization of contacts and joint limits) and
    ``actuator_acc0``. The CPU backend recomputes them with ``mj_setConst``, per model. On a
    GPU, where many envs reset at every step, that per-env host work limits the env's
    throughput, and ``mujoco_warp.set_const`` launches kernels per dof and per body row of
    every call.

    At ``qpos0`` the kinematics do not depend on these fields, so the body Jacobians are
    computed once, and each model's constants are a few batched tensor operations::

        M = sum_b  m_b Jp_b' Jp_b + Jr_b' R_b I_b R_b' Jr_b  + diag(armature)
        A = M^-1
        dof_invweight0  = diag(A)             (averaged over the 3 + 3 dofs of a free joint)
        body_invweight0 = mean diag(Jp A Jp'), mean diag(Jr A Jr')   (of each body's CoM)
        actuator_acc0   = |A moment|

    where ``Jp_b`` is the translational Jacobian at the body's centre of mass (it moves with
    ``body_ipos``: ``Jp(xipos) = Jp(xpos) - [xmat ipos]x Jr``). The results match
    ``mj_setConst`` to float64 round-off (``tests/test_tracking_env.py``).

    Args:
        model: The nominal model.
        device: Where to compute (float64).

    Raises:
        InputError: If the model has tendons, or bodies with dofs other than hinges, slides
            and one free joint at the root (the supported case of a floating-base robot).
    """

    def __init__(self, model: mujoco.MjModel, device: str | torch.device = "cpu") -> None:
        if model.ntendon:
            raise InputError("batched set-const: models with tendons are not supported")
        self.device = torch.device(device)
        d = mujoco.MjData(model)
        d.qpos[:] = model.qpos0
        mujoco.mj_forward(model, d)
        nb, nv = model.nbody, model.nv
        jp = np.zeros((nb, 3, nv))
        jr = np.zeros((nb, 3, nv))
        for b in range(1, nb):
            if model.body_weldid[b] != 0:
                mujoco.mj_jac(model, d, jp[b], jr[b], d.xpos[b], b)
        ximat = d.ximat.reshape(nb, 3, 3)
        # ximat = xmat * iquat: with body_iquat fixed, ximat does not change with the fields.
        subtree = np.zeros((nb, nb))  # subtree[b, c] = 1 if c is in the subtree of b
        for c in range(nb):
            b = c
            while True:
                subtree[b, c] = 1.0
                if b == 0:
                    break
                b = model.body_parentid[b]
        moment = np.zeros((model.nu, nv))
        mujoco.mju_sparse2dense(
            moment, d.actuator_moment, d.moment_rownnz, d.moment_rowadr, d.moment_colind
        )
        free = [
            int(model.jnt_dofadr[j])
            for j in range(model.njnt)
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
        ]
        if any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL for j in range(model.njnt)):
            raise InputError("batched set-const: ball joints are not supported")

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(x, dtype=torch.float64, device=self.device)

        self._jp_origin, self._jr = t(jp), t(jr)
        self._xmat = t(d.xmat.reshape(nb, 3, 3))
        self._ximat = t(ximat)
        self._subtree = t(subtree)
        self._moment = t(moment)
        self._free = free
        self._moving = torch.as_tensor(model.body_weldid != 0, device=self.device)

    def __call__(
        self,
        body_mass: torch.Tensor,
        body_inertia: torch.Tensor,
        body_ipos: torch.Tensor,
        dof_armature: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """The constants of n models.

        Args:
            body_mass: Shape: (n, nbody). body_inertia: Shape: (n, nbody, 3).
            body_ipos: Shape: (n, nbody, 3). dof_armature: Shape: (n, nv).

        Returns:
            ``body_subtreemass`` (n, nbody), ``dof_invweight0`` (n, nv), ``body_invweight0``
            (n, nbody, 2), ``actuator_acc0`` (n, nu), float64 on the device.
        """
        f64 = torch.float64
        mass = body_mass.to(self.device, f64)
        inertia = body_inertia.to(self.device, f64)
        ipos = body_ipos.to(self.device, f64)
        armature = dof_armature.to(self.device, f64)
        # Translational Jacobians at each body's centre of mass. Shape: (n, nb, 3, nv).
        offset = torch.einsum("bij,nbj->nbi", self._xmat, ipos)
        jp = self._jp_origin - _skew(offset) @ self._jr
        # Rotational inertia in the world frame: R diag(I) R'. Shape: (n, nb, 3, 3).
        rot = self._ximat * inertia[:, :, None, :] @ self._ximat.transpose(-1, -2)
        m = torch.einsum("nb,nbiv,nbiw->nvw", mass, jp, jp)
        m = m + torch.einsum("biv,nbij,bjw->nvw", self._jr, rot, self._jr)
        m = m + torch.diag_embed(armature)
        a = torch.cholesky_inverse(torch.linalg.cholesky(m))
        diag = torch.diagonal(a, dim1=-2, dim2=-1)
        dof = diag.clone()
        for adr in self._free:
            dof[:, adr : adr + 3] = diag[:, adr : adr + 3].mean(-1, keepdim=True)
            dof[:, adr + 3 : adr + 6] = diag[:, adr + 3 : adr + 6].mean(-1, keepdim=True)
        trans = torch.einsum("nbiv,nvw,nbiw->nbi", jp, a, jp).mean(-1)
        rot_w = torch.einsum("biv,nvw,biw->nbi", self._jr, a, self._jr).mean(-1)
        trans_fix = torch.where((trans < _MINVAL) & (rot_w > _MINVAL), rot_w, trans)
        rot_fix = torch.where((rot_w < _MINVAL) & (trans > _MINVAL), trans, rot_w)
        body = torch.stack([trans_fix, rot_fix], -1) * self._moving[None, :, None]
        acc0 = torch.linalg.vector_norm(torch.einsum("nvw,aw->nav", a, self._moment), dim=-1)
        return {
            "body_subtreemass": mass @ self._subtree.T,
            "dof_invweight0": dof,
            "body_invweight0": body,
            "actuator_acc0": acc0,
        }


__all__ = ["InertiaConstants"]
