"""Self-collision pairs come from the model's collision geometry, and the report sees them all."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from humimic.retarget.metrics import evaluate
from humimic.robots import get_robot, nominal_model
from humimic.robots.collision import rest_distances, robot_geoms, self_collision_pairs, tree_path

LEG_LINKS = ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")


def _mujoco_filter_pairs(model: mujoco.MjModel, geoms: list[int]) -> set[tuple[int, int]]:
    """The geom pairs MuJoCo's contact filter lets through whatever the bitmasks, by its
    documented rule (Computation > Collision detection), written here body pair by body pair:
    two bodies collide unless they are one weld body, or one's weld body is the other's
    weld body's parent (filterparent, on by default), or an <exclude> names them."""
    by_body: dict[int, list[int]] = {}
    for g in geoms:
        by_body.setdefault(int(model.geom_bodyid[g]), []).append(g)
    excluded = set()
    for k in range(model.nexclude):
        sig = int(model.exclude_signature[k])
        excluded |= {(sig >> 16, sig & 0xFFFF), (sig & 0xFFFF, sig >> 16)}
    weld = [int(model.body(b).weldid[0]) for b in range(model.nbody)]
    out = set()
    for b1, g1s in by_body.items():
        for b2, g2s in by_body.items():
            w1, w2 = weld[b1], weld[b2]
            if b1 >= b2 or w1 == w2 or (b1, b2) in excluded:
                continue
            if weld[int(model.body_parentid[w1])] == w2 or weld[int(model.body_parentid[w2])] == w1:
                continue
            out |= {(min(a, b), max(a, b)) for a in g1s for b in g2s}
    return out


@pytest.mark.parametrize("robot", ["g1", "h1", "t1"])
def test_pairs_are_every_pair_mujocos_contact_filter_tests(robot: str) -> None:
    """No exemption by proximity at rest or by mechanism: the pairs are exactly those MuJoCo
    itself would test (same and parent-child bodies and <exclude> pairs left out)."""
    cfg = get_robot(robot)
    model = nominal_model(cfg)
    geoms = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] != 0 and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]
    assert geoms == robot_geoms(model, cfg.root_body)
    expected = _mujoco_filter_pairs(model, geoms)
    got = {(int(a), int(b)) for a, b in self_collision_pairs(model, cfg.root_body)}
    assert got == expected
    assert len(got) > 50


def test_a_pair_close_at_rest_may_come_no_closer_than_it_is_there() -> None:
    """The G1's torso and shoulder-yaw links are 7.8 mm apart at rest, under the 10 mm margin:
    they were dropped from the IK and the report, and the walk put a shoulder-yaw link 26 mm
    into the torso. Now each pair's floor is its rest distance where that is smaller."""
    from humimic.configs import retarget_default
    from humimic.retarget import Retargeter

    rt = Retargeter("g1", "cmu", retarget_default())
    limit = rt.ik.self_collision
    assert limit is not None
    m = rt.ik.model
    rest = rest_distances(m, np.array(limit.geom_id_pairs), 1.0)
    names = [tuple(m.body(m.geom_bodyid[g]).name for g in p) for p in limit.geom_id_pairs]
    shoulder = names.index(("torso_link", "left_shoulder_yaw_link"))
    assert 0.005 < rest[shoulder] < 0.01
    assert limit.floors[shoulder] == pytest.approx(rest[shoulder])
    mechanism = np.array([len(tree_path(m, *m.geom_bodyid[list(p)])) <= 2
                          for p in limit.geom_id_pairs])  # fmt: skip
    assert mechanism.sum() > 10  # E.g. the pelvis and each hip-roll link.
    np.testing.assert_allclose(limit.floors, np.minimum(rest, np.where(mechanism, 0.003, 0.01)))


def test_the_ik_constrains_the_pairs_the_report_measures() -> None:
    from humimic.configs import retarget_default
    from humimic.retarget import Retargeter

    rt = Retargeter("g1", "cmu", retarget_default())
    limit = rt.ik.self_collision
    assert limit is not None
    constrained = {tuple(sorted(map(int, p))) for p in limit.geom_id_pairs}
    measured = {(int(a), int(b)) for a, b in self_collision_pairs(rt.ik.model, "pelvis")}
    assert constrained == measured


