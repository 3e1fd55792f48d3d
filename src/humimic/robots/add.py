"""``humimic robots add``: any humanoid, from its MJCF or URDF, as a robot every command takes.

The model is read by MuJoCo's own compiler (URDF too); what MuJoCo cannot use is made usable and
said: a URDF gets a floating base (a ``floating`` joint from a new world link: MuJoCo makes it a
free joint), its visual geometry is dropped (the viewer draws the collision geometry), collision
meshes MuJoCo cannot read (DAE and the like) are converted with trimesh or, where trimesh cannot
read them either, replaced by the box of the link's inertia. A floor is added where the model has
none, position actuators where it has none. Then the robot's humanoid structure is found from
its tree and geometry (:func:`find_structure`: feet, knees, hips, hands, elbows, shoulders,
torso, head) and a robot map of humimic's canonical key points is written from it, beside a
``robot.yaml`` with a motor per joint (the model's effort limits where it gives them, stated
defaults where not). Everything lands in one folder under the user's robots folder
(:mod:`humimic.robots.user`), written whole or not at all.

The model is read in :mod:`humimic.robots.add_read`, its structure found in
:mod:`humimic.robots.add_structure`; this module makes it a robot and writes it.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.errors import InputError, OutputPathError
from humimic.io import atomic_write_text
from humimic.robots.actuators import ActuatorRecipe
from humimic.robots.add_read import one_line, read_mjcf, read_urdf
from humimic.robots.add_structure import Structure, find_structure, geom_bounds
from humimic.robots.collision import robot_geoms
from humimic.robots.registry import ROBOTS
from humimic.robots.user import MAP_FILE, NAME_PATTERN, ROBOT_FILE, SCHEMA_VERSION, robots_dir

DEFAULT_ARMATURE_SWING = 0.5
"""Where a model gives no rotor inertia, the armature is chosen so that the gain recipe's kp
is the joint's effort limit over this many radians (a servo saturating at half a radian)."""
RECIPE_HZ = ActuatorRecipe.natural_frequency_hz
"""The gain recipe's natural frequency an added robot gets (the registered robots' default)."""
DEFAULT_SPEED = 20.0
"""Joint speed limit [rad/s] where the model gives none: a stated default, as for the
registered robots without one."""


@dataclass(kw_only=True)
class AddResult:
    """What ``robots add`` did."""

    name: str
    folder: Path
    structure: Structure
    notes: list[str]
    joints: int
    mass: float


# --- Making it a humimic robot -------------------------------------------------------------


