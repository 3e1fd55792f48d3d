"""Human-to-robot maps: every shipped map against real models and clips; parse errors."""

from __future__ import annotations

import copy
import dataclasses
import re
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import yaml

from humimic.datasets import load_bvh, load_positions
from humimic.errors import HumimicError, MapError
from humimic.robots import get_robot, nominal_model
from humimic.robots.maps import (
    CANONICAL_KEYPOINTS,
    RetargetMap,
    builtin_maps,
    compose_map,
    get_map,
    load_map_file,
    map_data,
    parse_map,
    skeleton_maps,
)

SHIPPED = sorted(builtin_maps())


@cache
def _robot_bodies(robot: str) -> frozenset[str]:
    model = nominal_model(get_robot(robot))
    return frozenset(model.body(i).name for i in range(model.nbody))


def _climb_npy(shared_data: Path) -> Path:
    return sorted((shared_data / "holosoma_climb").glob("*/*_joint_positions_*.npy"))[0]


@pytest.fixture(scope="module")
def human_joints(shared_data: Path) -> dict[str, tuple[str, ...]]:
    """Joint names of a real clip of each skeleton."""
    cmu = load_bvh(shared_data / "cmu" / "35_01.bvh")
    holo = load_positions(_climb_npy(shared_data))
    assert cmu.skeleton == "cmu"
    assert holo.skeleton == "holosoma"
    return {"cmu": cmu.names, "holosoma": holo.names}


def _cmu_g1_data() -> dict[str, Any]:
    return copy.deepcopy(map_data(get_map("cmu", "g1")))


def _parse_and_validate(data: dict[str, Any], human: tuple[str, ...] | None = None) -> RetargetMap:
    m = parse_map(data, "my_map.yaml")
    m.validate(human, set(_robot_bodies("g1")))
    return m


# --- Shipped maps -----------------------------------------------------------------------------


def test_shipped_maps_cover_both_skeletons_and_robots() -> None:
    assert {("cmu", "g1"), ("cmu", "t1"), ("holosoma", "g1"), ("holosoma", "t1")} <= set(SHIPPED)


@pytest.mark.parametrize(("skeleton", "robot"), SHIPPED)
def test_shipped_map_validates_against_robot_and_real_clip(
    skeleton: str, robot: str, human_joints: dict[str, tuple[str, ...]]
) -> None:
    m = get_map(skeleton, robot)
    assert (m.skeleton, m.robot) == (skeleton, robot)
    sp, rp = builtin_maps()[(skeleton, robot)]
    assert m.source == f"{sp} + {rp}"
    # The skeletons with a real clip here are checked against its joints; the others (LAFAN1,
    # Xsens, Mixamo: no third-party file in this repository) against their published names.
    names = human_joints.get(skeleton, tuple(skeleton_maps()[skeleton].joints.values()))
    m.validate(names, set(_robot_bodies(robot)))
    cfg = get_robot(robot)
    # Feet in the map are the robot's registered feet.
    assert {f.body for f in m.feet.values()} == set(cfg.feet.values())
    assert all(kp.weight >= 0 for kp in m.keypoints.values())


def test_a_map_is_a_skeleton_map_and_a_robot_map(tmp_path: Path) -> None:
    """N skeletons and M robots: every shipped pair is composed from two files, its key points
    the canonical ones, and written out in the one-file form it reads back as the same map."""
    files = builtin_maps()
    assert len({sp for sp, _ in files.values()}) * len({rp for _, rp in files.values()}) == len(
        files
    )
    for skeleton, robot in files:
        m = get_map(skeleton, robot)
        assert set(m.keypoints) <= set(CANONICAL_KEYPOINTS)
        out = tmp_path / f"{skeleton}_{robot}.yaml"
        out.write_text(yaml.safe_dump(map_data(m), sort_keys=False))
        again = load_map_file(out)
        assert dataclasses.replace(again, source="") == dataclasses.replace(m, source="")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("skeleton", "robot_edit", "message"),
    [
        ("joints:\n  pelvis: Hips\n", None, "no joint for the key point 'left_hip'"),
        ("joints:\n  pelvis: Hips\n  tail: Tail\n", None, "['tail'] are not canonical"),
        (None, ("    body: pelvis\n", "    body: pelvis\n    human: Hips\n"), "names no human"),
        (None, ("  left_hip:\n", "  left_hipp:\n"), "['left_hipp'] are not canonical"),
    ],
)
def test_composing_names_the_file_and_key_point(
    tmp_path: Path, skeleton: str | None, robot_edit: tuple[str, str] | None, message: str
) -> None:
    sp, rp = builtin_maps()[("cmu", "g1")]
    if skeleton is not None:
        sp = _write(tmp_path / "sk.yaml", f"schema_version: 1\nskeleton: mine\n{skeleton}")
    if robot_edit is not None:
        rp = _write(tmp_path / "rb.yaml", rp.read_text().replace(*robot_edit, 1))
    with pytest.raises(MapError, match=re.escape(message)):
        compose_map(sp, rp)


# --- Parse errors name the field -------------------------------------------------------------


def test_wrong_schema_version() -> None:
    data = _cmu_g1_data()
    data["schema_version"] = 2
    with pytest.raises(MapError, match=r"my_map\.yaml.*schema_version.*2"):
        parse_map(data, "my_map.yaml")
    del data["schema_version"]
    with pytest.raises(MapError, match="schema_version"):
        parse_map(data, "my_map.yaml")


def test_unknown_field_in_keypoint() -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_knee"]["colour"] = "red"
    with pytest.raises(MapError, match=r"my_map\.yaml: keypoints\.left_knee.*'colour'"):
        parse_map(data, "my_map.yaml")


