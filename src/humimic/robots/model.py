"""Build the MuJoCo model humimic simulates with: the robot's MJCF plus its explicit actuator
model. This module and the retargeter's configuration are the only places that compile MJCF."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from humimic.errors import InputError, OutputPathError, UnknownNameError
from humimic.io import atomic_write_text, check_not_input, check_writable
from humimic.motion import Motion
from humimic.robots.actuators import JointActuator, as_written
from humimic.robots.assets import find_robot_file
from humimic.robots.registry import RobotConfig


def robot_xml_path(
    cfg: RobotConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> Path:
    """Path of the robot's scene MJCF."""
    if cfg.model_file is not None:
        if not cfg.model_file.is_file():
            raise InputError(f"{cfg.model_file}: robot {cfg.name}'s model file is missing")
        return cfg.model_file
    return find_robot_file(
        cfg.menagerie_dir,
        cfg.xml,
        user_root=menagerie_root,
        robot_descriptions_module=cfg.robot_descriptions_module,
    )


def actuated_joints(spec: mujoco.MjSpec) -> list[str]:
    """Names of the joints driven by an actuator, in actuator order."""
    return [a.target for a in spec.actuators]


def nominal_spec(
    cfg: RobotConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> tuple[mujoco.MjSpec, dict[str, JointActuator]]:
    """The robot's spec with the explicit PD actuator model applied.

    Every actuator becomes a position servo written with explicit numbers:
    ``gainprm = [kp]``, ``biasprm = [0, -kp, -kd]``, ``forcerange = +-effort``, and no
    ``ctrlrange``: a target beyond the joint range commands torque up to the effort limit,
    as a real motor driver's position loop does (and mjlab's position actuators); clamping
    targets to the range would cap a low-gain servo's torque near the range's ends (the G1's
    ankle roll, +-0.26 rad at kp 28.5, at 7.4 of its 50 Nm). Each joint's ``armature`` is the
    motor's reflected inertia and its ``actuatorfrcrange`` the effort limit. Nothing is left
    to compile-time defaults such as ``dampratio`` or ``inheritrange``.

    Returns:
        The spec and the resolved actuator of every actuated joint.

    Raises:
        InputError: The model file (from ``menagerie_root`` or the installed assets) cannot
            be loaded, or does not fit the robot (its base, feet, joints or actuators); the
            message names the file.
    """
    spec, acts, _ = _nominal_spec(cfg, menagerie_root)
    return spec, acts


def _nominal_spec(
    cfg: RobotConfig, menagerie_root: str | os.PathLike[str] | None
) -> tuple[mujoco.MjSpec, dict[str, JointActuator], Path]:
    """:func:`nominal_spec`, with the model file it was read from."""
    path = robot_xml_path(cfg, menagerie_root=menagerie_root)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot load this model: {_one_line(e)}") from None
    _check_structure(cfg, spec, path)
    _contacts_by_bitmask(cfg, spec, path)
    for name, (lo, hi) in cfg.joint_ranges.items():
        joint = spec.joint(name)
        if joint is None:
            raise InputError(f"{path}: no joint {name!r} (robot {cfg.name}'s stated joint ranges)")
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.range = np.array([lo, hi], dtype=float)
    spec.meshdir = str(Path(path).parent / (spec.meshdir or ""))
    # No compile-time magic left in the defaults either (dampratio, inheritrange).
    for default in [spec.default, *(a.classname for a in spec.actuators)]:
        default.actuator.gainprm = np.zeros(10)
        default.actuator.biasprm = np.zeros(10)
        default.actuator.inheritrange = 0.0
    joints = actuated_joints(spec)
    try:
        acts = cfg.actuators.resolve(joints)
    except UnknownNameError as e:
        raise InputError(f"{path}: {e} of robot {cfg.name}'s actuator recipe") from None
    for act in spec.actuators:
        a = acts[act.target]
        joint = spec.joint(act.target)
        joint.armature = a.armature
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.actfrcrange = np.array([-a.effort_limit, a.effort_limit])
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.dyntype = mujoco.mjtDyn.mjDYN_NONE
        act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        gain = np.zeros(10)
        gain[0] = a.kp
        bias = np.zeros(10)
        bias[1], bias[2] = -a.kp, -a.kd
        act.gainprm = gain
        act.biasprm = bias
        act.inheritrange = 0.0
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        act.ctrlrange = np.array([as_written(v) for v in act.ctrlrange])  # Unused; exported.
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = np.array([-a.effort_limit, a.effort_limit])
    _fromto_as_written(spec)
    return spec, acts, path


def _fromto_as_written(spec: mujoco.MjSpec) -> None:
    """Capsules and cylinders given by ``fromto`` (the H1's legs and feet) as the position,
    orientation and half-length MuJoCo's XML writer prints for them, six significant digits:
    so that the model simulated and the one ``robots export`` writes are the same numbers (the
    writer turned a half-length of 0.2109502 into 0.21095). A change below 1e-6 m. Explicit
    body inertias likewise."""
    kinds = (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER)
    for g in spec.geoms:
        ft = np.asarray(g.fromto, dtype=float)
        if int(g.type) not in [int(k) for k in kinds] or not np.all(np.isfinite(ft)):
            continue
        a, b = ft[:3], ft[3:]
        axis = b - a
        length = float(np.linalg.norm(axis))
        if length < 1e-12:
            continue
        quat = np.zeros(4)
        mujoco.mju_quatZ2Vec(quat, axis / length)
        g.pos = np.array([as_written(v) for v in (a + b) / 2])
        g.quat = np.array([as_written(v) for v in quat])
        size = np.array(g.size, dtype=float)
        size[1] = as_written(length / 2)
        g.size = size
        g.fromto = np.full(6, np.nan)
    # Explicit inertias given to more digits (the Apollo's camera links: 0.00014442322916...).
    for b in spec.bodies:
        inertia = np.asarray(b.inertia, dtype=float)
        if np.all(np.isfinite(inertia)):
            b.inertia = np.array([as_written(v) for v in inertia])


def _in_tree(body: mujoco.MjsBody, root: str) -> bool:
    while body is not None and body.name != "world":
        if body.name == root:
            return True
        body = body.parent
    return False


def _contacts_by_bitmask(cfg: RobotConfig, spec: mujoco.MjSpec, path: Path) -> None:
    """A model whose contacts are all explicit ``<pair>``s (Menagerie's Apollo: every geom
    has ``contype`` and ``conaffinity`` 0, the floor's too) made to collide as the other
    robots do, so that one rule finds the robot's collision geometry everywhere (the IK's
    self-collision, the reports, the floor and scene contacts, friction randomization).

    The robot's collision geoms are the geoms in the groups its pairs' geoms use (group 3 on
    the Apollo). They get ``contype`` 0 and ``conaffinity`` 1: they touch the floor and scene
    objects but not each other, so the model's own robot-robot pairs stay the simulated
    self-contacts (no duplicate contacts). A pair between a robot geom and the floor is
    removed and its condim, friction and solver parameters move onto the robot geom, where
    MuJoCo's mixing (maximum condim and friction, solver parameters averaged) gives the same
    contact against a floor with the defaults of the pair (the floor gets ``contype`` and
    ``conaffinity`` 1 and condim 3, as the other robots' floors have).

    Raises:
        InputError: The robot has no geom that collides and no pair that names one.
    """
    robot = [g for g in spec.geoms if _in_tree(g.parent, cfg.root_body)]
    if any(g.contype or g.conaffinity for g in robot):
        return
    names = {g.name: g for g in robot if g.name}
    pairs = list(spec.pairs)
    groups = {int(names[n].group) for p in pairs for n in (p.geomname1, p.geomname2) if n in names}
    if not groups:
        raise InputError(
            f"{path}: no geom of robot {cfg.name} collides (contype and conaffinity are 0 and "
            "no <pair> names one): the robot has no collision geometry"
        )
    for g in robot:
        if int(g.group) in groups:
            g.contype, g.conaffinity = 0, 1
    floor = spec.geom(cfg.floor_geom)
    if floor is not None:
        floor.contype, floor.conaffinity, floor.condim = 1, 1, 3
    for p in pairs:
        ends = {p.geomname1, p.geomname2}
        if cfg.floor_geom not in ends:
            continue
        other = names.get(next(iter(ends - {cfg.floor_geom}), ""))
        if other is None:
            continue
        other.condim = p.condim
        other.friction = np.asarray(p.friction, dtype=float)[[0, 2, 3]]
        other.solref, other.solimp = p.solref, p.solimp
        spec.delete(p)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())[:300]