def _complete(spec: mujoco.MjSpec, path: Path, notes: list[str]) -> str:
    """Floor, light, collision groups and actuators; returns the floor geom's name."""
    for j in spec.joints:
        if j.type in (mujoco.mjtJoint.mjJNT_BALL,) or (
            j.type == mujoco.mjtJoint.mjJNT_FREE and j is not next(iter(spec.joints))
        ):
            raise InputError(
                f"{path}: joint {j.name!r} is a {j.type.name} joint; humimic needs hinge and "
                "slide joints after the base's free joint"
            )
    planes = [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE]
    if planes:
        floor = planes[0]
        if not floor.name:
            floor.name = "floor"
    else:
        floor = spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE,
                                        size=[0, 0, 0.05], rgba=[0.5, 0.55, 0.6, 1])  # fmt: skip
        spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
        notes.append("a floor added")
    floor.contype, floor.conaffinity = 1, 1
    hinge = [j for j in spec.joints if j.type in (mujoco.mjtJoint.mjJNT_HINGE,
                                                   mujoco.mjtJoint.mjJNT_SLIDE)]  # fmt: skip
    if len(hinge) < 6:
        raise InputError(f"{path}: {len(hinge)} hinge or slide joints: not a humanoid (no legs)")
    if not list(spec.actuators):
        for j in hinge:
            spec.add_actuator(name=j.name, target=j.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        notes.append(f"{len(hinge)} position actuators added, one per joint")
    return str(floor.name)


SOLE_SLAB = 0.02
"""A mesh foot stands on the box of its mesh's vertices within this height [m] of its lowest
point (the sole), not on the box of the whole mesh, which reaches up into the shin."""


def _box_feet(spec: mujoco.MjSpec, model: mujoco.MjModel, s: Structure, notes: list[str]) -> bool:
    """Feet whose collision geometry is meshes stand on boxes: the footprint of each foot
    mesh's lowest :data:`SOLE_SLAB` at ``qpos0`` (aligned with the robot's forward direction,
    1 cm thick) becomes the foot's collision geom, the mesh is kept for the look only (the
    feet's contact points come from boxes, spheres and capsules). Returns whether any foot
    changed."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    fwd = np.asarray(s.forward, dtype=float)
    axes = np.stack([fwd, np.cross([0.0, 0.0, 1.0], fwd), [0.0, 0.0, 1.0]])  # Rows: x y z.
    changed = False
    for side, name in s.feet.items():
        body = model.body(name).id
        meshes = [g for g in robot_geoms(model, s.root) if model.geom_bodyid[g] == body
                  and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]  # fmt: skip
        if not meshes:
            continue
        verts = []
        for g in meshes:
            mid = int(model.geom_dataid[g])
            v = model.mesh_vert[
                model.mesh_vertadr[mid] : model.mesh_vertadr[mid] + model.mesh_vertnum[mid]
            ]
            verts.append(data.geom_xpos[g] + v @ data.geom_xmat[g].reshape(3, 3).T)
        world = np.vstack(verts)
        low = world[world[:, 2] < world[:, 2].min() + SOLE_SLAB] @ axes.T  # In (fwd, left, up).
        lo, hi = low.min(axis=0), low.max(axis=0)
        lo[2], hi[2] = world[:, 2].min(), world[:, 2].min() + 0.01
        centre_w = axes.T @ (0.5 * (lo + hi))
        rot_b = data.xmat[body].reshape(3, 3)
        pos = rot_b.T @ (centre_w - data.xpos[body])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (rot_b.T @ axes.T).ravel())
        spec.body(name).add_geom(name=f"{name}_sole", type=mujoco.mjtGeom.mjGEOM_BOX,
                                 size=(0.5 * (hi - lo)).tolist(), pos=pos.tolist(),
                                 quat=quat.tolist(), contype=1, conaffinity=1,
                                 group=3)  # fmt: skip
        for g in meshes:
            mesh_geom = next((sg for sg in spec.geoms if sg.id == g), None)
            if mesh_geom is not None:
                mesh_geom.contype, mesh_geom.conaffinity, mesh_geom.group = 0, 0, 2
        changed = True
        size = 100 * (hi - lo)
        notes.append(f"{side} foot {name!r}: stands on a {size[0]:.0f} x {size[1]:.0f} cm box, "
                     "the footprint of its collision mesh's lowest 2 cm")  # fmt: skip
    return changed


def _toe_offset(
    model: mujoco.MjModel, data: mujoco.MjData, root: str, foot: int, forward: np.ndarray
) -> list[float]:
    """The toe key point in the foot body's frame: on the bottom of the foot's collision
    geometry, three quarters of the way from the ankle to its front (along ``forward``),
    under the ankle's line."""
    pts = np.vstack([geom_bounds(model, data, g) for g in robot_geoms(model, root)
                     if model.geom_bodyid[g] == foot])  # fmt: skip
    ankle = data.xpos[foot]
    front = float(((pts - ankle) @ forward).max())
    toe = ankle + 0.75 * front * forward
    toe[2] = float(pts[:, 2].min())
    rot = data.xmat[foot].reshape(3, 3)
    return [round(float(v), 4) for v in rot.T @ (toe - ankle)]


def robot_map(model: mujoco.MjModel, s: Structure, name: str) -> dict[str, Any]:
    """The robot map (the shipped robot maps' form) of a found structure."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)

    def off(body: str, frame_body: str) -> list[float]:
        b, f = model.body(body).id, model.body(frame_body).id
        rot = data.xmat[f].reshape(3, 3)
        return [round(float(v), 4) for v in rot.T @ (data.xpos[b] - data.xpos[f])]

    kp: dict[str, dict[str, Any]] = {"pelvis": {"body": s.root, "weight": 10.0}}
    for side in ("left", "right"):
        kp[f"{side}_hip"] = {"body": s.root, "offset": off(s.hips[side], s.root),
                             "parent": "pelvis", "frame": "pelvis", "weight": 2.0}  # fmt: skip
    for side in ("left", "right"):
        last = f"{side}_hip"
        if s.knees[side] is not None:
            kp[f"{side}_knee"] = {"body": s.knees[side], "parent": last, "weight": 3.0}
            last = f"{side}_knee"
        kp[f"{side}_ankle"] = {"body": s.feet[side], "parent": last, "weight": 10.0}
        foot = model.body(s.feet[side]).id
        toe = _toe_offset(model, data, s.root, foot, np.asarray(s.forward))
        kp[f"{side}_toe"] = {"body": s.feet[side], "offset": toe,
                             "parent": f"{side}_ankle", "weight": 5.0}  # fmt: skip
    arms = all(s.shoulders.get(x) and s.hands.get(x) for x in ("left", "right"))
    if arms:
        ls, rs = str(s.shoulders["left"]), str(s.shoulders["right"])
        mid = 0.5 * (np.array(off(ls, s.torso)) + np.array(off(rs, s.torso)))
        neck = [0.0, 0.0, round(float(mid[2]), 4)]
        kp["neck"] = {"body": s.torso, "offset": neck, "parent": "pelvis", "weight": 3.0}
        for side in ("left", "right"):
            kp[f"{side}_shoulder"] = {"body": s.shoulders[side], "parent": "neck",
                                      "frame": "torso", "weight": 2.0}  # fmt: skip
            last = f"{side}_shoulder"
            if s.elbows.get(side):
                kp[f"{side}_elbow"] = {"body": s.elbows[side], "parent": last, "weight": 3.0}
                last = f"{side}_elbow"
            kp[f"{side}_wrist"] = {"body": s.hands[side], "parent": last, "weight": 4.0}
    else:
        legs = float(np.linalg.norm(data.xpos[model.body(s.hips["left"]).id]
                                    - data.xpos[model.body(s.feet["left"]).id]))  # fmt: skip
        kp["neck"] = {"body": s.root, "offset": [0.0, 0.0, round(0.55 * legs, 4)],
                      "parent": "pelvis", "weight": 3.0}  # fmt: skip
    frames: dict[str, Any] = {
        "pelvis": {"body": s.root, "left": ["right_hip", "left_hip"], "up": ["pelvis", "neck"],
                   "weight": 2.0},
    }  # fmt: skip
    if arms:
        frames["torso"] = {"body": s.torso, "left": ["right_shoulder", "left_shoulder"],
                           "up": ["pelvis", "neck"], "weight": 2.0}  # fmt: skip
    return {
        "schema_version": 1,
        "robot": name,
        "root": "pelvis",
        "posture_weight": 0.05,
        "keypoints": kp,
        "frames": frames,
        "feet": {
            side: {"ankle": f"{side}_ankle", "toe": f"{side}_toe", "body": s.feet[side]}
            for side in ("left", "right")
        },
    }


def _motors(model: mujoco.MjModel, mass: float, height: float) -> tuple[dict[str, Any], list[str]]:
    """A motor per actuated joint: the model's armature and effort limit where it gives them,
    stated defaults where not (said in the notes)."""
    notes: list[str] = []
    default_effort = round(mass * 9.81 * height / 4.0, 1)
    wn = 2.0 * math.pi * RECIPE_HZ
    motors: dict[str, Any] = {}
    no_effort, no_armature = [], []
    for a in range(model.nu):
        j = int(model.actuator_trnid[a, 0])
        name = model.joint(j).name
        effort = (float(model.jnt_actfrcrange[j, 1]) if model.jnt_actfrclimited[j]
                  else float(model.actuator_forcerange[a, 1]) if model.actuator_forcelimited[a]
                  else 0.0)  # fmt: skip
        if effort <= 0:
            effort = default_effort
            no_effort.append(name)
        armature = float(model.dof_armature[model.jnt_dofadr[j]])
        if armature <= 0:
            armature = effort / (DEFAULT_ARMATURE_SWING * wn * wn)
            no_armature.append(name)
        motors[name] = {"armature": float(f"{armature:.6g}"), "effort_limit": effort,
                        "velocity_limit": DEFAULT_SPEED}  # fmt: skip
    if no_effort:
        notes.append(f"{len(no_effort)} joints give no effort limit: {default_effort} N m stated "
                     "(mass x g x height / 4)")  # fmt: skip
    if no_armature:
        notes.append(f"{len(no_armature)} joints give no armature: chosen so that kp is the "
                     f"effort limit over {DEFAULT_ARMATURE_SWING} rad")  # fmt: skip
    notes.append(f"joint speeds: {DEFAULT_SPEED} rad/s stated (the model gives none)")
    return motors, notes


def add_robot(
    model_path: str | Path, name: str, *, root: Path | None = None, force: bool = False
) -> AddResult:
    """Add the humanoid in ``model_path`` (MJCF ``.xml`` or ``.urdf``) as robot ``name`` under
    ``root`` (default :func:`~humimic.robots.user.robots_dir`).

    Raises:
        InputError: A bad name, a model that cannot be read or is not a humanoid (no floating
            root, no legs, broken XML, missing meshes), naming what is wrong.
        OutputPathError: The robot exists (without ``force``) or the folder cannot be written.
    """
    path = Path(model_path)
    kind = _checked_source(path, name)
    base = robots_dir() if root is None else Path(root)
    dest = base / name
    if dest.exists() and not force:
        raise OutputPathError(f"{dest}: robot {name!r} was added already; --force replaces it")
    tmp = _fresh_folder(base, name)
    try:
        notes: list[str] = []
        assets = (tmp / "assets").resolve()
        spec, model, root_body, structure, floor = _compiled(path, kind, assets, notes)
        mass = float(model.body_subtreemass[root_body])
        motors, motor_notes = _motors(model, mass, structure.height)
        notes += motor_notes
        _stand(spec, model, root_body, structure, notes)
        spec.compile()
        xml = spec.to_xml().replace(f'meshdir="{assets}', 'meshdir="assets')
        _write_robot(tmp, name, path, xml, model, structure, floor, motors, notes)
        if dest.exists():
            shutil.rmtree(dest)
        tmp.rename(dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return AddResult(name=name, folder=dest, structure=structure, notes=notes,
                     joints=len(motors), mass=mass)  # fmt: skip


def _checked_source(path: Path, name: str) -> str:
    """The model's kind (its suffix: ``.xml`` or ``.urdf``), once the name and the file are
    checked.

    Raises:
        InputError: A name that is malformed or a registered robot's, no such file, or a
            file that is neither MJCF nor URDF.
    """
    if not NAME_PATTERN.fullmatch(name):
        raise InputError(f"--name {name!r}: lower case letters, digits and _, a letter first")
    if name in ROBOTS:
        raise InputError(f"--name {name!r}: a registered robot has that name; choose another")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    kind = path.suffix.lower()
    if kind not in (".xml", ".urdf"):
        raise InputError(f"{path}: expected an MJCF .xml or a .urdf file")
    return kind


def _fresh_folder(base: Path, name: str) -> Path:
    """An empty temporary folder for robot ``name`` under ``base`` (``.<name>.tmp``, with its
    ``assets`` folder), replacing one a failed run left; the robot is written there and
    renamed into place whole.

    Raises:
        OutputPathError: The folder cannot be written.
    """
    try:
        base.mkdir(parents=True, exist_ok=True)
        tmp = base / f".{name}.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        (tmp / "assets").mkdir(parents=True)
    except OSError as e:
        raise OutputPathError(f"{base}: cannot write the robot's folder: {e.strerror}") from None
    return tmp


def _compiled(
    path: Path, kind: str, assets: Path, notes: list[str]
) -> tuple[mujoco.MjSpec, mujoco.MjModel, int, Structure, str]:
    """The model read (its meshes into ``assets``), completed and compiled, with its structure
    found and its feet on boxes: (spec, model, root body id, structure, floor geom name).

    Raises:
        InputError: The model cannot be read or compiled, or is not a humanoid.
    """
    spec = (read_urdf if kind == ".urdf" else read_mjcf)(path, assets, notes)
    floor = _complete(spec, path, notes)
    try:
        model = spec.compile()
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot compile this model: {one_line(e)}") from None
    free = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
    root_body = int(model.jnt_bodyid[free])
    try:
        structure = find_structure(model, root_body)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    if _box_feet(spec, model, structure, notes):
        try:
            model = spec.compile()
        except ValueError as e:
            raise InputError(f"{path}: MuJoCo cannot compile the model with box feet: "
                             f"{one_line(e)}") from None  # fmt: skip
    return spec, model, root_body, structure, floor


def _stand(
    spec: mujoco.MjSpec,
    model: mujoco.MjModel,
    root_body: int,
    structure: Structure,
    notes: list[str],
) -> None:
    """The robot's root body in ``spec`` moved so that it stands on the floor at ``qpos0``,
    facing +x (said in the notes where it is turned)."""
    # Stand the robot on the floor at qpos0: its root at the height that puts the lowest
    # collision point on z = 0.
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    lowest = min(float(geom_bounds(model, data, g)[:, 2].min())
                 for g in robot_geoms(model, structure.root))  # fmt: skip
    rb = spec.body(model.body(root_body).name)
    rb.pos = np.asarray(rb.pos, dtype=float) - np.array([0.0, 0.0, lowest])
    # Facing +x at qpos0, as every registered robot does (iCub's base faces -x).
    yaw = math.atan2(structure.forward[1], structure.forward[0])
    if abs(yaw) > 1e-6:
        turn = np.array([math.cos(-yaw / 2), 0.0, 0.0, math.sin(-yaw / 2)])
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, turn, np.asarray(rb.quat, dtype=float))
        rb.quat = quat
        pos = np.zeros(3)
        mujoco.mju_rotVecQuat(pos, np.asarray(rb.pos, dtype=float), turn)
        rb.pos = pos
        notes.append(f"turned {math.degrees(yaw):+.0f} deg about z to face +x at qpos0 "
                     "(its knees bend and its toes point that way)")  # fmt: skip


def _key_bodies(structure: Structure) -> list[str]:
    """The bodies of the found structure, each once: root, legs, torso, arms."""
    key_bodies = [structure.root]
    for side in ("left", "right"):
        key_bodies += [b for b in (structure.hips[side], structure.knees[side],
                                   structure.feet[side]) if b]  # fmt: skip
    if structure.torso != structure.root:
        key_bodies.append(structure.torso)
    for side in ("left", "right"):
        key_bodies += [b for b in (structure.shoulders.get(side), structure.elbows.get(side),
                                   structure.hands.get(side)) if b]  # fmt: skip
    return list(dict.fromkeys(key_bodies))


def _write_robot(
    tmp: Path,
    name: str,
    path: Path,
    xml: str,
    model: mujoco.MjModel,
    structure: Structure,
    floor: str,
    motors: dict[str, Any],
    notes: list[str],
) -> None:
    """The robot's files written into ``tmp``: its scene MJCF, ``robot.yaml``, its robot map
    (from ``model``, the compiled model before it was stood on the floor) and ``SOURCE.txt``
    (the source model and the notes)."""
    import yaml

    model_file = f"{name}.xml"
    atomic_write_text(tmp / model_file, xml)
    map_doc = robot_map(model, structure, name)
    robot_doc = {
        "schema_version": SCHEMA_VERSION,
        "description": f"{name}, {len(motors)} DoF, added from {path.name}",
        "license": f"as its source model's ({path})",
        "model": model_file,
        "root_body": structure.root,
        "torso_body": structure.torso,
        "floor_geom": floor,
        "feet": dict(structure.feet),
        "hands": {k: v for k, v in structure.hands.items() if v},
        "key_bodies": _key_bodies(structure),
        "natural_frequency_hz": RECIPE_HZ,
        "damping_ratio": ActuatorRecipe.damping_ratio,
        "motors": motors,
    }
    header = f"# Robot {name}, added by `humimic robots add` from {path.resolve()}.\n"
    atomic_write_text(
        tmp / ROBOT_FILE,
        header + yaml.safe_dump(robot_doc, sort_keys=False, default_flow_style=None),
    )
    map_header = (f"# Robot map of {name}, generated from its tree and geometry by "
                  "`humimic robots add`: edit it to move a key point.\n")  # fmt: skip
    atomic_write_text(
        tmp / MAP_FILE,
        map_header + yaml.safe_dump(map_doc, sort_keys=False, default_flow_style=None),
    )
    atomic_write_text(tmp / "SOURCE.txt", f"{path.resolve()}\n" + "\n".join(notes) + "\n")
