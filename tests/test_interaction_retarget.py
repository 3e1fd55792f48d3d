"""Interaction-mesh retargeting on a real walk with a synthetic scene, and on the CLI."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.configs import InteractionConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.datasets.scene import Scene, SceneObject, box_mesh
from humimic.motion import load_motion
from humimic.retarget import Retargeter, RetargetOutput

PAD_HEIGHT = 0.08  # Human scale [m]: 6 cm on the robot's side.


def _pad_under_feet(shared_data: Path) -> tuple[Path, Scene]:
    """The CMU walk (0.8 s) and a pad that covers every footfall: the human walks *through*
    it (its feet are on the floor, the pad's top is 8 cm higher), so the robot must step
    onto it to keep out."""
    path = shared_data / "cmu" / "35_01.bvh"
    clip = load_clip(path).slice(1, 97)
    feet = np.concatenate([clip.position(n) for n in ("LeftFoot", "RightFoot", "LeftToeBase")])
    lo, hi = feet[:, :2].min(axis=0) - 0.4, feet[:, :2].max(axis=0) + 0.4
    v, f = box_mesh(np.array([*(hi - lo), PAD_HEIGHT]))
    pose = np.array([[*(lo + hi) / 2, PAD_HEIGHT / 2, 1.0, 0.0, 0.0, 0.0]])
    return path, Scene(objects=(SceneObject(name="pad", vertices=v, faces=f, poses=pose),),
                       source="pad")  # fmt: skip


@cache
def _walk_on_pad(root: Path) -> RetargetOutput:
    path, scene = _pad_under_feet(root)
    clip = load_clip(path).slice(1, 97)
    r = Retargeter("g1", "cmu", RetargetConfig(fps=30.0), method="interaction-mesh",
                   mesh=InteractionConfig())  # fmt: skip
    return r.run(clip, scene=scene)


def test_kinematic_walks_through_the_pad_interaction_mesh_steps_onto_it(shared_data: Path) -> None:
    r = _walk_on_pad(shared_data).report
    kin = r["kinematic"]
    # The kinematic warm start ignores the pad: its feet stand inside it (6 cm high on the
    # robot's side, its bottom on the floor).
    assert kin["max_scene_penetration_mm"] > 25.0, kin
    assert kin["scene_penetration_frames"] >= r["frames"] // 2
    assert r["max_scene_penetration_mm"] <= 10.0, r
    assert r["scene_penetration_frames"] <= 1
    assert r["joint_limit_violations"] == 0 and r["max_ground_penetration_mm"] <= 5.0
    # Feet stay on the pad's top. (The human's swing foot passes through the pad too, which
    # counts as a contact the robot, stepping over the pad, does not keep.)
    assert r["human_contacts"] > 0 and r["contact_preservation"] >= 0.75
    # ... resting on it, not floating above it (with daqp 0.11 a wrongly accepted QP step threw
    # the robot 0.75 m back: its planted feet were 168 mm above the pad, key points 568 mm off).
    assert r["planted_foot_gap_mm"] <= 10.0, r["planted_foot_gap_mm"]
    assert r["keypoint_error_mm_mean"] <= 40.0, r["keypoint_error_mm_mean"]


@pytest.mark.parametrize("robot", ["t1", "op3"])
def test_box_feet_step_onto_the_pad_not_into_it(
    robot: str, shared_data: Path, tmp_path: Path
) -> None:
    """The T1's and the OP3's feet are boxes: one pair of witness points per foot and object
    let the foot turn about them into the pad (48 and 20 mm, in 24 and 17 frames). Their sole
    corners are kept out of the scene too. The report's self-collision is the independent
    all-pairs check's on the exported robot (the corners renumber the robot's geoms in the
    model with the scene: the report once measured the scene-less model's pair ids there)."""
    from humimic.robots import export_nominal, get_robot
    from test_self_collision import _independent_self_penetration

    path, scene = _pad_under_feet(shared_data)
    clip = load_clip(path).slice(1, 97)
    out = Retargeter(robot, "cmu", RetargetConfig(fps=30.0), method="interaction-mesh",
                     mesh=InteractionConfig()).run(clip, scene=scene)  # fmt: skip
    r = out.report
    frames, deepest = _independent_self_penetration(
        export_nominal(get_robot(robot), tmp_path / f"{robot}.xml"), out.motion.qpos
    )
    assert r["self_collision_frames"] == frames
    assert r["max_self_penetration_mm"] == pytest.approx(deepest, abs=1e-6)
    assert r["kinematic"]["max_scene_penetration_mm"] > 15.0  # It walks through the pad.
    assert r["max_scene_penetration_mm"] <= 1.0 and r["scene_penetration_frames"] == 0, r
    assert r["human_contacts"] > 0 and r["contact_preservation"] >= 0.9
    assert r["keypoint_error_mm_mean"] <= 40.0 and r["joint_limit_violations"] == 0


@pytest.mark.parametrize("robot", ["berkeley_humanoid", "apollo"])
def test_the_interaction_reports_self_collision_is_the_independent_checks(
    robot: str, shared_data: Path, tmp_path: Path
) -> None:
    """The sole corners renumber the robot's geoms in the model with the scene; the report
    measured the scene-less model's pair ids there (on this walk: 1 frame at 1.07 mm on the
    Berkeley Humanoid, 5 at 5.95 mm on the Apollo, where every geom pair of the exported
    robot, by mj_geomDistance, has none)."""
    from humimic.robots import export_nominal, get_robot
    from test_self_collision import _independent_self_penetration

    path, scene = _pad_under_feet(shared_data)
    out = Retargeter(robot, "cmu", RetargetConfig(fps=30.0), method="interaction-mesh",
                     mesh=InteractionConfig()).run(load_clip(path).slice(1, 97), scene=scene)  # fmt: skip
    frames, deepest = _independent_self_penetration(
        export_nominal(get_robot(robot), tmp_path / f"{robot}.xml"), out.motion.qpos
    )
    assert out.report["self_collision_frames"] == frames
    assert out.report["max_self_penetration_mm"] == pytest.approx(deepest, abs=1e-6)


def test_motion_file_has_the_scene_tracks(shared_data: Path, tmp_path: Path) -> None:
    out = _walk_on_pad(shared_data)
    poses = out.motion.extras["scene_poses"]  # type: ignore[index]
    assert poses.shape == (out.motion.num_frames, 1, 7)
    contacts = out.motion.extras["metric_contact_preserved"]  # type: ignore[index]
    assert contacts.shape[0] == out.motion.num_frames and (contacts >= 0).any()


def test_cli_interaction_mesh_with_a_scene_file(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, scene = _pad_under_feet(shared_data)
    obj = scene.objects[0]
    size = obj.vertices.max(axis=0) - obj.vertices.min(axis=0)
    (tmp_path / "pad.yaml").write_text(
        f"schema_version: 1\nobjects:\n  - name: pad\n    box: {size.tolist()}\n"
        f"    pos: {obj.poses[0, :3].tolist()}\n"
    )
    src = shared_data / "cmu" / "35_01.bvh"
    argv = ["retarget", str(src), "--out", str(tmp_path / "m.npz"), "--ik.fps", "30"]
    # The method and the scene go together: either alone is an error, and nothing is written.
    assert main([*argv, "--method", "interaction-mesh"]) == 2
    assert "needs --scene" in capsys.readouterr().err
    assert main([*argv, "--scene", str(tmp_path / "pad.yaml")]) == 2
    assert "interaction-mesh only" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
    code = main([*argv, "--start", "1", "--method", "interaction-mesh", "--scene",
                 str(tmp_path / "pad.yaml"), "--report", str(tmp_path / "m.json"), "--quiet"])  # fmt: skip
    assert code == 0
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["method"] == "interaction-mesh" and report["scene_objects"] == ["pad"]
    assert report["max_scene_penetration_mm"] <= 10.0
    assert "scene: penetration" in capsys.readouterr().out
    motion = load_motion(tmp_path / "m.npz")
    assert motion.extras["scene_poses"].shape[1] == 1  # type: ignore[index]
    # A walk: the pelvis moves less than 10 cm per frame (an earlier version kept out of the
    # pad at frame 38 by a 23 cm jump up and 53 cm down), and the feet rest on the pad.
    assert np.abs(np.diff(motion.qpos[:, :3], axis=0)).max() < 0.1
    assert report["planted_foot_gap_mm"] <= 3.0


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("still_travel", 0.0),
        ("still_travel", 1.5),
        ("still_reach", 0.0),
        ("still_speed", -0.1),
        ("stick_height_scale", -0.1),
    ],
)
def test_toe_hold_settings_are_checked(field: str, value: float) -> None:
    from dataclasses import replace

    from humimic.errors import InputError

    with pytest.raises(InputError, match=f"mesh.{field}"):
        replace(InteractionConfig(), **{field: value}).validate()