def _check_structure(cfg: RobotConfig, spec: mujoco.MjSpec, path: Path) -> None:
    """The model is one the robot's configuration fits: a free base joint then hinge or
    slide joints (motion files store ``qpos`` as 7 + joints), the registry's base and foot
    bodies, and actuators that each drive a joint of the model."""
    one_dof = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
    joints = list(spec.joints)
    if not joints or joints[0].type != mujoco.mjtJoint.mjJNT_FREE:
        raise InputError(f"{path}: the model's first joint must be the base's free joint")
    for j in joints[1:]:
        if j.type not in one_dof:
            raise InputError(
                f"{path}: joint {j.name!r} is a {j.type.name} joint; expected hinge or slide "
                "joints after the base's free joint"
            )
    for what, body in [("base", cfg.root_body), *((f"{s} foot", b) for s, b in cfg.feet.items())]:
        if spec.body(body) is None:
            raise InputError(f"{path}: no body {body!r} (robot {cfg.name}'s {what})")
    if not spec.actuators:
        raise InputError(f"{path}: the model has no actuators")
    names = {j.name for j in joints}
    for act in spec.actuators:
        if act.target not in names:
            raise InputError(
                f"{path}: actuator {act.name!r} drives {act.target!r}, which is not a joint of "
                "this model"
            )


