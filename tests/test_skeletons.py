"""Any skeleton (issue 55): a BVH is matched to a shipped skeleton map by its joint names, and a
rig no map knows gets a map proposed from its joint names and tree, or is refused naming the
key points it could not place.

The rigs are written by these tests: the CMU walk of ../shared/data with its joints renamed
as LAFAN1, Xsens MVN, Mixamo (under another namespace), SMPL (the smplx package's names and
PHC's) and a made-up ``L_Thigh`` rig name
them (published joint lists, no third-party file). Only names change, so every rig must
retarget to exactly the motion of the CMU file.
"""

from __future__ import annotations

import json
import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from humimic.cli.main import main
from humimic.motion import load_motion
from humimic.robots.maps import load_map_file
from humimic.robots.maps.detect import _split, match_skeleton

FRAMES = 30

CMU_TO = {
    "lafan1": {"LeftToeBase": "LeftToe", "RightToeBase": "RightToe"},
    "xsens": {
        "Hips": "Pelvis", "LeftUpLeg": "LeftUpperLeg", "RightUpLeg": "RightUpperLeg",
        "LeftLeg": "LeftLowerLeg", "RightLeg": "RightLowerLeg", "LeftToeBase": "LeftToe",
        "RightToeBase": "RightToe", "LeftArm": "LeftUpperArm", "RightArm": "RightUpperArm",
    },
    "smpl": {
        "Hips": "pelvis", "LeftUpLeg": "left_hip", "RightUpLeg": "right_hip",
        "LeftLeg": "left_knee", "RightLeg": "right_knee", "LeftFoot": "left_ankle",
        "RightFoot": "right_ankle", "LeftToeBase": "left_foot", "RightToeBase": "right_foot",
        "Spine": "spine1", "Spine1": "spine3", "Neck": "neck", "Head": "head",
        "LeftShoulder": "left_collar", "RightShoulder": "right_collar",
        "LeftArm": "left_shoulder", "RightArm": "right_shoulder", "LeftForeArm": "left_elbow",
        "RightForeArm": "right_elbow", "LeftHand": "left_wrist", "RightHand": "right_wrist",
    },
    "smpl_phc": {
        "Hips": "Pelvis", "LeftUpLeg": "L_Hip", "RightUpLeg": "R_Hip", "LeftLeg": "L_Knee",
        "RightLeg": "R_Knee", "LeftFoot": "L_Ankle", "RightFoot": "R_Ankle",
        "LeftToeBase": "L_Toe", "RightToeBase": "R_Toe", "Spine": "Spine1", "Spine1": "Spine3",
        "Neck": "Neck", "Head": "Head", "LeftShoulder": "L_Collar",
        "RightShoulder": "R_Collar", "LeftArm": "L_Shoulder", "RightArm": "R_Shoulder",
        "LeftForeArm": "L_Elbow", "RightForeArm": "R_Elbow", "LeftHand": "L_Wrist",
        "RightHand": "R_Wrist",
    },
    "made_up": {
        "Hips": "pelvis", "LeftUpLeg": "L_Thigh", "RightUpLeg": "R_Thigh",
        "LeftLeg": "L_Knee", "RightLeg": "R_Knee", "LeftFoot": "L_Ankle",
        "RightFoot": "R_Ankle", "LeftToeBase": "L_Toe", "RightToeBase": "R_Toe",
        "LeftArm": "L_UpperArm", "RightArm": "R_UpperArm", "LeftForeArm": "L_Elbow",
        "RightForeArm": "R_Elbow", "LeftHand": "L_Wrist", "RightHand": "R_Wrist",
        "Neck": "neck", "LeftShoulder": "L_Clavicle", "RightShoulder": "R_Clavicle",
    },
}  # fmt: skip
"""CMU joint -> the rig's name. The CMU-only joints are renamed as well (below), so that no
rig is taken for CMU."""

CMU_ONLY = {"LHipJoint": "LeftPelvisLink", "RHipJoint": "RightPelvisLink",
            "LowerBack": "Waist"}  # fmt: skip


def _rename(text: str, names: dict[str, str], prefix: str = "") -> str:
    def sub(m: re.Match[str]) -> str:
        return f"{m.group(1)} {prefix}{names.get(m.group(2), m.group(2))}"

    return re.sub(r"^(\s*(?:ROOT|JOINT)) (\S+)", sub, text, flags=re.MULTILINE)


def _rig(shared_data: Path, folder: Path, rig: str) -> Path:
    """The walk's first frames as ``rig`` names its joints (``cmu``: unchanged)."""
    lines = (shared_data / "cmu" / "35_01.bvh").read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("Frames:"))
    text = "".join(
        [*lines[:i], f"Frames: {FRAMES}\n", lines[i + 1], *lines[i + 2 : i + 2 + FRAMES]]
    )
    if rig == "mixamo":
        text = _rename(text, CMU_ONLY, prefix="mixamorig1:")
    elif rig != "cmu":
        text = _rename(text, {**CMU_ONLY, **CMU_TO[rig]})
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{rig}.bvh"
    path.write_text(text)
    return path


def _retarget(path: Path, *extra: str) -> tuple[int, Path]:
    out = path.with_suffix(".npz")
    argv = ["retarget", str(path), "--out", str(out), "--report", str(out.with_suffix(".json")),
            "--start", "1", *extra]  # fmt: skip
    return main(argv), out