def test_planted_feet_rest_on_the_floor_while_climbing_down(shared_data: Path) -> None:
    """A real climb down (seq_1, 2.7 s): where the human's foot rests, the robot's rests too.
    Holding a planted foot at its previous frame's height kept one that landed high floating
    through its stance, well past these bounds."""
    from humimic.datasets.scene import load_scene

    folder = shared_data / "holosoma_climb" / "mocap_climb_seq_1"
    clip = load_clip(next(folder.glob("*.npy"))).slice(1760, 2080)
    r = Retargeter("g1", "holosoma", RetargetConfig(fps=30.0), method="interaction-mesh",
                   mesh=InteractionConfig()).run(clip, scene=load_scene(folder)).report  # fmt: skip
    assert r["planted_foot_gap_mm"] <= 3.0, r["planted_foot_gap_mm"]
    assert r["floating_planted_feet"] <= 8, r["floating_planted_feet"]
    assert r["max_scene_penetration_mm"] <= 10.0 and r["contact_preservation"] >= 0.9


def _walk_beside_one_box(
    shared_data: Path, folder: Path, name: str, box: list[float], pos: list[float],
    *, quiet: bool = True,
) -> dict:  # fmt: skip
    """``humimic retarget --method interaction-mesh`` of the CMU walk's first 13 frames with a
    scene of one box (sizes ``box``, centre ``pos``) written in ``folder``; its report."""
    lines = (shared_data / "cmu" / "35_01.bvh").read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("Frames:"))
    clip = folder / "walk.bvh"
    clip.write_text("".join([*lines[:i], "Frames: 13\n", lines[i + 1], *lines[i + 2 : i + 15]]))
    scene = folder / f"{name}.yaml"
    scene.write_text(f"schema_version: 1\nobjects:\n  - name: {name}\n    box: {box}\n"
                     f"    pos: {pos}\n")  # fmt: skip
    report = folder / "m.json"
    argv = ["retarget", str(clip), "--method", "interaction-mesh", "--scene", str(scene),
            "--out", str(folder / "m.npz"), "--report", str(report)]  # fmt: skip
    assert main([*argv, "--quiet"] if quiet else argv) == 0
    return json.loads(report.read_text())


