"""What the viewer draws, computed once: robot visual meshes and their poses for every frame.

No viser here: this module turns a motion (generalized positions) into per-frame world poses of
the robot's visual geoms by MuJoCo forward kinematics, so it can be tested against MuJoCo
directly and the viewer only moves handles.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.transforms import matrix_to_quat


@dataclass(frozen=True, kw_only=True)
class VisualMesh:
    """One visual geom of the robot.

    Attributes:
        geom: MuJoCo geom id.
        body: Body name.
        vertices: In the geom frame. Shape: (V, 3).
        faces: Shape: (F, 3).
        rgba: Colour in [0, 1]. Shape: (4,).
    """

    geom: int
    body: str
    vertices: np.ndarray
    faces: np.ndarray
    rgba: np.ndarray


def visual_meshes(model: mujoco.MjModel) -> list[VisualMesh]:
    """The robot's visual meshes: mesh geoms of group 2 (MuJoCo Menagerie's convention), or
    every mesh geom of a robot body when the model has no group-2 geoms."""
    robot = [g for g in range(model.ngeom) if model.body_weldid[model.geom_bodyid[g]] != 0]
    meshes = [g for g in robot if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
    visual = [g for g in meshes if model.geom_group[g] == 2] or meshes
    out = []
    for g in visual:
        mid = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
        f0, nf = model.mesh_faceadr[mid], model.mesh_facenum[mid]
        mat = model.geom_matid[g]
        rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
        out.append(
            VisualMesh(
                geom=g,
                body=model.body(model.geom_bodyid[g]).name,
                vertices=model.mesh_vert[v0 : v0 + nv].copy(),
                faces=model.mesh_face[f0 : f0 + nf].copy(),
                rgba=np.asarray(rgba, dtype=np.float64).copy(),
            )
        )
    return out


@dataclass(frozen=True, kw_only=True)
class PoseTrack:
    """World poses of geoms and bodies for every frame.

    Attributes:
        geom_pos: Shape: (T, G, 3). geom_quat: Shape: (T, G, 4), wxyz.
        body_pos: Shape: (T, B, 3). body_quat: Shape: (T, B, 4), wxyz.
        body_names: The B bodies (all bodies but the world).
    """

    geom_pos: np.ndarray
    geom_quat: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    body_names: tuple[str, ...]


def pose_track(model: mujoco.MjModel, qpos: np.ndarray, geoms: list[int]) -> PoseTrack:
    """Forward kinematics of a qpos trajectory. Shape of qpos: (T, nq)."""
    data = mujoco.MjData(model)
    T = qpos.shape[0]
    gpos = np.zeros((T, len(geoms), 3))
    gmat = np.zeros((T, len(geoms), 3, 3))
    bpos = np.zeros((T, model.nbody - 1, 3))
    bquat = np.zeros((T, model.nbody - 1, 4))
    for t in range(T):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        gpos[t] = data.geom_xpos[geoms]
        gmat[t] = data.geom_xmat[geoms].reshape(-1, 3, 3)
        bpos[t] = data.xpos[1:]
        bquat[t] = data.xquat[1:]
    return PoseTrack(
        geom_pos=gpos,
        geom_quat=matrix_to_quat(gmat),
        body_pos=bpos,
        body_quat=bquat,
        body_names=tuple(model.body(b).name for b in range(1, model.nbody)),
    )


def skeleton_segments(positions: np.ndarray, parents: tuple[int, ...]) -> np.ndarray:
    """Bone segments of a skeleton for every frame.

    Args:
        positions: Joint positions. Shape: (T, J, 3).
        parents: Parent of each joint (-1 for roots).

    Returns:
        Segment end points. Shape: (T, S, 2, 3).
    """
    pairs = [(j, p) for j, p in enumerate(parents) if p >= 0]
    if not pairs:
        return np.zeros((positions.shape[0], 0, 2, 3))
    child = np.array([a for a, _ in pairs])
    parent = np.array([b for _, b in pairs])
    return np.stack([positions[:, parent], positions[:, child]], axis=2)