def test_unknown_top_level_field() -> None:
    data = _cmu_g1_data()
    data["robto"] = "g1"
    with pytest.raises(MapError, match=r"my_map\.yaml.*'robto'"):
        parse_map(data, "my_map.yaml")


def test_unknown_key_point_in_frame() -> None:
    data = _cmu_g1_data()
    data["frames"]["torso"]["left"] = ["right_shoulder", "left_shouldr"]
    with pytest.raises(MapError, match=r"my_map\.yaml: frames\.torso.*'left_shouldr'"):
        _parse_and_validate(data)


def test_frame_pair_must_be_two_names() -> None:
    data = _cmu_g1_data()
    data["frames"]["torso"]["up"] = ["pelvis"]
    with pytest.raises(MapError, match=r"my_map\.yaml: frames\.torso\.up"):
        parse_map(data, "my_map.yaml")


def test_parent_listed_after_child() -> None:
    data = _cmu_g1_data()
    kps = data["keypoints"]
    # Move left_knee (parent of left_ankle) after left_ankle.
    knee = kps.pop("left_knee")
    reordered: dict[str, Any] = {}
    for name, kp in kps.items():
        reordered[name] = kp
        if name == "left_ankle":
            reordered["left_knee"] = knee
    data["keypoints"] = reordered
    with pytest.raises(MapError, match=r"my_map\.yaml: keypoints\.left_ankle\.parent: 'left_knee'"):
        _parse_and_validate(data)


def test_missing_parent_for_non_root() -> None:
    data = _cmu_g1_data()
    del data["keypoints"]["left_knee"]["parent"]
    with pytest.raises(MapError, match=r"keypoints\.left_knee\.parent"):
        _parse_and_validate(data)


def test_unknown_robot_body_via_validate() -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_knee"]["body"] = "left_kneee_link"
    m = parse_map(data, "my_map.yaml")
    with pytest.raises(
        MapError, match=r"my_map\.yaml: keypoints\.left_knee\.body.*left_kneee_link"
    ):
        m.validate(None, set(_robot_bodies("g1")))


def test_unknown_human_joint_via_validate(human_joints: dict[str, tuple[str, ...]]) -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_knee"]["human"] = "LeftKnee"
    with pytest.raises(MapError, match=r"my_map\.yaml: keypoints\.left_knee\.human.*'LeftKnee'"):
        _parse_and_validate(data, human_joints["cmu"])
    # Without clip names (human=None) the human joints are not checked.
    _parse_and_validate(data, None)


@pytest.mark.parametrize(
    ("offset", "expected"),
    [
        ([0.1, 0.0], r"expected \[x, y, z\]"),
        ("0.1 0 0", r"expected \[x, y, z\]"),
        (["a", 0.0, 0.0], "expected numbers"),
        ([0.1, None, 0.0], "expected numbers"),
    ],
)
def test_bad_offset(offset: object, expected: str) -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_toe"]["offset"] = offset
    with pytest.raises(MapError, match=rf"my_map\.yaml: keypoints\.left_toe\.offset: {expected}"):
        parse_map(data, "my_map.yaml")


def test_good_offset_is_parsed_as_floats() -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_toe"]["offset"] = [1, "0.5", -0.02]
    m = parse_map(data, "my_map.yaml")
    assert m.keypoints["left_toe"].offset == (1.0, 0.5, -0.02)
    assert all(isinstance(v, float) for v in m.keypoints["left_toe"].offset)


def test_non_numeric_weight_names_the_field() -> None:
    data = _cmu_g1_data()
    data["keypoints"]["left_knee"]["weight"] = "heavy"
    with pytest.raises(MapError, match=r"keypoints\.left_knee\.weight"):
        _parse_and_validate(data)


def test_non_mapping_inputs() -> None:
    with pytest.raises(MapError, match=r"my_map\.yaml: expected a mapping"):
        parse_map(["not", "a", "mapping"], "my_map.yaml")
    data = _cmu_g1_data()
    data["keypoints"]["left_knee"] = "left_knee_link"
    with pytest.raises(MapError, match=r"keypoints\.left_knee: expected a mapping"):
        parse_map(data, "my_map.yaml")
    data = _cmu_g1_data()
    data["keypoints"] = {}
    with pytest.raises(MapError, match=r"keypoints: expected a non-empty mapping"):
        parse_map(data, "my_map.yaml")


# --- Files ------------------------------------------------------------------------------------


def test_load_map_file_round_trips_a_written_map(tmp_path: Path) -> None:
    path = tmp_path / "copy.yaml"
    path.write_text(yaml.safe_dump(_cmu_g1_data()))
    m = load_map_file(path)
    assert m.source == str(path)
    assert m.keypoints == get_map("cmu", "g1").keypoints


def test_load_map_file_invalid_yaml_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("schema_version: 1\nkeypoints: [unclosed\n  pelvis: {human: Hips\n")
    with pytest.raises(MapError, match=r"broken\.yaml: invalid YAML"):
        load_map_file(path)


def test_load_map_file_missing_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"nothere\.yaml: cannot read"):
        load_map_file(tmp_path / "nothere.yaml")


def test_get_map_unknown_pair_lists_shipped_maps() -> None:
    with pytest.raises(MapError) as info:
        get_map("cmu", "atlas")
    msg = str(info.value)
    assert "'atlas'" in msg
    assert (
        "skeleton maps: canonical, cmu, holosoma, lafan1, mixamo, smpl, smpl_phc, xsens; robot maps: "
        "apollo, berkeley_humanoid, g1, h1, op3, t1" in msg
    )
    assert isinstance(info.value, HumimicError)