def test_a_large_object_sampled_coarsely_is_reported(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 90 m floor slab cannot be sampled every 5 cm within the point budget: the spacing
    widens, and the report and a warning say by how much (no silent fallback)."""
    r = _walk_beside_one_box(shared_data, tmp_path, "slab", [90.0, 90.0, 0.02], [0, 0, -0.5])
    err = capsys.readouterr().err
    spacing = r["scene_spacing_mm"]["slab"]
    assert spacing > 2 * 1e3 * InteractionConfig().scene_spacing
    assert "slab every" in err and "coarsely" in err


def test_a_scene_the_human_never_touches_reports_no_preservation_and_says_so(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A box 20 m from the walk: 0 human-scene contacts gave contact_preservation 1.0, a
    perfect score over nothing. Now it is null, printed n/a, and a warning says why."""
    r = _walk_beside_one_box(shared_data, tmp_path, "far", [0.5, 0.5, 0.5], [20.0, 0, 0.25],
                             quiet=False)  # fmt: skip
    captured = capsys.readouterr()
    assert r["human_contacts"] == 0 and r["contact_preservation"] is None
    assert r["kinematic"]["contact_preservation"] is None
    assert "contacts kept n/a% of 0" in captured.out
    assert "never touches the scene" in captured.err
    # Nor does a toe rest on it: the floor is taken at z = 0, and a warning says so.
    assert r["scene_floor"]["from"].startswith("z = 0") and "--ik.floor-height" in captured.err


def _climb_contacts(shared_data: Path, lift: float, sink: float) -> tuple[int, dict]:
    """Human-scene contacts that interaction-mesh retargeting finds on 8 s of climbing clip 2
    with its boxes, the human's joints raised by ``lift`` and the boxes lowered by ``sink``
    [m], and where the scene's floor was put."""
    from dataclasses import replace as dc_replace

    from humimic.datasets.scene import load_scene
    from humimic.retarget.interaction import InteractionMeshRetargeter
    from humimic.robots import get_robot
    from humimic.robots.maps import get_map

    folder = shared_data / "holosoma_climb" / "mocap_climb_seq_2"
    clip = load_clip(next(folder.glob("*.npy"))).slice(0, 960)
    clip = dc_replace(clip, positions_w=clip.positions_w + np.array([0.0, 0.0, lift]))
    scene = load_scene(folder)
    objects = tuple(dc_replace(o, poses=o.poses - np.array([0, 0, sink, 0, 0, 0, 0]))
                    for o in scene.objects)  # fmt: skip
    m = get_map("holosoma", "g1")
    r = InteractionMeshRetargeter(get_robot("g1"), m, RetargetConfig(fps=30.0),
                                  InteractionConfig())  # fmt: skip
    tg = r.kin.targets(clip)
    placed, floor = r.scene_placement(clip, dc_replace(scene, objects=objects), tg)
    found, _ = r.human_contacts(placed, tg)
    return int((found >= 0).sum()), floor


def test_the_scene_is_placed_by_where_the_toes_rest_on_it(shared_data: Path) -> None:
    """Issue 54: a climbing clip of the same source had 0 human-scene contacts. The scene was
    mapped so that the planted toe *joints* met the robot's toes, but a toe joint rests 3-4 cm
    above the surface under it, so the boxes sank out of the contact detector's reach; and a
    clip's world floor is no better a reference (its planted toe joints are 1.6-6.5 cm above
    z = 0 on these clips, where they rest 3.4-4.4 cm above the boxes). Now the floor is put
    where the human's toe joints rest as far above it as they rest above the objects: the
    same clip with its joints 4 cm higher, or its boxes 4 cm lower (a capture and a scene
    that disagree), finds the same contacts."""
    n0, floor0 = _climb_contacts(shared_data, 0.0, 0.0)
    assert floor0["from"] == "toe rests on objects"
    assert 0.02 < floor0["toe_clearance_m"] < 0.06
    assert n0 > 200
    n_lift, floor_lift = _climb_contacts(shared_data, 0.04, 0.0)
    assert n_lift == n0
    assert floor_lift["floor_m"] == pytest.approx(floor0["floor_m"], abs=1e-9)
    n_sink, floor_sink = _climb_contacts(shared_data, 0.0, 0.04)
    assert n_sink >= 0.95 * n0
    assert floor_sink["toe_clearance_m"] == pytest.approx(
        floor0["toe_clearance_m"] + 0.04, abs=0.01
    )


@pytest.mark.parametrize("robot", ["op3", "g1", "t1"])
def test_the_scene_in_the_robot_model_is_the_scene_as_given(robot: str) -> None:
    """Each object's mesh in the IK model, posed by its mocap body, has the scene's own
    vertices in the world: the OP3's default mesh class scales meshes by 0.001, and the
    scene's boxes had inherited it (points, so no robot of that kind ever met its scene)."""
    import mujoco

    from humimic.retarget.robot_model import ik_model, scene_geoms
    from humimic.robots import get_robot
    from humimic.robots.maps import get_map

    v, f = box_mesh(np.array([0.4, 0.3, 0.2]))
    pose = np.array([[0.5, -0.2, 0.1, np.cos(0.3), 0.0, 0.0, np.sin(0.3)]])
    scene = Scene(objects=(SceneObject(name="box", vertices=v, faces=f, poses=pose),),
                  source="test")  # fmt: skip
    model, _ = ik_model(get_robot(robot), get_map("cmu", robot), scene=scene)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    (g,) = scene_geoms(model)
    mesh = model.geom_dataid[g]
    local = model.mesh_vert[
        model.mesh_vertadr[mesh] : model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]
    ]
    world = local @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
    expected = scene.objects[0].world_vertices(0)
    # The same point set (MuJoCo re-centres and turns a mesh into its inertial frame).
    dist = np.linalg.norm(world[:, None] - expected[None], axis=-1)
    assert dist.min(axis=1).max() < 1e-6 and dist.min(axis=0).max() < 1e-6


