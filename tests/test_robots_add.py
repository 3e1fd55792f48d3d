"""``humimic robots add``: a humanoid URDF or MJCF the tests write becomes a robot every command
takes, with its structure found from the tree and geometry; bad models exit 2 naming what is
wrong and leave nothing behind."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh

from humanoid_urdf import humanoid_urdf, write_humanoid
from humimic.cli.main import main
from humimic.robots import get_robot, nominal_model
from humimic.robots.add import add_robot
from humimic.robots.user import ROBOTS_DIR_ENV
from test_hostile_cli import _refused


@pytest.fixture
def robots(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty robots folder, the one every command reads."""
    root = tmp_path / "robots"
    monkeypatch.setenv(ROBOTS_DIR_ENV, str(root))
    return root


def test_an_added_urdf_humanoid_is_found_whole_and_retargets_the_walk(
    tmp_path: Path, robots: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The test's 25-joint URDF: every part is found (the bodies the URDF names for them),
    the model stands on its floor, `robots list` shows it, and `retarget --robot` meets the
    quality bar on the CMU walk."""
    urdf = write_humanoid(tmp_path / "src", world_link=True)
    assert main(["robots", "add", str(urdf), "--name", "testbot"]) == 0
    out = capsys.readouterr().out
    assert "everything found" in out and "world" in out  # The fixed world link, said.
    s = add_robot(urdf, "testbot2", root=robots).structure
    assert (s.root, s.torso, s.head) == ("pelvis", "torso", "head")
    for side in ("left", "right"):
        p = side[0]
        assert s.feet[side] == f"{p}_foot" and s.hips[side] == f"{p}_hip_yaw_link"
        assert s.knees[side] == f"{p}_shin"  # The body the knee joint moves.
        assert (s.shoulders[side], s.elbows[side], s.hands[side]) == (
            f"{p}_shoulder_pitch_link", f"{p}_forearm", f"{p}_hand")  # fmt: skip
    assert main(["robots", "list"]) == 0
    assert "testbot " in capsys.readouterr().out
    cfg = get_robot("testbot")
    model = nominal_model(cfg)
    assert model.nu == 25 and model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    soles = [data.geom_xpos[g, 2] - 0.015 for g in range(model.ngeom)
             if model.body(model.geom_bodyid[g]).name in ("l_foot", "r_foot")]  # fmt: skip
    np.testing.assert_allclose(soles, 0.0, atol=1e-9)  # Standing on the floor at qpos0.
    # A new process, as a user's next command: the --robot choices are read at start-up.
    import json
    import os
    import subprocess
    import sys

    report = tmp_path / "walk.json"
    argv = ["retarget", str(shared_data / "cmu" / "35_01.bvh"), "--robot", "testbot",
            "--out", str(tmp_path / "walk.npz"), "--report", str(report)]  # fmt: skip
    run = subprocess.run([sys.executable, "-c", "import sys; from humimic.cli.main import main; "
                          "sys.exit(main(sys.argv[1:]))", *argv], capture_output=True,
                         text=True, env={**os.environ, ROBOTS_DIR_ENV: str(robots)})  # fmt: skip
    assert run.returncode == 0, run.stderr

    r = json.loads(report.read_text())
    assert r["joint_limit_violations"] == 0
    assert r["max_ground_penetration_mm"] <= 5.0
    assert r["self_collision_frames"] == 0
    assert r["keypoint_error_mm_mean"] < 25.0


def test_the_toe_is_on_the_sole_under_its_front(tmp_path: Path, robots: Path) -> None:
    """The foot box of the test URDF (0.2 x 0.08 x 0.03 m, centred 4 cm ahead of and 4.5 cm
    under the ankle): its bottom is 6 cm under the ankle, its front 14 cm ahead; the toe key
    point is three quarters of the way to the front: 10.5 cm, by hand."""
    import yaml

    add_robot(write_humanoid(tmp_path / "src"), "testbot", root=robots)
    m = yaml.safe_load((robots / "testbot" / "map.yaml").read_text())
    for side in ("left", "right"):
        toe = m["keypoints"][f"{side}_toe"]
        assert toe["body"] == f"{side[0]}_foot"
        np.testing.assert_allclose(toe["offset"], [0.105, 0.0, -0.06], atol=1e-4)


def test_effort_limits_come_from_the_urdf_or_a_stated_default(tmp_path: Path, robots: Path) -> None:
    """With efforts in the URDF, each motor's limit is the joint's 80 N m; without, the stated
    mass x g x height / 4, said in the notes; the armature makes kp the effort over 0.5 rad."""
    import math

    import yaml

    add_robot(write_humanoid(tmp_path / "a"), "with_effort", root=robots)
    r = add_robot(write_humanoid(tmp_path / "b", effort=None), "no_effort", root=robots)
    a = yaml.safe_load((robots / "with_effort" / "robot.yaml").read_text())["motors"]
    b = yaml.safe_load((robots / "no_effort" / "robot.yaml").read_text())["motors"]
    assert {m["effort_limit"] for m in a.values()} == {80.0}
    stated = round(r.mass * 9.81 * r.structure.height / 4.0, 1)
    assert {m["effort_limit"] for m in b.values()} == {stated}
    assert any("no effort limit" in n for n in r.notes)
    wn = 2 * math.pi * 10.0
    for m in a.values():
        assert m["armature"] * wn**2 == pytest.approx(80.0 / 0.5, rel=1e-5)


def test_meshes_are_copied_converted_or_replaced_and_said(tmp_path: Path, robots: Path) -> None:
    """An STL thigh is copied; a PLY foot (a format MuJoCo does not read) is converted by
    trimesh; a DAE file trimesh cannot read either becomes the box of the link's inertia."""
    src = tmp_path / "src"
    (src / "meshes").mkdir(parents=True)
    trimesh.creation.cylinder(radius=0.05, height=0.3).export(src / "meshes" / "thigh.stl")
    trimesh.creation.box((0.2, 0.08, 0.03)).export(src / "meshes" / "foot.ply")
    (src / "meshes" / "bad.dae").write_text("<COLLADA>not really</COLLADA>")
    path = src / "testbot.urdf"
    path.write_text(humanoid_urdf(thigh_mesh="package://src/meshes/thigh.stl",
                                  foot_mesh="meshes/foot.ply"))  # fmt: skip
    r = add_robot(path, "meshbot", root=robots)
    assert any("foot.ply: converted to STL" in n for n in r.notes), r.notes
    assets = {p.name for p in (robots / "meshbot" / "assets").iterdir()}
    assert {"thigh.stl", "foot.stl"} <= assets
    model = nominal_model(get_robot("meshbot", "test"))  # Loads from its own folder.
    assert sum(model.geom_type == mujoco.mjtGeom.mjGEOM_MESH) == 2
    path.write_text(humanoid_urdf(thigh_mesh="meshes/bad.dae"))
    r = add_robot(path, "boxbot", root=robots)
    assert any("bad.dae" in n and "inertia" in n for n in r.notes), r.notes


def test_an_added_mjcf_keeps_its_actuators_and_meshes(tmp_path: Path, robots: Path) -> None:
    """The testbot converted to MJCF by MuJoCo, with a fixed base (no free joint): humimic
    gives it one and says so; its meshes come along."""
    src = tmp_path / "src"
    (src / "meshes").mkdir(parents=True)
    trimesh.creation.cylinder(radius=0.05, height=0.3).export(src / "meshes" / "thigh.stl")
    floating = ('<link name="w"/><joint name="base" type="floating"><parent link="w"/>'
                '<child link="pelvis"/></joint></robot>')  # fmt: skip
    text = humanoid_urdf(thigh_mesh="thigh.stl").replace("</robot>", floating)
    spec = mujoco.MjSpec.from_string(text.replace('<?xml version="1.0"?>\n', ""))
    spec.delete(spec.joint("base"))  # A pelvis fixed to the world.
    spec.compiler.fusestatic = False  # (URDF import fuses jointless bodies.)
    spec.meshdir = str(src / "meshes")
    spec.compile()
    xml = spec.to_xml().replace(str(src / "meshes"), "meshes")
    (src / "bot.xml").write_text(xml)
    r = add_robot(src / "bot.xml", "mjcfbot", root=robots)
    assert any("free joint" in n for n in r.notes)
    model = nominal_model(get_robot("mjcfbot"))
    assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    assert r.structure.feet == {"left": "l_foot", "right": "r_foot"}


@pytest.mark.parametrize(
    ("what", "expect"),
    [
        ("broken", "not valid XML"),
        ("no_legs", "no legs found"),
        ("missing_mesh", "collision mesh 'meshes/nope.stl' not found"),
        ("not_urdf", "not a URDF"),
        ("two_roots", "no floating root found"),
        ("suffix", "expected an MJCF .xml or a .urdf"),
        ("bad_mass", "link 'pelvis': <mass value='heavy'>: not numbers"),
        ("nan_inertia", "link 'pelvis': <inertia ixx='nan'>: not numbers"),
    ],
)
def test_bad_models_exit_2_naming_what_is_wrong_and_leave_nothing(
    what: str, expect: str, tmp_path: Path, robots: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / ("bot.urdf" if what != "suffix" else "bot.dae")
    text = humanoid_urdf(
        legs=what != "no_legs", thigh_mesh="meshes/nope.stl" if what == "missing_mesh" else None
    )
    if what == "broken":
        text = text[: len(text) // 2]
    elif what == "not_urdf":
        text = "<mujoco><worldbody/></mujoco>"
    elif what == "bad_mass":  # A broken inertia to repair, whose mass is no number.
        text = text.replace('<mass value="8.0"/>', '<mass value="heavy"/>', 1).replace(
            'ixx="0.01" iyy="0.01" izz="0.01"', 'ixx="0" iyy="0" izz="0"', 1
        )
    elif what == "nan_inertia":
        text = text.replace('ixx="0.01"', 'ixx="nan"', 1)
    elif what == "two_roots":
        text = text.replace("</robot>", '<link name="stray"/></robot>')
    path.write_text(text)
    _refused(["robots", "add", str(path), "--name", "bad"], capsys, str(path), expect)
    assert not robots.exists() or not any(robots.iterdir())


def test_names_and_existing_robots_are_checked(
    tmp_path: Path, robots: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    urdf = write_humanoid(tmp_path / "src")
    _refused(["robots", "add", str(urdf), "--name", "g1"], capsys, "--name 'g1'", "registered")
    _refused(["robots", "add", str(urdf), "--name", "Bad Name"], capsys, "--name")
    assert main(["robots", "add", str(urdf), "--name", "bot"]) == 0
    capsys.readouterr()
    _refused(["robots", "add", str(urdf), "--name", "bot"], capsys, "bot", "--force")
    assert main(["robots", "add", str(urdf), "--name", "bot", "--force"]) == 0
