"""The Pinocchio adapter: its model against MuJoCo's, and payload identification on logs of
``humimic sysid simulate``."""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np
import pytest

from humimic.errors import InputError, UnknownNameError
from humimic.real2sim import LogSettings, read_robot_log, simulate_log, write_robot_log
from humimic.real2sim.pinocchio import (
    PayloadFit,
    PinocchioRobot,
    accelerations,
    identify_payload,
    pin,
)
from humimic.robots import get_robot
from humimic.robots.model import nominal_model, nominal_spec
from humimic.sim.effects import parse_injection

# Two hinges on one body (the second's axis turned by the first), an unaligned hinge, a
# slide, a body without joints (fused into its parent's joint), rotated inertia frames,
# armature, damping: every path of the model builder.
TREE = """
<mujoco>
  <option gravity="0.3 -0.2 -9.81"/>
  <worldbody>
    <body name="a" pos="0.1 0 1" quat="0.9 0.1 0.3 0.2">
      <freejoint/>
      <inertial pos="0.01 0.02 -0.03" mass="2" diaginertia="0.03 0.02 0.01"
                quat="0.8 0.2 0.1 0.4"/>
      <body name="b" pos="0 0.2 0" quat="0.7 0.7 0 0">
        <joint name="j1" type="hinge" axis="1 0 0" pos="0.05 0 0" armature="0.02"/>
        <joint name="j2" type="hinge" axis="0.3 1 0.2" pos="0 0.04 0.01" damping="0.5"/>
        <inertial pos="0 0 -0.1" mass="1.2" diaginertia="0.02 0.02 0.004"
                  quat="0.9 0 0.4 0.1"/>
        <body name="c" pos="0 0 -0.2" quat="0.95 0 0.3 0">
          <inertial pos="0.03 0 0" mass="0.4" diaginertia="0.002 0.003 0.001"/>
          <body name="d" pos="0.1 0 0">
            <joint name="s" type="slide" axis="0.2 0.1 1" armature="0.1"/>
            <inertial pos="0 0.02 0" mass="0.7" diaginertia="0.004 0.003 0.002"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _random_state(model: mujoco.MjModel, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    q = model.qpos0.copy()
    q[:3] = rng.normal(size=3)
    q[3:7] = rng.normal(size=4)
    q[3:7] /= np.linalg.norm(q[3:7])
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    lo, hi = np.where(model.jnt_limited[1:], lo, -1.0), np.where(model.jnt_limited[1:], hi, 1.0)
    q[7:] = rng.uniform(lo, hi)
    return q, rng.normal(size=model.nv), 5.0 * rng.normal(size=model.nv)


def _inverse(model: mujoco.MjModel, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``mj_inverse`` without constraints or passive forces: ``M qdd + C qd + g``."""
    m = copy.copy(model)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_DAMPER)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SPRING)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qacc[:] = q, v, a
    mujoco.mj_inverse(m, d)
    return d.qfrc_inverse.copy()


@pytest.mark.parametrize("robot", ["g1", "h1", "t1"])
def test_model_matches_mujoco(robot: str) -> None:
    mj = nominal_model(get_robot(robot))
    r = PinocchioRobot.from_mujoco(mj)
    assert r.free_base and (r.model.nq, r.model.nv) == (mj.nq, mj.nv)
    assert r.joint_names == tuple(mj.joint(j).name for j in range(1, mj.njnt))
    assert tuple(r.model.names)[2:] == r.joint_names  # universe, the free base, the joints
    # One body per joint on these robots: each joint's inertia is its body's.
    for j in range(1, mj.njnt):
        b = int(mj.jnt_bodyid[j])
        assert r.model.inertias[j + 1].mass == pytest.approx(mj.body_mass[b], abs=1e-9)
    assert r.model.inertias[1].mass == pytest.approx(mj.body_mass[1], abs=1e-9)
    np.testing.assert_allclose(r.model.armature, mj.dof_armature, atol=1e-12)
    np.testing.assert_allclose(r.friction_loss, mj.dof_frictionloss, atol=1e-12)
    data = mujoco.MjData(mj)
    rng = np.random.default_rng(3)
    for _ in range(10):
        q, v, a = _random_state(mj, rng)
        data.qpos[:] = q
        mujoco.mj_kinematics(mj, data)
        mujoco.mj_comPos(mj, data)
        pq, _, _ = r.to_pinocchio(q, v, a)
        pin.framesForwardKinematics(r.model, r.data, pq)
        for b in range(1, mj.nbody):
            pose = r.data.oMf[r.model.getFrameId(mj.body(b).name)]
            np.testing.assert_allclose(pose.translation, data.xpos[b], atol=1e-9)
            np.testing.assert_allclose(pose.rotation, data.xmat[b].reshape(3, 3), atol=1e-9)
        com = pin.centerOfMass(r.model, r.data, pq)
        np.testing.assert_allclose(com, data.subtree_com[1], atol=1e-9)
        np.testing.assert_allclose(
            r.inverse_dynamics(q[None], v[None], a[None])[0], _inverse(mj, q, v, a), atol=1e-6
        )


def test_every_joint_kind_and_a_fused_body_match_mujoco() -> None:
    mj = mujoco.MjModel.from_xml_string(TREE)
    r = PinocchioRobot.from_mujoco(mj)
    assert r.joint_names == ("j1", "j2", "s")
    assert r.body_joint["c"] == r.body_joint["b"]  # c has no joint: fused into b's.
    np.testing.assert_allclose(r.damping, mj.dof_damping)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q, v, a = _random_state(mj, rng)
        np.testing.assert_allclose(
            r.inverse_dynamics(q[None], v[None], a[None])[0], _inverse(mj, q, v, a), atol=1e-9
        )