def _climb_contacts_by_point(shared_data: Path, robot: str) -> dict[str, int]:
    """Human-scene contacts per key point on 8 s of climbing clip 2, retargeted to ``robot``."""
    from humimic.datasets.scene import load_scene
    from humimic.retarget.interaction import InteractionMeshRetargeter
    from humimic.robots import get_robot
    from humimic.robots.maps import get_map

    folder = shared_data / "holosoma_climb" / "mocap_climb_seq_2"
    clip = load_clip(next(folder.glob("*.npy"))).slice(0, 960)
    m = get_map("holosoma", robot)
    r = InteractionMeshRetargeter(get_robot(robot), m, RetargetConfig(fps=30.0),
                                  InteractionConfig())  # fmt: skip
    tg = r.kin.targets(clip)
    placed, _ = r.scene_placement(clip, load_scene(folder), tg)
    found, _ = r.human_contacts(placed, tg)
    return {n: int(c) for n, c in zip(m.keypoints, (found >= 0).sum(axis=0), strict=True)}


def test_the_humans_contacts_do_not_depend_on_the_robots_size_or_arms(shared_data: Path) -> None:
    """The human's hands, hips and knees touch the boxes where the human's do, whichever robot
    the clip goes to: on the 0.5 m OP3 a fixed 5 cm contact radius stood for 19 cm of the
    human, and the T1's long-armed targets reached boxes the human's hands never did."""
    g1 = _climb_contacts_by_point(shared_data, "g1")
    feet = {n for n in g1 if n.endswith(("ankle", "toe"))}
    assert sum(g1[n] for n in feet) > 200
    for robot in ("op3", "t1"):
        other = _climb_contacts_by_point(shared_data, robot)
        for name in set(g1) - feet:
            assert abs(other[name] - g1[name]) <= 0.05 * g1[name] + 2, (robot, name, other, g1)


@pytest.mark.slow
def test_interaction_frames_with_crossed_links_are_solved_again(
    shared_data: Path, tmp_path: Path
) -> None:
    """Climbing clip 1 on the Berkeley Humanoid (about 30 s): the scene's pull left its two
    hip ab/ad links 2.6 mm into each other in 4 frames. Those frames are solved again with
    guarded steps; the independent check finds none left."""
    from humimic.datasets.scene import load_scene
    from humimic.robots import export_nominal, get_robot
    from test_self_collision import _independent_self_penetration

    folder = shared_data / "holosoma_climb" / "mocap_climb_seq_1"
    out = Retargeter("berkeley_humanoid", "holosoma", RetargetConfig(), method="interaction-mesh",
                     mesh=InteractionConfig()).run(
        load_clip(next(folder.glob("*.npy"))), scene=load_scene(folder))  # fmt: skip
    assert out.report["interaction_retried_frames"] >= 1
    frames, deepest = _independent_self_penetration(
        export_nominal(get_robot("berkeley_humanoid"), tmp_path / "bh.xml"), out.motion.qpos
    )
    assert (frames, out.report["self_collision_frames"]) == (0, 0), deepest
