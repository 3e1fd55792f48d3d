"""IK terms: every Jacobian against finite differences; contact detection on synthetic signals."""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from humimic.retarget.contacts import detect_contacts, plant_segments, runs
from humimic.retarget.interaction_mesh import build_mesh
from humimic.retarget.limits import (
    FloorLimit,
    PointTravelLimit,
    SelfCollisionLimit,
)
from humimic.retarget.tasks import (
    InteractionMeshTask,
    KeypointsTask,
    OrientationsTask,
    PostureTask,
    SceneContactTask,
    rotation_log,
    so3_right_jacobian_inverse,
)

ARM_XML = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <body name="base" pos="0 0 0.6">
      <freejoint/>
      <geom name="torso" type="capsule" fromto="0 0 -0.2 0 0 0.2" size="0.08"/>
      <body name="upper" pos="0 0.15 0.1">
        <joint name="shoulder" axis="0 1 0" range="-2 2"/>
        <joint name="shoulder_roll" axis="1 0 0" range="-2 2"/>
        <geom name="upper_geom" type="capsule" fromto="0 0 0 0 0 -0.25" size="0.03"/>
        <body name="lower" pos="0 0 -0.25">
          <joint name="elbow" axis="0 1 0" range="-2.5 0.1"/>
          <geom name="lower_geom" type="capsule" fromto="0 0 0 0.25 0 0" size="0.025"/>
          <site name="hand" pos="0.25 0 0"/>
          <site name="elbow_site" pos="0 0 0"/>
        </body>
      </body>
      <body name="foot" pos="0 0 -0.5">
        <joint name="hip" axis="0 1 0" range="-1 1"/>
        <geom name="sole" type="sphere" size="0.02" pos="0.05 0 -0.05"/>
        <geom name="heel" type="box" size="0.03 0.02 0.01" pos="-0.05 0 -0.05"/>
        <site name="foot_site" pos="0 0 -0.05"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture
def arm() -> mink.Configuration:
    model = mujoco.MjModel.from_xml_string(ARM_XML)
    conf = mink.Configuration(model)
    q = model.qpos0.copy()
    q[3:7] = Rotation.from_euler("xyz", [0.2, -0.3, 0.5]).as_quat(scalar_first=True)
    q[7:] = [0.4, 0.5, -1.1, 0.3]
    conf.update(q)
    return conf


def fd_jacobian(conf: mink.Configuration, f, eps: float = 1e-6) -> np.ndarray:
    """Central finite differences of f(configuration) along each tangent direction."""
    q0 = conf.q.copy()
    cols = []
    for i in range(conf.model.nv):
        dq = np.zeros(conf.model.nv)
        dq[i] = eps
        conf.update(q0)
        conf.integrate_inplace(dq, 1.0)
        fp = f(conf)
        conf.update(q0)
        conf.integrate_inplace(-dq, 1.0)
        fm = f(conf)
        cols.append((fp - fm) / (2 * eps))
    conf.update(q0)
    return np.stack(cols, axis=1)


def test_keypoints_task_jacobian(arm: mink.Configuration) -> None:
    task = KeypointsTask(arm.model, ["hand"])
    task.targets = np.array([[0.1, 0.2, 0.3]])
    jac = task.compute_jacobian(arm)
    fd = fd_jacobian(arm, lambda c: task.compute_error(c).copy())
    np.testing.assert_allclose(jac, fd, atol=1e-6)


@pytest.mark.parametrize("angle", [0.1, 1.0, 2.5])
def test_orientations_task_jacobian(arm: mink.Configuration, angle: float) -> None:
    task = OrientationsTask(arm.model, ["lower", "base"])
    current = arm.data.xmat[[arm.model.body("lower").id, arm.model.body("base").id]]
    offsets = Rotation.from_rotvec(np.array([[angle, 0.0, 0.0], [0.0, 0.0, angle]])).as_matrix()
    task.targets = current.reshape(-1, 3, 3) @ offsets  # Errors of about `angle` radians.
    err = task.compute_error(arm)
    np.testing.assert_allclose(np.linalg.norm(err.reshape(2, 3), axis=1), angle, atol=1e-9)
    jac = task.compute_jacobian(arm)
    fd = fd_jacobian(arm, lambda c: task.compute_error(c).copy())
    np.testing.assert_allclose(jac, fd, atol=1e-5)