def test_fixed_base_matches_a_welded_mujoco_model() -> None:
    cfg = get_robot("g1")
    pose = np.array([0.1, -0.2, 1.0, 0.9, 0.1, -0.1, 0.2])
    pose[3:] /= np.linalg.norm(pose[3:])
    spec, _ = nominal_spec(cfg)
    root = spec.body(cfg.root_body)
    spec.delete(root.joints[0])
    root.pos, root.quat = pose[:3], pose[3:]
    for key in list(spec.keys):
        spec.delete(key)
    welded = spec.compile()
    r = PinocchioRobot.from_mujoco(nominal_model(cfg), base_pose=pose)
    assert not r.free_base and r.model.nv == welded.nv
    rng = np.random.default_rng(1)
    for _ in range(10):
        q = rng.uniform(welded.jnt_range[:, 0], welded.jnt_range[:, 1])
        v, a = rng.normal(size=welded.nv), rng.normal(size=welded.nv)
        np.testing.assert_allclose(
            pin.rnea(r.model, r.data, q, v, a), _inverse(welded, q, v, a), atol=1e-6
        )


def test_ball_joints_are_refused() -> None:
    xml = """<mujoco><worldbody><body><joint type="ball"/><geom size="0.1"/></body>
    </worldbody></mujoco>"""
    with pytest.raises(InputError, match="BALL"):
        PinocchioRobot.from_mujoco(mujoco.MjModel.from_xml_string(xml))


def test_accelerations_skip_samples_across_a_command() -> None:
    t = np.arange(10) * 0.005
    qd = (t**2)[:, None] * np.ones((1, 2))
    qdd, valid = accelerations(t, qd, breaks=np.array([0.02, 0.0325]))
    np.testing.assert_allclose(qdd[1:-1], 2.0 * t[1:-1, None] * np.ones((1, 2)), atol=1e-12)
    # 0.02 is sample 4 (invalid: a jump at it), 0.0325 lies between samples 6 and 7.
    assert valid.tolist() == [False, True, True, True, False, True, False, False, True, False]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``humimic sysid simulate`` logs (MCAP) of the G1: a hidden wrist payload, none."""
    robot = get_robot("g1")
    out = {}
    for name, inj in (("wrist", ["payload_mass:right_wrist_yaw_link=0.6"]), ("clean", [])):
        log = simulate_log(robot, [parse_injection(x) for x in inj], LogSettings(duration=12.0))
        out[name] = write_robot_log(log, tmp_path_factory.mktemp(name) / "log.mcap")
    return out


def _fit(path: Path, body: str, *, fit_com: bool = False) -> PayloadFit:
    mj = nominal_model(get_robot("g1"))
    log = read_robot_log(path, tuple(mj.joint(j).name for j in range(1, mj.njnt)))
    r = PinocchioRobot.from_mujoco(mj, base_pose=log.base_pose)
    qdd, valid = accelerations(log.t, log.qd, log.t_cmd)
    assert log.effort is not None
    return identify_payload(r, log.q, log.qd, qdd, log.effort, body, samples=valid, fit_com=fit_com)


def test_payload_is_recovered_from_a_simulated_log(logs: dict[str, Path]) -> None:
    fit = _fit(logs["wrist"], "right_wrist_yaw_link")
    assert fit.mass == pytest.approx(0.6, abs=0.02)
    assert fit.mass_std < 0.01
    nothing = _fit(logs["clean"], "right_wrist_yaw_link")
    assert abs(nothing.mass) < 0.02
    # Where the mass sits: at the wrist link's centre of mass, as the effect adds it.
    placed = _fit(logs["wrist"], "right_wrist_yaw_link", fit_com=True)
    mj = nominal_model(get_robot("g1"))
    assert placed.mass == pytest.approx(0.6, abs=0.03) and placed.mass_std < 0.02
    np.testing.assert_allclose(placed.com, mj.body("right_wrist_yaw_link").ipos, atol=0.015)


def test_a_mass_its_joints_cannot_separate_from_its_moment_says_so(
    logs: dict[str, Path],
) -> None:
    # The waist's three axes meet near the torso's joint frame: only m c shows, and the
    # standard error says the mass is unknown; at the body's centre of mass it is sized.
    assert _fit(logs["clean"], "torso_link", fit_com=True).mass_std > 100.0
    fit = _fit(logs["clean"], "torso_link")
    assert fit.mass_std < 0.5 and abs(fit.mass) < 3 * fit.mass_std
    # A hip pitch link's mass moment along the hip pitch axis moves no joint of the gantry.
    blind = _fit(logs["clean"], "right_hip_pitch_link", fit_com=True)
    assert np.isnan(blind.mass) and blind.mass_std == np.inf


def test_identify_payload_refuses_what_it_cannot_use() -> None:
    mj = nominal_model(get_robot("g1"))
    floating = PinocchioRobot.from_mujoco(mj)
    x = np.zeros((5, mj.nv))
    with pytest.raises(InputError, match="fixed-base"):
        identify_payload(floating, x, x, x, x, "torso_link")
    fixed = PinocchioRobot.from_mujoco(mj, base_pose=np.array([0, 0, 1.0, 1, 0, 0, 0]))
    x = np.zeros((5, fixed.model.nv))
    with pytest.raises(UnknownNameError, match="no body 'hand'"):
        identify_payload(fixed, x, x, x, x, "hand")
    with pytest.raises(InputError, match="tau: expected shape"):
        identify_payload(fixed, x, x, x, x[:, :3], "torso_link")
    with pytest.raises(InputError, match="no sample moves"):
        identify_payload(fixed, x, x, x, x, "torso_link")
