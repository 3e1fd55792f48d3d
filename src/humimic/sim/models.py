"""The robot models humimic simulates, each built from the robot's nominal MJCF.

:func:`training_model` (floating base, mesh-free colliders, read-out sensors) serves tracking and
dynamics retargeting; :func:`fixed_base_spec` (a robot hanging in a gantry) the robot logs of
real2sim, and :func:`prediction_spec` (the same without geometry) their k-step predictions.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from humimic.errors import InputError, UnknownNameError
from humimic.robots.model import nominal_spec
from humimic.robots.registry import RobotConfig

_CONTACT_FOUND = 1 << int(mujoco.mjtConDataField.mjCONDATA_FOUND)
_CONTACT_FORCE = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE)
_REDUCE_NETFORCE = 3

PHYSICS_DT = 0.001
"""Simulation step of simulated logs and of gantry predictions [s]: the drives' PD runs at
1 kHz (predictions on the floor may step longer, up to :data:`MAX_STEP`)."""
MAX_STEP = 0.005
"""The longest step [s] a prediction on the floor takes (the tracking env's): see
:func:`humimic.real2sim.floating.prediction_step`."""


def _mesh_free_spec(
    robot: RobotConfig, timestep: float, menagerie_root: str | os.PathLike[str] | None = None
) -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    """The nominal spec with mesh colliders as boxes, robot geoms colliding with the floor
    only, no textures, and the tracking solver settings (see :func:`training_model`); and the
    compiled nominal model it was made from."""
    spec, _ = nominal_spec(robot, menagerie_root=menagerie_root)
    # A copy is compiled: deleting elements from a compiled spec costs ~45 ms each (3.2 s
    # for the G1's 72), from one never compiled under 2 ms. The copy's elements are in the
    # spec's order, and carry their compiled ids.
    twin = spec.copy()
    full = twin.compile()
    ids = [g.id for g in twin.geoms]
    floor_id = mujoco.mj_name2id(full, mujoco.mjtObj.mjOBJ_GEOM, robot.floor_geom)
    if floor_id < 0:
        raise UnknownNameError(f"robot {robot.name!r}: no floor geom {robot.floor_geom!r}")

    for i, geom in reversed(list(enumerate(spec.geoms))):
        gid = ids[i]
        if gid == floor_id:
            geom.contype, geom.conaffinity = 1, 1
            continue
        collides = full.geom_contype[gid] != 0 or full.geom_conaffinity[gid] != 0
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            if not collides:
                spec.delete(geom)
                continue
            # Box of the mesh's bounding box, in the mesh geom's (compiled) frame.
            center, half = full.geom_aabb[gid, :3], full.geom_aabb[gid, 3:]
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, full.geom_quat[gid])
            geom.type = mujoco.mjtGeom.mjGEOM_BOX
            geom.meshname = ""
            geom.size = half.copy()
            geom.pos = full.geom_pos[gid] + rot.reshape(3, 3) @ center
            geom.quat = full.geom_quat[gid].copy()
        elif not collides:
            continue
        geom.contype, geom.conaffinity = 0, 1
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    # Textures (the G1 scene's skybox and floor grid: 5 MB) serve rendering only, and every
    # per-env copy of the model would carry them: 5 GB at 1024 envs, and caches evicted.
    for mat in spec.materials:
        mat.textures = [""] * len(mat.textures)
    for tex in list(spec.textures):
        spec.delete(tex)

    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    spec.option.iterations = 10
    spec.option.ls_iterations = 20
    return spec, full


def training_model(
    robot: RobotConfig,
    *,
    body_names: Sequence[str],
    contact_body_names: Sequence[str] = (),
    foot_body_names: Sequence[str] = (),
    timestep: float = 0.005,
    menagerie_root: str | os.PathLike[str] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
) -> mujoco.MjModel:
    """The mesh-free training model of a robot, with the read-out sensors compiled in.

    Stepping with mesh colliders is slow and a per-env copy of a model with meshes is large, so
    the model has none: visual mesh geoms are removed, each collision mesh becomes the box of its
    bounding box (``geom_aabb``) at the same pose, primitive colliders (the G1's foot spheres)
    stay, and robot geoms collide with the floor only (mjlab's G1 tracking penalizes
    self-collision rather than simulating it). Solver settings follow mjlab's tracking task:
    implicitfast, pyramidal cone, 10 solver and 20 line-search iterations.

    Args:
        robot: The robot.
        body_names: Bodies whose pose and velocity are read (frame sensors).
        contact_body_names: Bodies whose floor contacts are counted.
        foot_body_names: Bodies whose net floor contact force is read.
        timestep: Physics step [s].
        menagerie_root: Where the robot files are (see :func:`humimic.robots.nominal_spec`).
        edit: Changes to the model, applied last (e.g. a physics file's
            :meth:`~humimic.sim.physics.Physics.edit`).

    Raises:
        UnknownNameError: If a body name is not in the model.
    """
    spec, full = _mesh_free_spec(robot, timestep, menagerie_root)
    known = {full.body(b).name for b in range(full.nbody)}
    for name in (*body_names, *contact_body_names, *foot_body_names):
        if name not in known:
            raise UnknownNameError(f"body {name!r} is not in robot {robot.name!r}")
    for sensor in list(spec.sensors):  # The robot's own sensors (IMU...) are not read here.
        spec.delete(sensor)
    xbody = mujoco.mjtObj.mjOBJ_XBODY
    for kind in (
        mujoco.mjtSensor.mjSENS_FRAMEPOS,
        mujoco.mjtSensor.mjSENS_FRAMEQUAT,
        mujoco.mjtSensor.mjSENS_FRAMELINVEL,
        mujoco.mjtSensor.mjSENS_FRAMEANGVEL,
    ):
        for name in body_names:
            spec.add_sensor(type=kind, objtype=xbody, objname=name)
    for data_bits, names in (
        (_CONTACT_FOUND, contact_body_names),
        (_CONTACT_FORCE, foot_body_names),
    ):
        for name in names:
            spec.add_sensor(
                type=mujoco.mjtSensor.mjSENS_CONTACT,
                objtype=mujoco.mjtObj.mjOBJ_BODY,
                objname=name,
                reftype=mujoco.mjtObj.mjOBJ_GEOM,
                refname=robot.floor_geom,
                intprm=[data_bits, _REDUCE_NETFORCE, 1],
            )
    model = spec.compile()
    mass_full = float(np.sum(full.body_mass))
    mass = float(np.sum(model.body_mass))
    if not np.isclose(mass, mass_full, rtol=1e-6):
        raise InputError(
            f"robot {robot.name!r}: removing meshes changed the mass ({mass_full} -> {mass} kg); "
            "the MJCF must give explicit <inertial> elements"
        )
    if edit is not None:
        edit(spec)
        model = spec.compile()
    return model


def fixed_base_spec(robot: RobotConfig, base_pose: np.ndarray) -> mujoco.MjSpec:
    """The nominal spec with the floating base welded at ``base_pose`` (x y z qw qx qy qz)."""
    spec, _ = nominal_spec(robot)
    root = spec.body(robot.root_body)
    for j in list(root.joints):
        if j.type == mujoco.mjtJoint.mjJNT_FREE:
            spec.delete(j)
    root.pos = base_pose[:3]
    root.quat = base_pose[3:]
    for key in list(spec.keys):  # Keyframes hold the floating base's coordinates.
        spec.delete(key)
    # Body pairs whose collision hulls already touch in the zero pose (neighbours' convex hulls
    # overlap) are excluded: they are artefacts, not contacts a hanging robot makes. (A copy
    # is compiled: elements are deleted from a compiled spec 40x slower, see _mesh_free_spec.)
    model = spec.copy().compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    pairs = {
        tuple(sorted((model.body(model.geom_bodyid[c.geom1]).name,
                      model.body(model.geom_bodyid[c.geom2]).name)))
        for c in data.contact[: data.ncon]
    }  # fmt: skip
    for a, b in sorted(pairs):
        spec.add_exclude(bodyname1=a, bodyname2=b)
    spec.option.timestep = PHYSICS_DT
    # A hanging robot's excitation is chosen free of self-contact
    # (:func:`humimic.real2sim.simulate.excitation`); what remains are neighbouring links'
    # convex hulls grazing each other, an artefact of the collision geometry. The fixed-base
    # robot ignores contact, so logs and predictions agree on that (the excitation check
    # switches it back on).
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    # Semi-implicit Euler at 1 kHz is stable with these servos (kd / armature ~ 250 1/s) and
    # keeps inverse dynamics (mj_inverse) exactly consistent with the forward simulation.
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    return spec


def floating_prediction_spec(robot: RobotConfig, *, filters: bool = True) -> mujoco.MjSpec:
    """The robot on the floor as the predictions of a floating-base log simulate it: the
    training model's mesh-free colliders and solver (:func:`training_model`) stepped at
    :data:`PHYSICS_DT`, without sensors, and (``filters``) with each actuator's
    zero-time-constant filter of :func:`prediction_spec`."""
    spec, _ = _mesh_free_spec(robot, PHYSICS_DT)
    for sensor in list(spec.sensors):
        spec.delete(sensor)
    depth = _rest_depth(robot.name, spec)
    for key in list(spec.keys):
        spec.delete(key)
    if filters:
        _add_filters(spec)
    spec.add_numeric(name=REST_DEPTH, data=[depth])
    return spec


REST_DEPTH = "humimic_rest_depth"
"""A floating-base prediction model's numeric: how deep [m] its feet sink into the floor
when it stands (MuJoCo's contacts are soft), to place a robot standing on the floor."""
_REST_DEPTHS: dict[str, float] = {}


def floor_and_colliders(model: mujoco.MjModel) -> tuple[int, list[int]]:
    """The floor (the first plane) and the robot geoms that collide with it.

    Raises:
        InputError: The model has no plane.
    """
    floor = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if not floor:
        raise InputError("the model has no floor (a plane) for a floating-base log")
    f = floor[0]
    colliders = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0
                 and (model.geom_contype[g] & model.geom_conaffinity[f]
                      or model.geom_contype[f] & model.geom_conaffinity[g])]  # fmt: skip
    return f, colliders


def lowest_point(
    model: mujoco.MjModel, data: mujoco.MjData, floor: int, colliders: list[int]
) -> tuple[float, np.ndarray, int]:
    """The collider nearest the floor (kinematics done): its signed distance [m] (negative:
    into the floor), its nearest point (world) and its body."""
    fromto = np.zeros(6)
    best, point, body = np.inf, np.zeros(3), 0
    for g in colliders:
        d = mujoco.mj_geomDistance(model, data, floor, g, 10.0, fromto)
        if d < best:
            best, point, body = d, fromto[3:].copy(), int(model.geom_bodyid[g])
    return best, point, body


def _rest_depth(name: str, spec: mujoco.MjSpec) -> float:
    """How deep the robot's lowest collider sinks when it stands in its first keyframe,
    holding the pose with its drives (0.2-0.4 s after a touch-down start; the contacts
    settle in a few of their 20 ms time constants). 0 without a keyframe."""
    if name in _REST_DEPTHS:
        return _REST_DEPTHS[name]
    m = spec.copy().compile()
    depth = 0.0
    free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if m.nkey and free.size:
        d = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, d, 0)
        hinge = m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT
        ctrl = np.where(hinge, d.qpos[m.jnt_qposadr[m.actuator_trnid[:, 0]]], 0.0)
        f, colliders = floor_and_colliders(m)
        mujoco.mj_kinematics(m, d)
        d.qpos[int(m.jnt_qposadr[free[0]]) + 2] -= lowest_point(m, d, f, colliders)[0]
        seen = []
        for k in range(round(0.4 / m.opt.timestep)):
            d.ctrl[:] = ctrl
            mujoco.mj_step(m, d)
            if k * m.opt.timestep >= 0.2:
                seen.append(lowest_point(m, d, f, colliders)[0])
        depth = max(0.0, -float(np.median(seen)))
    _REST_DEPTHS[name] = depth
    return depth


def _add_filters(spec: mujoco.MjSpec) -> None:
    for a in spec.actuators:
        a.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
        a.dynprm = np.zeros(10)
        a.actearly = True
        a.actdim = 1


def prediction_spec(robot: RobotConfig, base_pose: np.ndarray) -> mujoco.MjSpec:
    """The fixed-base robot as the predictions simulate it.

    Geometry is removed (masses and inertias are explicit in the robot files; a hanging robot's
    excitation is free of contact by design), so a copy of the compiled model costs under a
    millisecond and a step a third less. Every actuator gets a first-order filter
    (``filterexact``, applied in the same step) with time constant 0, which behaves exactly as
    no filter: the diagnosis sets a time constant (``lag``) on the compiled model.
    """
    spec = fixed_base_spec(robot, base_pose)
    for m in list(spec.meshes):  # Meshes first: deleting a geom is slow while meshes exist.
        spec.delete(m)
    for g in list(spec.geoms):
        spec.delete(g)
    _add_filters(spec)
    return spec