def test_floor_limit_rows_are_height_derivatives(arm: mink.Configuration) -> None:
    limit = FloorLimit(arm.model, ["foot"])
    # A sphere (one point) and a box (eight corners).
    assert len(limit.ids) == 9
    cons = limit.compute_qp_inequalities(arm, 1.0)
    assert cons.G is not None and cons.h is not None

    def bottoms(c: mink.Configuration) -> np.ndarray:
        h = limit.compute_qp_inequalities(c, 1.0).h  # h = height - floor
        assert h is not None
        return h.copy()

    fd = fd_jacobian(arm, bottoms)
    np.testing.assert_allclose(-cons.G, fd, atol=1e-6)
    expected_sphere_bottom = arm.data.geom_xpos[arm.model.geom("sole").id][2] - 0.02
    assert cons.h[0] == pytest.approx(expected_sphere_bottom)


MESH_FOOT_XML = """
<mujoco>
  <asset>
    <!-- A foot mesh whose toe reaches 3 cm ahead of and 1 cm under its sole box, as an added
         robot's mesh foot does on the box it is given; one vertex inside the hull. -->
    <mesh name="foot_mesh" vertex="-0.06 -0.03 0  0.08 -0.03 0  0.08 0.03 0  -0.06 0.03 0
                                    -0.05 0 -0.02  0.11 0.01 -0.03  0.02 0 0.04  0 0 0"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <body name="base" pos="0 0 0.4">
      <freejoint/>
      <geom name="torso" type="capsule" fromto="0 0 -0.1 0 0 0.1" size="0.05"/>
      <body name="foot" pos="0 0 -0.3">
        <joint name="ankle" axis="0 1 0" range="-1 1"/>
        <geom name="sole" type="box" size="0.07 0.03 0.01" pos="0.01 0 -0.03"/>
        <geom name="shell" type="mesh" mesh="foot_mesh" pos="0 0 -0.02"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("pitch", [-0.5, -0.2, 0.0, 0.3, 0.6])
def test_floor_limit_keeps_a_mesh_foot_above_the_floor_not_only_its_box(pitch: float) -> None:
    """A foot mesh beyond its sole box (Romeo's and Talos's went 11-28 mm into the floor at
    toe-off while the box stayed above): the limit's lowest point is the mesh's lowest, as
    MuJoCo's own plane-mesh distance says, and its rows are height derivatives."""
    model = mujoco.MjModel.from_xml_string(MESH_FOOT_XML)
    conf = mink.Configuration(model)
    q = model.qpos0.copy()
    q[2] = 0.39
    q[3:7] = Rotation.from_euler("xyz", [0.15, 0.1, 0.4]).as_quat(scalar_first=True)
    q[7] = pitch
    conf.update(q)
    limit = FloorLimit(model, ["foot"])
    assert len(limit.meshes) == 1 and len(limit.meshes[0][1]) == 7  # The hull, not the inner one.
    cons = limit.compute_qp_inequalities(conf, 1.0)
    assert cons.G is not None and cons.h is not None
    n_rows = len(cons.h)
    floor, shell, sole = (model.geom(n).id for n in ("floor", "shell", "sole"))
    fromto = np.zeros(6)
    mesh_low = mujoco.mj_geomDistance(model, conf.data, floor, shell, 1.0, fromto)
    box_low = mujoco.mj_geomDistance(model, conf.data, floor, sole, 1.0, fromto)
    assert float(cons.h.min()) == pytest.approx(min(mesh_low, box_low), abs=1e-9)
    assert float(cons.h[8:].min()) == pytest.approx(mesh_low, abs=1e-9)  # After the 8 corners.

    def heights(c: mink.Configuration) -> np.ndarray:
        h = limit.compute_qp_inequalities(c, 1.0).h
        assert h is not None and len(h) == n_rows  # The same points either side.
        return h.copy()

    np.testing.assert_allclose(-cons.G, fd_jacobian(conf, heights), atol=1e-6)