def nominal_model(
    cfg: RobotConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> mujoco.MjModel:
    """Compiled nominal model (robot, floor, explicit actuators).

    Raises:
        InputError: The model file cannot be loaded or compiled (names the file).
    """
    spec, _, path = _nominal_spec(cfg, menagerie_root)
    return _compile(spec, path)


def motion_model(motion: Motion, source: str) -> mujoco.MjModel:
    """The nominal model of the robot a motion names, after checking that the motion is one
    of that robot's: a registered name, and its joints (names, in order) and ``qpos`` width.

    Args:
        motion: The motion.
        source: What messages name (the file).

    Raises:
        InputError: An unknown robot name, or joints that are not the robot's.
    """
    from humimic.robots.registry import get_robot

    model = nominal_model(get_robot(motion.robot, source))
    names = tuple(model.joint(j).name for j in range(1, model.njnt))
    if names != tuple(motion.joint_names):
        other = next((f"joint {i} is {a!r}, the robot's {b!r}" for i, (a, b)
                      in enumerate(zip(motion.joint_names, names, strict=False)) if a != b),
                     f"{len(motion.joint_names)} joints, the robot has {len(names)}")  # fmt: skip
        raise InputError(
            f"{source}: labelled robot {motion.robot!r}, but its joints are not that robot's "
            f"({other})"
        )
    if motion.qpos.shape[1] != model.nq:
        raise InputError(
            f"{source}: qpos has {motion.qpos.shape[1]} columns, robot {motion.robot!r} has "
            f"nq = {model.nq}"
        )
    return model


def _compile(spec: mujoco.MjSpec, path: Path) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as e:  # Missing mesh files, bad values...
        raise InputError(f"{path}: MuJoCo cannot compile this model: {_one_line(e)}") from None


def export_nominal(
    cfg: RobotConfig,
    out: str | os.PathLike[str],
    *,
    menagerie_root: str | os.PathLike[str] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
) -> Path:
    """Write the exact nominal MJCF humimic simulates with, self-contained.

    The meshes are copied into ``<out stem>_assets/`` beside the file and referenced relative
    to it, so the file loads from any working directory. The XML is written atomically.
    ``edit`` changes the spec before it is written (e.g. to add identified effects).
    """
    if Path(out).suffix.lower() != ".xml":
        raise InputError(f"{out}: the exported model must be an .xml file")
    spec, _, path = _nominal_spec(cfg, menagerie_root)
    check_not_input(out, {"the robot model": path}, "--out")
    # The model's folder holds the files it includes (a Menagerie scene.xml includes g1.xml)
    # and its meshes: the export must neither replace one nor remove it with an old
    # <out>_assets folder.
    model_dir, out_abs = path.parent.resolve(), Path(out).resolve()
    assets_abs = out_abs.parent / f"{out_abs.stem}_assets"
    if model_dir in out_abs.parents or assets_abs == model_dir or assets_abs in model_dir.parents:
        raise OutputPathError(
            f"--out {out}: inside or around the robot model's folder {path.parent}, whose "
            "files the export reads; choose another folder"
        )
    if edit is not None:
        edit(spec)
    src_meshdir = Path(spec.meshdir)
    for mesh in spec.meshes:  # Before anything is created beside --out.
        if not (src_meshdir / mesh.file).is_file():
            raise InputError(f"{path}: mesh {mesh.name!r}: no file {src_meshdir / mesh.file}")
    out_path = check_writable(out, create=True)
    asset_dir_name = f"{out_path.stem}_assets"
    asset_dir = out_path.parent / asset_dir_name
    tmp_assets = out_path.parent / f".{asset_dir_name}.tmp"
    if tmp_assets.exists():
        shutil.rmtree(tmp_assets)
    try:
        tmp_assets.mkdir()
        for i, mesh in enumerate(spec.meshes):
            # Keep the path under the mesh folder: the OP3 has body.stl and
            # simplified_convex/body.stl, which one flat folder would merge.
            rel = Path(mesh.file)
            if rel.is_absolute() or ".." in rel.parts:
                rel = Path(f"{i}_{rel.name}")
            (tmp_assets / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src_meshdir / mesh.file, tmp_assets / rel)
            mesh.file = rel.as_posix()
        abs_dir = str(tmp_assets.resolve())
        spec.meshdir = abs_dir
        _compile(spec, path)  # Validate before anything is written in place.
        xml = spec.to_xml().replace(f'meshdir="{abs_dir}', f'meshdir="{asset_dir_name}')
        if asset_dir_name not in xml:
            raise OutputPathError(
                f"{out_path}: cannot point the exported XML at {asset_dir_name}/ (a folder "
                "name with XML special characters?); choose a plainer --out"
            )
        licence = src_meshdir.parent / "LICENSE"
        if licence.is_file():
            shutil.copy2(licence, tmp_assets / "LICENSE")
        if asset_dir.exists():
            shutil.rmtree(asset_dir)
        os.replace(tmp_assets, asset_dir)
    except OSError as e:
        raise OutputPathError(f"{out_path}: cannot write the model's meshes: {e}") from None
    finally:
        if tmp_assets.exists():
            shutil.rmtree(tmp_assets, ignore_errors=True)
    header = (
        f"<!-- humimic nominal model of {cfg.name}: {cfg.description}. "
        f"Model files: {cfg.license}; see {asset_dir_name}/LICENSE. -->\n"
    )
    atomic_write_text(out_path, header + xml)
    return out_path
