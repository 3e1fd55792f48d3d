"""The IK's robot model: the nominal robot, one site per key point, and a scene's objects.

:func:`ik_model` builds it; :func:`robot_collision_geoms`, :func:`scene_geoms` and
:func:`sole_corner_geoms` find its kinds of geoms again.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from humimic.datasets.scene import Scene
from humimic.errors import InputError, MapError
from humimic.robots.maps import RetargetMap
from humimic.robots.model import nominal_spec
from humimic.robots.registry import RobotConfig

KEYPOINT_SITE_PREFIX = "humimic_kp_"


SCENE_BODY_PREFIX = "humimic_scene_"


def ik_model(
    robot: RobotConfig,
    m: RetargetMap,
    *,
    menagerie_root: str | Path | None = None,
    scene: Scene | None = None,
) -> tuple[mujoco.MjModel, dict[str, float]]:
    """The nominal model plus one site per key point (sites change no physics), and the
    scene's objects, each a mesh geom on a mocap body ``humimic_scene_<name>`` (moved per
    frame with ``data.mocap_pos``/``mocap_quat``; posed at its first frame).

    Returns:
        The model and each actuated joint's speed limit [rad/s].
    """
    spec, acts = nominal_spec(robot, menagerie_root=menagerie_root)
    for name, kp in m.keypoints.items():
        body = spec.body(kp.body)
        if body is None:
            raise MapError(
                f"{m.source}: keypoints.{name}.body: robot {robot.name} has no body {kp.body!r}"
            )
        body.add_site(name=KEYPOINT_SITE_PREFIX + name, pos=list(kp.offset), group=5)
    for obj in scene.objects if scene is not None else ():
        mesh_name = SCENE_BODY_PREFIX + obj.name
        # Unscaled whatever the robot's default mesh class says: the OP3's scales its meshes
        # by 0.001 (millimetres), which shrank every box of the scene to a point.
        spec.add_mesh(name=mesh_name, uservert=obj.vertices.ravel().tolist(),
                      userface=obj.faces.ravel().tolist(), scale=[1.0, 1.0, 1.0])  # fmt: skip
        body = spec.worldbody.add_body(name=mesh_name, mocap=True, pos=obj.poses[0, :3].tolist(),
                                       quat=obj.poses[0, 3:].tolist())  # fmt: skip
        body.add_geom(name=mesh_name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh_name,
                      contype=1, conaffinity=1, group=2, rgba=[0.55, 0.6, 0.7, 0.6])  # fmt: skip
    try:
        model = spec.compile()
        if scene is not None and _add_sole_corners(spec, model, [f.body for f in m.feet.values()]):
            model = spec.compile()
    except ValueError as e:
        where = f"{scene.source}: " if scene is not None and scene.source else ""
        detail = " ".join(str(e).split())
        raise InputError(f"{where}the scene cannot be added to the robot model: {detail}") from None
    return model, {j: a.velocity_limit for j, a in acts.items()}


SOLE_CORNER_PREFIX = "humimic_corner_"
SOLE_CORNER_RADIUS = 1e-3
"""Radius [m] of the spheres at a box foot's corners (their surfaces at the corners)."""


def _add_sole_corners(spec: mujoco.MjSpec, model: mujoco.MjModel, feet: list[str]) -> bool:
    """Tiny spheres at the sole corners of the feet's collision boxes (the four lowest in the
    rest pose), without contact bits or mass: the scene limit keeps them out of the objects
    too. One box against a box-shaped
    object gives one pair of witness points, which does not hold the foot's turn about them:
    the T1's box feet ended up to 72 mm inside the climbing clips' boxes. Returns whether any
    were added (:func:`sole_corner_geoms` finds them)."""
    added = False
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)  # The rest pose, qpos0.
    for name in feet:
        b = model.body(name).id
        for g in range(model.ngeom):
            if (model.geom_bodyid[g] != b or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX
                    or (model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0)):  # fmt: skip
                continue
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, model.geom_quat[g])
            inner = np.maximum(model.geom_size[g] - SOLE_CORNER_RADIUS, 0.0)
            corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3)
            local = model.geom_pos[g] + (corners * inner) @ rot.reshape(3, 3).T
            world_z = (data.geom_xpos[g] + (corners * inner) @ data.geom_xmat[g].reshape(3, 3).T)[
                :, 2
            ]
            # The sole: the box's four corners lowest in the rest pose.
            for i in np.argsort(world_z, kind="stable")[:4]:
                spec.body(name).add_geom(
                    name=f"{SOLE_CORNER_PREFIX}{g}_{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE,
                    size=[SOLE_CORNER_RADIUS, 0, 0], pos=local[i].tolist(),
                    contype=0, conaffinity=0, group=5, density=0.0, mass=0.0,
                )  # fmt: skip
                added = True
    return added


def sole_corner_geoms(model: mujoco.MjModel) -> list[int]:
    """Geom ids of :func:`_add_sole_corners`'s spheres in a model of :func:`ik_model`."""
    return [g for g in range(model.ngeom) if model.geom(g).name.startswith(SOLE_CORNER_PREFIX)]


def scene_geoms(model: mujoco.MjModel) -> list[int]:
    """Geom ids of the scene's objects in a model of :func:`ik_model`."""
    return [
        g
        for g in range(model.ngeom)
        if (name := model.geom(g).name) and name.startswith(SCENE_BODY_PREFIX)
    ]


def robot_collision_geoms(model: mujoco.MjModel) -> list[int]:
    """Geom ids of the robot's collision geoms (not the floor's, not the scene's)."""
    return [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] != 0
        and (model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0)
        and not model.geom(g).name.startswith(SCENE_BODY_PREFIX)
    ]


__all__ = [
    "KEYPOINT_SITE_PREFIX",
    "SCENE_BODY_PREFIX",
    "SOLE_CORNER_PREFIX",
    "SOLE_CORNER_RADIUS",
    "ik_model",
    "robot_collision_geoms",
    "scene_geoms",
    "sole_corner_geoms",
]