def _wrist_into(model: mujoco.MjModel, wrist: int, target: int) -> np.ndarray:
    """A configuration (joint limits ignored, base fixed) with geom ``wrist``'s centre on geom
    ``target``'s: damped Gauss-Newton on the distance of the two centres."""
    data = mujoco.MjData(model)
    ja, jb = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for _ in range(200):
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        e = data.geom_xpos[wrist] - data.geom_xpos[target]
        if np.linalg.norm(e) < 1e-4:
            break
        mujoco.mj_jacGeom(model, data, ja, None, wrist)
        mujoco.mj_jacGeom(model, data, jb, None, target)
        J = (ja - jb)[:, 6:]  # Joints only: the base stays put.
        dq = np.zeros(model.nv)
        dq[6:] = -J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(3), e)
        mujoco.mj_integratePos(model, data.qpos, dq, 0.5)
    return data.qpos.copy()


def test_a_wrist_inside_any_leg_link_is_a_self_collision() -> None:
    """The hand-written groups this replaces left the hip-pitch links out; the CMU kick put a
    wrist 5-32 mm into them in 48 of 135 frames while the report said 0."""
    cfg = get_robot("g1")
    model = nominal_model(cfg)
    names = {model.body(model.geom_bodyid[g]).name: g for g in robot_geoms(model, cfg.root_body)}
    pairs = self_collision_pairs(model, cfg.root_body)
    wrist = names["left_wrist_yaw_link"]
    seen = []
    for side in ("left", "right"):
        for link in LEG_LINKS:
            body = f"{side}_{link}_link"
            target = names[body]
            q = _wrist_into(model, wrist, target)
            report, _ = evaluate(
                model,
                q[None],
                50.0,
                keypoint_sites=["imu_in_pelvis"],
                keypoint_targets=np.zeros((1, 1, 3)),
                foot_bodies=[f"{s}_ankle_roll_link" for s in ("left", "right")],
                self_collision=pairs,
            )
            data = mujoco.MjData(model)
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            depth = -mujoco.mj_geomDistance(model, data, wrist, target, 0.1, np.zeros(6))
            assert depth > 0.005, (body, depth)  # The placement worked: 5 mm or more inside.
            assert report.self_collision_frames == 1, body
            assert report.max_self_penetration_mm >= 1e3 * depth - 1e-6, body
            seen.append(body)
    assert len(seen) == 2 * len(LEG_LINKS)


def _independent_self_penetration(xml: Path, qpos: np.ndarray) -> tuple[int, float]:
    """Frames with a robot geom pair deeper than 1 mm inside each other beyond their overlap
    at rest, and the deepest [mm], on the exported model: every pair of geoms of the robot's bodies (parent and child
    bodies and one body's geoms left out), by ``mj_geomDistance``; this file's own pair
    list, not the project's."""
    m = mujoco.MjModel.from_xml_path(str(xml))
    geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] != 0
             and (m.geom_contype[g] or m.geom_conaffinity[g])]  # fmt: skip
    body = m.geom_bodyid
    # The model's own <exclude> pairs (the OP3's hip-yaw and hip-pitch links), by body id.
    excluded = {frozenset((int(s) >> 16, int(s) & 0xFFFF)) for s in m.exclude_signature}
    pairs = [(a, b) for i, a in enumerate(geoms) for b in geoms[i + 1 :]
             if body[a] != body[b] and m.body_parentid[body[a]] != body[b]
             and m.body_parentid[body[b]] != body[a]
             and frozenset((int(body[a]), int(body[b]))) not in excluded]  # fmt: skip
    data = mujoco.MjData(m)
    fromto = np.zeros(6)
    rest = {}  # The overlap of each pair in the model's own poses (qpos0, keyframes).
    for q in [m.qpos0, *m.key_qpos]:
        data.qpos[:] = q
        mujoco.mj_kinematics(m, data)
        for a, b in pairs:
            d = -mujoco.mj_geomDistance(m, data, a, b, 0.05, fromto)
            rest[a, b] = max(rest.get((a, b), 0.0), d)
    frames, deepest = 0, 0.0
    for q in qpos:
        data.qpos[:] = q
        mujoco.mj_kinematics(m, data)
        depth = max(-mujoco.mj_geomDistance(m, data, a, b, 0.05, fromto) - rest[a, b]
                    for a, b in pairs)  # fmt: skip
        frames += depth > 1e-3
        deepest = max(deepest, depth)
    return frames, 1e3 * deepest