def test_a_mesh_foot_pitched_into_the_floor_is_seen_where_its_box_is_not() -> None:
    """The case the box alone missed: toe down, the box above the floor, the mesh 1 cm in."""
    model = mujoco.MjModel.from_xml_string(MESH_FOOT_XML)
    conf = mink.Configuration(model)
    floor, shell, sole = (model.geom(n).id for n in ("floor", "shell", "sole"))
    q = model.qpos0.copy()
    q[7] = 0.2
    conf.update(q)
    fromto = np.zeros(6)
    q[2] -= mujoco.mj_geomDistance(model, conf.data, floor, sole, 1.0, fromto) - 0.001
    conf.update(q)  # The box's lowest corner 1 mm above the floor.
    mesh_low = mujoco.mj_geomDistance(model, conf.data, floor, shell, 1.0, fromto)
    assert mesh_low < -0.005
    limit = FloorLimit(model, ["foot"])
    h = limit.compute_qp_inequalities(conf, 1.0).h
    assert h is not None
    assert h[:8].min() == pytest.approx(0.001)
    assert h[8:].min() == pytest.approx(mesh_low)


def test_point_travel_limit_rows_and_step(arm: mink.Configuration) -> None:
    model = arm.model
    body = model.body("lower").id
    point = np.array([[0.05, 0.02, -0.1]])
    limit = PointTravelLimit(model, np.array([body]), point)
    assert limit.compute_qp_inequalities(arm, 1.0).G is None  # Free until a radius is set.
    start = limit.positions(arm.data)
    np.testing.assert_allclose(  # The point in the world, as MuJoCo moves it.
        start[0], arm.data.xpos[body] + arm.data.xmat[body].reshape(3, 3) @ point[0], atol=1e-12
    )
    anchor = start + np.array([[0.004, -0.003, 0.5]])  # Height does not count.
    limit.set(anchor, np.array([0.01]))
    cons = limit.compute_qp_inequalities(arm, 1.0)
    assert cons.G is not None and cons.h is not None and cons.G.shape == (8, model.nv)

    def slack(c: mink.Configuration) -> np.ndarray:
        h = limit.compute_qp_inequalities(c, 1.0).h
        assert h is not None
        return h.copy()

    np.testing.assert_allclose(-cons.G, fd_jacobian(arm, slack), atol=1e-6)
    d = (start - anchor)[0, :2]
    assert np.all(cons.h > 0) and np.linalg.norm(d) < 0.01 * np.cos(np.pi / 8)
    # A step that would carry the point 5 cm away is cut back to the octagon, to first order.
    jac = np.zeros((3, model.nv))
    mujoco.mj_jac(model, arm.data, jac, None, start[0], body)
    pull = np.linalg.pinv(jac[:2]) @ np.array([0.05, 0.0])
    scale = min(1.0, float(np.min(np.where(cons.G @ pull > 0, cons.h / (cons.G @ pull), np.inf))))
    assert scale < 0.5
    arm.integrate_inplace(scale * pull, 1.0)
    moved = limit.positions(arm.data)[0, :2] - anchor[0, :2]
    assert np.linalg.norm(moved) <= 0.01 + 1e-4


def test_self_collision_limit_row_is_distance_derivative(arm: mink.Configuration) -> None:
    model = arm.model
    g1, g2 = model.geom("lower_geom").id, model.geom("torso").id
    limit = SelfCollisionLimit(
        model, np.array([[g1, g2]]), np.zeros(1), gain=1.0, collision_detection_distance=1.0
    )
    cons = limit.compute_qp_inequalities(arm, 1.0)
    assert cons.G is not None and cons.h is not None

    def dist(c: mink.Configuration) -> np.ndarray:
        return np.array([mujoco.mj_geomDistance(model, c.data, g1, g2, 1.0, np.zeros(6))])

    d0 = dist(arm)[0]
    assert 0 < d0 < 1.0
    fd = fd_jacobian(arm, dist)
    # Row: -d(dist)/dq; bound: the distance itself (gain 1, zero margin).
    np.testing.assert_allclose(-cons.G[0], fd[0], atol=1e-5)
    assert cons.h[0] == pytest.approx(d0)
    assert limit.min_slack == pytest.approx(d0)


