"""Build the MuJoCo model humimic simulates with: the robot's MJCF plus its explicit actuator
model. This module and the retargeter's configuration are the only places that compile MJCF."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from humimic.errors import InputError, OutputPathError
from humimic.io import atomic_write_text, check_writable
from humimic.robots.actuators import JointActuator
from humimic.robots.assets import find_robot_file
from humimic.robots.registry import RobotConfig


def robot_xml_path(
    cfg: RobotConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> Path:
    """Path of the robot's scene MJCF."""
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
    """
    path = robot_xml_path(cfg, menagerie_root=menagerie_root)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot load this model: {e}") from None
    spec.meshdir = str(Path(path).parent / (spec.meshdir or ""))
    # No compile-time magic left in the defaults either (dampratio, inheritrange).
    for default in [spec.default, *(a.classname for a in spec.actuators)]:
        default.actuator.gainprm = np.zeros(10)
        default.actuator.biasprm = np.zeros(10)
        default.actuator.inheritrange = 0.0
    joints = actuated_joints(spec)
    acts = cfg.actuators.resolve(joints)
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
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = np.array([-a.effort_limit, a.effort_limit])
    return spec, acts


def nominal_model(
    cfg: RobotConfig, *, menagerie_root: str | os.PathLike[str] | None = None
) -> mujoco.MjModel:
    """Compiled nominal model (robot, floor, explicit actuators)."""
    spec, _ = nominal_spec(cfg, menagerie_root=menagerie_root)
    return spec.compile()


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
    out_path = check_writable(out)
    spec, _ = nominal_spec(cfg, menagerie_root=menagerie_root)
    if edit is not None:
        edit(spec)
    src_meshdir = Path(spec.meshdir)
    asset_dir_name = f"{out_path.stem}_assets"
    asset_dir = out_path.parent / asset_dir_name
    tmp_assets = out_path.parent / f".{asset_dir_name}.tmp"
    if tmp_assets.exists():
        shutil.rmtree(tmp_assets)
    try:
        tmp_assets.mkdir()
        for mesh in spec.meshes:
            shutil.copy2(src_meshdir / mesh.file, tmp_assets / Path(mesh.file).name)
            mesh.file = Path(mesh.file).name
        abs_dir = str(tmp_assets.resolve())
        spec.meshdir = abs_dir
        spec.compile()  # Validate before anything is written in place.
        xml = spec.to_xml().replace(f'meshdir="{abs_dir}', f'meshdir="{asset_dir_name}')
        if asset_dir_name not in xml:
            raise RuntimeError("could not relocate the mesh folder in the exported XML")
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