@pytest.mark.parametrize(("robot", "clip"), [("g1", "35_01"), ("t1", "13_32"), ("apollo", "35_01")])
def test_the_reports_self_collision_equals_an_independent_all_pairs_check(
    robot: str, clip: str, shared_data: Path, tmp_path: Path
) -> None:
    """On a real clip, with the IK's self-collision limit off (so that there is something to
    count: the shoulder-yaw links go into the torso) and on: the report's frames and depth
    are those of the independent check on the exported model."""
    from dataclasses import replace

    from humimic.configs import retarget_default
    from humimic.datasets import load_clip
    from humimic.robots import export_nominal

    xml = export_nominal(get_robot(robot), tmp_path / f"{robot}.xml")
    source = load_clip(shared_data / "cmu" / f"{clip}.bvh").slice(1)
    counted = []
    for on in (False, True):
        from humimic.retarget import Retargeter

        rt = Retargeter(robot, source.skeleton, replace(retarget_default(), self_collision=on))
        out = rt.run(source)
        frames, deepest = _independent_self_penetration(xml, out.motion.qpos)
        assert out.report["self_collision_frames"] == frames, (on, frames)
        assert out.report["max_self_penetration_mm"] == pytest.approx(deepest, abs=1e-6)
        counted.append(frames)
    if robot == "g1":
        assert counted[0] > 10  # Off: the walk's arms go into the torso, seen by both.
    if robot == "apollo":
        assert counted[0] > 10  # Off: its hands go into its thighs (beyond their rest overlap).
    # On: no pair deeper than 1 mm (on the Apollo, 7 frames at 1.5 mm before the repair
    # checked every pair and line-searched its steps).
    assert counted[1] == 0


def test_a_pair_that_overlaps_at_rest_counts_only_deeper_than_there() -> None:
    """Two capsules of radius 5 cm whose axes are 8 cm apart at rest (2 cm overlap, as the
    Apollo's coarse arm capsules overlap its thighs): the report measures only what a pose
    adds, checked against the capsules' geometry by hand. The second capsule's axis is 4 cm
    from its hinge, the hinge 4 cm from the first axis: turned by theta, the axes are
    0.08 cos(theta / 2) apart."""
    xml = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 .1"/>
      <body name="base" pos="0 0 1"><freejoint/>
        <geom type="capsule" size="0.05 0.2"/>
        <body name="foot" pos="0 0 -0.6"><geom type="sphere" size="0.02"/></body>
        <body name="mid"><joint name="j1" axis="0 0 1"/><inertial pos="0 0 0" mass="0.1" diaginertia="1e-3 1e-3 1e-3"/>
          <body name="arm" pos="0.04 0 0"><joint name="j2" axis="0 0 1"/>
            <geom type="capsule" size="0.05 0.2" pos="0.04 0 0"/>
            <site name="s"/>
          </body></body></body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    pairs = self_collision_pairs(model, "base")
    assert len(pairs) == 2  # The capsules, and the foot with the second.
    theta = np.array([0.0, 0.3, 1.0, 2.0])
    qpos = np.tile(model.qpos0, (len(theta), 1))
    qpos[:, 8] = theta
    report, _ = evaluate(
        model, qpos, 50.0, keypoint_sites=["s"], keypoint_targets=np.zeros((len(theta), 1, 3)),
        foot_bodies=["foot"], self_collision=pairs,
    )  # fmt: skip
    beyond = (0.1 - 0.08 * np.cos(theta / 2)) - 0.02  # 0, 0.9, 9.8, 36.8 mm.
    assert report.self_collision_rest_overlaps == 1
    assert report.self_collision_frames == int(np.sum(beyond > 1e-3)) == 2
    assert report.max_self_penetration_mm == pytest.approx(1e3 * beyond.max(), abs=1e-6)


@pytest.mark.parametrize("robot", ["h1", "berkeley_humanoid"])
def test_crossed_legs_are_solved_again_until_they_uncross(
    robot: str, shared_data: Path, tmp_path: Path
) -> None:
    """The CMU backflip with the orientation-led stage on every frame (``stage1_iters`` 1,
    the default until it ran on the first frame only): one frame where that stage (no
    self-collision rows) carried one thigh through the other, which the repair could not
    undo (H1 60 mm, Berkeley Humanoid 23 mm). That frame is solved again with guarded steps,
    the report counts it, and the independent check finds no crossed frame."""
    import dataclasses

    from humimic.configs import retarget_default
    from humimic.datasets import load_clip
    from humimic.retarget import Retargeter
    from humimic.robots import export_nominal

    xml = export_nominal(get_robot(robot), tmp_path / f"{robot}.xml")
    source = load_clip(shared_data / "cmu" / "87_03.bvh").slice(1)
    cfg = dataclasses.replace(retarget_default(), stage1_iters=1)
    out = Retargeter(robot, source.skeleton, cfg).run(source)
    assert out.report["retried_frames"] >= 1
    frames, deepest = _independent_self_penetration(xml, out.motion.qpos)
    assert (frames, out.report["self_collision_frames"]) == (0, 0), deepest