def test_self_collision_rows_equal_minks_pair_by_pair() -> None:
    """The limit's rows, built for all near pairs at once, equal mink's own per-pair
    ``compute_contact_normal_jacobian`` (signed as the limit signs them) on the G1's 579 pairs
    in random poses."""
    from mink.limits.collision_avoidance_limit import compute_contact_normal_jacobian

    from humimic.robots import get_robot, nominal_model
    from humimic.robots.collision import self_collision_pairs

    robot = get_robot("g1")
    model = nominal_model(robot)
    pairs = self_collision_pairs(model, robot.root_body)
    limit = SelfCollisionLimit(model, pairs, np.zeros(len(pairs)), gain=0.85,
                               collision_detection_distance=0.04)  # fmt: skip
    conf = mink.Configuration(model)
    rng = np.random.default_rng(5)
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    ft, normal = np.zeros(6), np.zeros(3)
    j1, j2 = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    checked = 0
    for _ in range(5):
        q = model.qpos0.copy()
        q[7:] = lo + (hi - lo) * rng.random(lo.size)
        conf.update(q)
        cons = limit.compute_qp_inequalities(conf, 1.0)
        assert cons.G is not None and cons.h is not None
        for i, (a, b) in enumerate(pairs):
            d = mujoco.mj_geomDistance(model, conf.data, int(a), int(b), 0.04, ft)
            if d >= 0.04 - 1e-12:
                assert np.isinf(cons.h[i])
                continue
            row = compute_contact_normal_jacobian(model, conf.data, int(a), int(b), ft, normal,
                                                  j1, j2)  # fmt: skip
            np.testing.assert_allclose(cons.G[i], (-1.0 if d >= 0 else 1.0) * row, atol=1e-12)
            assert cons.h[i] == pytest.approx(0.85 * d)
            checked += 1
    assert checked > 30