@cache
def _cmu_qpos(shared_data: Path, tmp: Path) -> np.ndarray:
    code, out = _retarget(_rig(shared_data, tmp / "cmu", "cmu"))
    assert code == 0
    return load_motion(out).qpos


@pytest.mark.parametrize(("rig", "skeleton"), [("lafan1", "lafan1"), ("xsens", "xsens"),
                                               ("mixamo", "mixamo"), ("smpl", "smpl"),
                                               ("smpl_phc", "smpl_phc")])  # fmt: skip
def test_a_known_rig_is_matched_by_its_joint_names(
    shared_data: Path, tmp_path_factory: pytest.TempPathFactory, rig: str, skeleton: str
) -> None:
    base = tmp_path_factory.getbasetemp()
    path = _rig(shared_data, base / rig, rig)
    code, out = _retarget(path)
    assert code == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["skeleton"] == skeleton
    assert f"skeletons/{skeleton}.yaml" in report["map"]
    assert "map_written" not in report
    np.testing.assert_array_equal(load_motion(out).qpos, _cmu_qpos(shared_data, base))


def test_an_unknown_rig_gets_a_map_from_its_joint_names_written_for_editing(
    shared_data: Path, tmp_path_factory: pytest.TempPathFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    base = tmp_path_factory.getbasetemp()
    path = _rig(shared_data, base / "made_up", "made_up")
    code, out = _retarget(path)
    assert code == 0
    assert f"give it back with --map {out.with_suffix('.map.yaml')}" in capsys.readouterr().out
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["skeleton"].startswith("proposed:") and "proposed by name" in report["map"]
    written = Path(report["map_written"])
    assert written == out.with_suffix(".map.yaml")
    m = load_map_file(written)
    assert m.keypoints["left_knee"].human == "L_Knee"
    assert m.keypoints["left_shoulder"].human == "L_UpperArm"  # Not the clavicle.
    assert m.keypoints["pelvis"].human == "pelvis"
    np.testing.assert_array_equal(load_motion(out).qpos, _cmu_qpos(shared_data, base))
    # The written map is the one to edit and give back: the same motion again.
    data = yaml.safe_load(written.read_text())
    assert data["skeleton"] == "proposed"
    again = path.parent / "again.bvh"
    again.write_text(path.read_text())
    code, out2 = _retarget(again, "--map", str(written))
    assert code == 0
    np.testing.assert_array_equal(load_motion(out2).qpos, load_motion(out).qpos)


@pytest.mark.parametrize(
    ("renames", "named"),
    [
        ({"L_Elbow": "Bone7"}, ["left_elbow: no joint"]),
        ({"R_Wrist": "R_Hand", "R_Clavicle": "R_Wrist"}, ["right_wrist: 2 joints"]),
        ({"L_Toe": "L_Ankle", "L_Ankle": "L_Toe"}, ["left_toe: L_Toe is not below L_Ankle"]),
    ],
)
def test_a_rig_that_cannot_be_placed_is_refused_naming_the_key_points(
    shared_data: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    renames: dict[str, str],
    named: list[str],
) -> None:
    path = _rig(shared_data, tmp_path, "made_up")
    path.write_text(_rename(path.read_text(), renames))
    code, out = _retarget(path)
    err = capsys.readouterr().err
    assert code == 2
    assert path.name in err and "cannot place every key point" in err
    for text in named:
        assert text in err
    assert not out.exists() and not out.with_suffix(".map.yaml").exists()


def test_side_and_stem_of_joint_names() -> None:
    cases = {
        "LeftUpLeg": ("left", "upleg"), "RightUpperLeg": ("right", "upperleg"),
        "L_Hip": ("left", "hip"), "LHip": ("left", "hip"), "leftThigh": ("left", "thigh"),
        "Hip.L": ("left", "hip"), "hip_R": ("right", "hip"), "Leg": (None, "leg"),
        "LowerBack": (None, "lowerback"), "Root": (None, "root"), "RightHand": ("right", "hand"),
        "mixamorig:LeftToeBase": ("left", "toebase"),
    }  # fmt: skip
    for name, expected in cases.items():
        assert _split(name) == expected, name


def test_cmu_names_match_cmu_not_a_map_that_shares_them() -> None:
    names = ("Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
             "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase", "LowerBack",
             "Spine", "Neck", "Head", "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
             "RightShoulder", "RightArm", "RightForeArm", "RightHand")  # fmt: skip
    found = match_skeleton(names)
    assert found is not None and found.skeleton == "cmu"
    assert match_skeleton(("a", "b")) is None


def test_a_motion_that_cannot_be_written_leaves_no_proposed_map(
    shared_data: Path, tmp_path: Path
) -> None:
    """The proposed map is written just before its motion; where the motion then cannot be
    written (here its path became a folder between the check and the write), the map goes
    too: no half output."""
    from humimic.errors import HumimicError
    from humimic.pipeline.batch import plan_retarget

    path = _rig(shared_data, tmp_path, "made_up")
    out = tmp_path / "out" / "m.npz"
    out.parent.mkdir()
    batch = plan_retarget((path,), out, start=1)
    assert batch.jobs[0].map_path == out.with_suffix(".map.yaml")
    out.mkdir()  # The motion's path is now taken by a folder.
    with pytest.raises((HumimicError, OSError)):
        list(batch.run())
    assert not out.with_suffix(".map.yaml").exists()