def test_self_collision_limit_pushes_out_penetrating_pairs() -> None:
    xml = """<mujoco><worldbody>
      <body name="a"><joint name="x" type="slide" axis="1 0 0"/>
        <geom name="ga" type="sphere" size="0.1"/></body>
      <body name="b" pos="0.15 0 0"><joint name="y" type="slide" axis="0 1 0"/>
        <geom name="gb" type="sphere" size="0.1"/></body>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    conf = mink.Configuration(model)
    pair = np.array([[model.geom("ga").id, model.geom("gb").id]])
    limit = SelfCollisionLimit(
        model, pair, np.full(1, 0.01), gain=0.5, collision_detection_distance=0.2
    )
    cons = limit.compute_qp_inequalities(conf, 1.0)
    assert cons.G is not None and cons.h is not None
    # Penetration 5 cm: moving a by dx changes the distance by -dx. The limit must demand
    # dx <= -0.5 * (0.05 + 0.01), i.e. a push apart, not merely "no closer".
    assert cons.G[0, 0] * 1.0 > 0
    assert cons.h[0] == pytest.approx(0.5 * (-0.05 - 0.01))
    # Each pair's own floor: one that overlapped 2 cm at rest may not go deeper than that.
    limit = SelfCollisionLimit(model, pair, np.full(1, -0.02), gain=0.5,
                               collision_detection_distance=0.2)  # fmt: skip
    cons = limit.compute_qp_inequalities(conf, 1.0)
    assert cons.h is not None and cons.h[0] == pytest.approx(0.5 * (-0.05 + 0.02))


def test_rotation_log_and_right_jacobian() -> None:
    rots = Rotation.random(500, rng=np.random.default_rng(3))
    np.testing.assert_allclose(rotation_log(rots.as_matrix()), rots.as_rotvec(), atol=1e-9)
    near_pi = Rotation.from_rotvec([[np.pi - 1e-5, 0, 0], [0, 0, 1e-9]])
    np.testing.assert_allclose(rotation_log(near_pi.as_matrix()), near_pi.as_rotvec(), atol=1e-7)
    # Jr^{-1}(phi) maps a small right perturbation to the change of log: check by differences.
    phi = np.array([[0.3, -0.7, 1.1]])
    jinv = so3_right_jacobian_inverse(phi)[0]
    base = Rotation.from_rotvec(phi[0])
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-6
        plus = (base * Rotation.from_rotvec(d)).as_rotvec()
        minus = (base * Rotation.from_rotvec(-d)).as_rotvec()
        np.testing.assert_allclose((plus - minus) / 2e-6, jinv[:, i], atol=1e-6)


def test_runs_and_contacts() -> None:
    assert runs(np.array([0, 1, 1, 0, 1], dtype=bool)) == [(1, 3), (4, 5)]
    assert runs(np.zeros(4, dtype=bool)) == []
    fps = 50.0
    t = np.arange(100) / fps
    heights = np.where((t > 0.5) & (t < 1.2), 0.005, 0.2)
    xy = np.zeros((100, 2))
    xy[:, 0] = np.where(heights < 0.01, 1.0, t)  # Still while down.
    c = detect_contacts(heights, xy, fps, max_height=0.05, max_speed=0.3, min_frames=2)
    (run,) = runs(c)
    assert 25 <= run[0] <= 27 and 59 <= run[1] <= 61
    # A fast-moving low point is not in contact.
    xy_fast = np.stack([t * 3.0, np.zeros_like(t)], axis=1)
    assert not detect_contacts(heights, xy_fast, fps, max_height=0.05, max_speed=0.3).any()


def test_plant_segments_split_on_drift() -> None:
    flags = np.ones(10, dtype=bool)
    xy = np.zeros((10, 2))
    xy[:, 0] = np.arange(10) * 0.01  # Drifts 1 cm per frame.
    segs = plant_segments(flags, xy, radius=0.025)
    assert segs[0] == (0, 3) and segs[-1][1] == 10
    for a, b in segs:
        assert np.abs(xy[a:b, 0] - xy[a, 0]).max() <= 0.025


@pytest.mark.parametrize("weighting", ["uniform", "inverse_distance"])
def test_interaction_mesh_task_jacobian(arm: mink.Configuration, weighting: str) -> None:
    sites = ["hand", "elbow_site", "foot_site"]
    rng = np.random.default_rng(3)
    robot_now = np.array([arm.data.site(s).xpos for s in sites])
    # The source (human) mesh: the sites moved a little, and scene points around them.
    source = robot_now + 0.05 * rng.standard_normal(robot_now.shape)
    scene = robot_now.mean(axis=0) + 0.4 * rng.standard_normal((12, 3))
    task = InteractionMeshTask(arm.model, sites, cost=2.0)
    task.set_mesh(build_mesh(source, scene, weighting=weighting))
    err = task.compute_error(arm)
    assert err.shape == (3 * 15,) and np.abs(err).max() > 1e-3  # Deformed: a real test.
    jac = task.compute_jacobian(arm)
    np.testing.assert_allclose(jac, fd_jacobian(arm, task.compute_error), atol=1e-6)
    # At the source configuration the error vanishes: the residual is relative to the source.
    assert task.mesh is not None
    np.testing.assert_allclose(task.mesh.residual(source), 0.0, atol=1e-12)


def test_scene_contact_task_error_gap_and_jacobian(arm: mink.Configuration) -> None:
    """The signed distance of a body to a surface, minus the gap aimed for; its Jacobian."""
    model = arm.model
    lower, torso = model.geom("lower_geom").id, model.geom("torso").id
    task = SceneContactTask(model, [[lower], [torso]], cost=3.0, reach=1.0)
    task.set_contacts([(0, model.geom("floor").id), (1, model.geom("floor").id)])
    d = task.compute_error(arm)
    # The torso capsule's lowest point (half-length 0.2, radius 0.08) over the floor plane.
    axis_z = arm.data.geom_xmat[torso].reshape(3, 3)[2, 2]
    lowest = arm.data.geom_xpos[torso][2] - 0.2 * abs(axis_z) - 0.08
    assert d[1] == pytest.approx(lowest, abs=1e-9)
    task.gap = 0.01
    np.testing.assert_allclose(task.compute_error(arm), d - 0.01, atol=1e-12)
    jac = task.compute_jacobian(arm)
    assert np.abs(jac).max() > 0.5  # The base's height moves both distances one to one.
    np.testing.assert_allclose(jac, fd_jacobian(arm, task.compute_error), atol=1e-6)


def test_posture_objective_equals_minks_dense_one(arm: mink.Configuration) -> None:
    """The diagonal posture objective is mink's own (its dense J'WJ, J'We path), floating
    base excluded, at a turned base and bent joints, for a scalar and a per-dof cost."""
    model = arm.model
    q = model.qpos0.copy()
    q[3:7] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_quat(scalar_first=True)
    q[7:] = np.linspace(-1.1, 0.4, model.nq - 7)
    arm.update(q)
    target = model.qpos0.copy()
    target[:3] = [0.2, -0.1, 0.9]
    for cost in (0.3, np.linspace(0.1, 0.9, model.nv)):
        ours, theirs = PostureTask(model, cost=1.0), mink.PostureTask(model, cost=1.0)
        for task in (ours, theirs):
            task.set_cost(cost)
            task.set_target(target)
        a, b = ours.compute_qp_objective(arm), theirs.compute_qp_objective(arm)
        np.testing.assert_array_equal(a.H, b.H)
        np.testing.assert_allclose(a.c, b.c, rtol=0, atol=1e-15)
        assert np.all(a.H[:6] == 0) and np.any(a.c[6:] != 0)
