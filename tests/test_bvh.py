"""BVH loading: real CMU clips, synthetic files for semantics, units, axes and errors."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from humimic.datasets import estimate_height, load_bvh, load_clip
from humimic.errors import BvhParseError, InputError
from humimic.transforms import Y_UP_TO_Z_UP, quat_to_matrix

CMU_JOINTS = [
    "Hips",
    "LHipJoint",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "LeftToeBase",
    "RHipJoint",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "RightToeBase",
    "LowerBack",
    "Spine",
    "Spine1",
    "Neck",
    "Neck1",
    "Head",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "LeftFingerBase",
    "LeftHandIndex1",
    "LThumb",
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
    "RightFingerBase",
    "RightHandIndex1",
    "RThumb",
]


def write(tmp_path: Path, text: str, name: str = "clip.bvh", newline: str = "\n") -> Path:
    """Write ``text`` (LF line breaks) with the given line break."""
    p = tmp_path / name
    p.write_bytes(text.replace("\n", newline).encode())
    return p


def line_of(text: str, needle: str) -> int:
    """1-based number of the first line of ``text`` that contains ``needle``."""
    for n, line in enumerate(text.split("\n"), start=1):
        if needle in line:
            return n
    raise AssertionError(needle)


def two_joint_bvh(frames: list[str], *, count: int | None = None, frame_time: str = "0.01") -> str:
    """A root with 6 channels and one child with 3; one End Site."""
    n = len(frames) if count is None else count
    return (
        "HIERARCHY\n"
        "ROOT Hips\n"
        "{\n"
        "  OFFSET 0 0 0\n"
        "  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
        "  JOINT Chest\n"
        "  {\n"
        "    OFFSET 0 1 0\n"
        "    CHANNELS 3 Zrotation Yrotation Xrotation\n"
        "    End Site\n"
        "    {\n"
        "      OFFSET 0 0.5 0\n"
        "    }\n"
        "  }\n"
        "}\n"
        "MOTION\n"
        f"Frames: {n}\n"
        f"Frame Time: {frame_time}\n" + "".join(f + "\n" for f in frames)
    )


GOOD_FRAMES = ["0 0 0 0 0 0 0 0 0", "1 2 3 10 20 30 5 6 7", "0 0 0 0 0 0 0 0 0"]


# --------------------------------------------------------------------------- real CMU data


@pytest.mark.parametrize(("name", "frames"), [("35_01", 359), ("09_01", 149)])
def test_cmu_clip_loads_upright_and_plausible(shared_data: Path, name: str, frames: int) -> None:
    path = shared_data / "cmu" / f"{name}.bvh"
    clip = load_bvh(path)
    assert clip.num_frames == frames
    assert clip.fps == pytest.approx(120.0, rel=1e-4)
    assert clip.skeleton == "cmu"
    assert clip.source == str(path)
    # 31 joints plus 7 End Sites (two toes, two finger tips, two thumbs, head).
    assert set(CMU_JOINTS) <= set(clip.names)
    ends = [n for n in clip.names if n.endswith("_End")]
    assert len(clip.names) == 31 + len(ends) and len(ends) == 7
    assert clip.positions_w.shape == (frames, len(clip.names), 3)
    assert clip.quats_w is not None
    assert np.allclose(np.linalg.norm(clip.quats_w, axis=-1), 1.0)

    # CMU units are not metres, cm or inches: the leg fallback must have picked the scale.
    assert clip.meta["units"].startswith("auto: leg scaled")
    assert 0.045 < float(clip.meta["metres_per_unit"]) < 0.065
    assert 1.4 <= estimate_height(clip) <= 2.0

    first = clip.positions_w[0]
    z = {n: first[clip.index(n), 2] for n in ("Head", "Hips", "LeftFoot", "RightFoot")}
    assert z["Head"] > z["Hips"] > max(z["LeftFoot"], z["RightFoot"])
    assert 1.35 <= first[:, 2].max() - first[:, 2].min() <= 2.0
    assert min(z["LeftFoot"], z["RightFoot"]) < 0.1  # Standing on (near) the ground.

    # First frame is a T-pose: arms horizontal and spread, legs straight down.
    for side in ("Left", "Right"):
        arm, hand = first[clip.index(f"{side}Arm")], first[clip.index(f"{side}Hand")]
        assert abs(hand[2] - arm[2]) < 0.15
        hip, foot = first[clip.index(f"{side}UpLeg")], first[clip.index(f"{side}Foot")]
        assert np.linalg.norm((hip - foot)[:2]) < 0.1
    span = first[clip.index("LeftHand")] - first[clip.index("RightHand")]
    assert np.linalg.norm(span[:2]) > 1.0

    # Handedness: the left leg is on the performer's left (a reflection would swap sides).
    forward = first[clip.index("LeftToeBase_End")] - first[clip.index("LeftFoot")]
    forward[2] = 0.0
    left = np.cross([0.0, 0.0, 1.0], forward)
    hips = first[clip.index("LeftUpLeg")] - first[clip.index("RightUpLeg")]
    assert hips @ left > 0.05 * np.linalg.norm(forward)

    # Rigid bones: every joint keeps its distance to its parent in every frame.
    for j, parent in enumerate(clip.parents):
        if parent >= 1:  # Skip the root's 6-channel translation.
            d = np.linalg.norm(clip.positions_w[:, j] - clip.positions_w[:, parent], axis=-1)
            assert np.ptp(d) < 1e-9


def test_cmu_load_is_fast(shared_data: Path, tmp_path: Path) -> None:
    text = (shared_data / "cmu" / "35_01.bvh").read_text()
    head, data = text.split("Frame Time:")
    rows = data.splitlines()[1:]
    rows = (rows * 10)[:3000]
    body = head.replace("Frames: 359", "Frames: 3000") + "Frame Time: 0.0083333\n"
    path = write(tmp_path, body + "\n".join(rows) + "\n", name="long.bvh")
    start = time.perf_counter()
    clip = load_bvh(path)
    elapsed = time.perf_counter() - start
    assert clip.num_frames == 3000
    assert elapsed < 1.0


# ---------------------------------------------------------------------- rotation semantics


def test_arbitrary_channel_orders_match_scipy_intrinsic(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    text_head = (
        "HIERARCHY\n"
        "ROOT Root\n{\n"
        "\tOFFSET 0 0 0\n"
        "\tCHANNELS 6 Zposition Xrotation Yposition Zrotation Xposition Yrotation\n"
        "\tJOINT A\n\t{\n"
        "\t\tOFFSET 1 2 3\n"
        "\t\tCHANNELS 3 Xrotation Zrotation Yrotation\n"
        "\t\tJOINT B\n\t\t{\n"
        "\t\t\tOFFSET -1 0.5 2\n"
        "\t\t\tCHANNELS 3 Yrotation Xrotation Zrotation\n"
        "\t\t\tJOINT C\n\t\t\t{\n"
        "\t\t\t\tOFFSET 0.3 -0.7 1.1\n"
        "\t\t\t\tCHANNELS 0\n"
        "\t\t\t\tEnd Site\n\t\t\t\t{\n\t\t\t\t\tOFFSET 0 0 1\n\t\t\t\t}\n"
        "\t\t\t}\n"
        "\t\t}\n"
        "\t}\n"
        "}\n"
    )
    frames = 4
    values = rng.uniform(-170, 170, size=(frames, 12))
    text = (
        text_head
        + f"MOTION\nFrames: {frames}\nFrame Time: 0.02\n"
        + "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in values)
    )
    clip = load_bvh(write(tmp_path, text), units="m", up="z")
    assert clip.names == ("Root", "A", "B", "C", "C_End")
    assert clip.parents == (-1, 0, 1, 2, 3)
    assert clip.fps == pytest.approx(50.0)
    assert clip.quats_w is not None
    got = quat_to_matrix(clip.quats_w)
    assert np.all(clip.quats_w[..., 0] >= 0)
    for t in range(frames):
        v = np.round(values[t], 6)
        r_root = Rotation.from_euler("XZY", v[[1, 3, 5]], degrees=True).as_matrix()
        p_root = v[[4, 2, 0]]  # Xposition, Yposition, Zposition columns.
        r_a = r_root @ Rotation.from_euler("XZY", v[6:9], degrees=True).as_matrix()
        p_a = p_root + r_root @ [1, 2, 3]
        r_b = r_a @ Rotation.from_euler("YXZ", v[9:12], degrees=True).as_matrix()
        p_b = p_a + r_a @ [-1, 0.5, 2]
        p_c = p_b + r_b @ [0.3, -0.7, 1.1]
        p_end = p_c + r_b @ [0, 0, 1]
        for j, r in enumerate((r_root, r_a, r_b, r_b, r_b)):
            np.testing.assert_allclose(got[t, j], r, atol=1e-9)
        for j, p in enumerate((p_root, p_a, p_b, p_c, p_end)):
            np.testing.assert_allclose(clip.positions_w[t, j], p, atol=1e-9)


def test_six_channel_non_root_joint_replaces_offset(tmp_path: Path) -> None:
    text = (
        "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Zrotation Yrotation Xrotation\n"
        "  JOINT Free\n  {\n    OFFSET 10 20 30\n"
        "    CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
        "    End Site\n    {\n      OFFSET 1 0 0\n    }\n  }\n}\n"
        "MOTION\nFrames: 2\nFrame Time: 0.5\n"
        "0 0 0 1 2 3 0 0 0\n"
        "90 0 0 1 2 3 0 0 90\n"
    )
    clip = load_bvh(write(tmp_path, text), units="m", up="z")
    free, end = clip.index("Free"), clip.index("Free_End")
    np.testing.assert_allclose(clip.positions_w[0, free], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(clip.positions_w[0, end], [2, 2, 3], atol=1e-12)
    # Frame 1: root yaws 90 degrees about z; Free then rolls 90 about its x.
    rz = Rotation.from_euler("Z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(clip.positions_w[1, free], rz @ [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(clip.positions_w[1, end], rz @ [2, 2, 3], atol=1e-12)
    assert clip.fps == pytest.approx(2.0)


def test_end_site_names_are_unique_and_zero_channel(tmp_path: Path) -> None:
    text = (
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition Zposition\n"
        " JOINT Hand\n {\n  OFFSET 1 0 0\n  CHANNELS 0\n"
        "  End Site\n  {\n   OFFSET 0 1 0\n  }\n"
        "  End Site\n  {\n   OFFSET 0 2 0\n  }\n }\n"
        " JOINT Hand_End\n {\n  OFFSET -1 0 0\n  CHANNELS 1 Zrotation\n }\n"
        " End Site\n {\n  OFFSET 0 0 -1\n }\n"
        "}\nMOTION\nFrames: 1\nFrame Time: 0.1\n5 6 7 45\n"
    )
    clip = load_bvh(write(tmp_path, text), units="m", up="z")
    assert len(set(clip.names)) == len(clip.names)
    assert clip.names[0] == "Hips"
    hand = clip.index("Hand")
    hand_ends = [n for n in clip.names if n.startswith("Hand_End") and n != "Hand_End"]
    assert len(hand_ends) == 2  # Distinct names, though the file has a joint named Hand_End.
    assert all(clip.parents[clip.index(n)] == hand for n in hand_ends)
    assert clip.parents[clip.index("Hips_End")] == 0
    np.testing.assert_allclose(clip.positions_w[0, clip.index("Hips_End")], [5, 6, 6])
    np.testing.assert_allclose(clip.positions_w[0, clip.index(hand_ends[1])], [6, 8, 7])
    assert clip.meta["end_sites"] == "3"
    assert clip.skeleton == "bvh"


@pytest.mark.parametrize("newline", ["\r\n", "\r", "\n"])
def test_line_endings_and_tabs(tmp_path: Path, newline: str) -> None:
    text = two_joint_bvh(GOOD_FRAMES).replace("  ", "\t")
    ref = load_bvh(write(tmp_path, two_joint_bvh(GOOD_FRAMES), name="lf.bvh"), units="m")
    clip = load_bvh(write(tmp_path, text, newline=newline), units="m")
    np.testing.assert_array_equal(clip.positions_w, ref.positions_w)


def test_mixed_line_endings_like_cmu(tmp_path: Path) -> None:
    lines = two_joint_bvh(GOOD_FRAMES).split("\n")
    text = "".join(line + ("\n" if n % 3 == 0 else "\r\n") for n, line in enumerate(lines))
    p = tmp_path / "mixed.bvh"
    p.write_bytes(text.encode())
    clip = load_bvh(p, units="m")
    assert clip.num_frames == 3
    assert clip.names == ("Hips", "Chest", "Chest_End")


def test_load_clip_dispatches_on_suffix(tmp_path: Path) -> None:
    clip = load_clip(write(tmp_path, two_joint_bvh(GOOD_FRAMES)), units="m")
    assert clip.num_frames == 3
    with pytest.raises(InputError, match=r"clip\.txt.*\.bvh"):
        load_clip(tmp_path / "clip.txt")


# ---------------------------------------------------------------------------- units and axes


def standing_bvh(height: float) -> str:
    """A 4-joint y-up figure whose rest pose is ``height`` tall: leg 0.5, torso 0.5."""
    leg, torso = 0.5 * height, 0.5 * height
    return (
        "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n"
        "  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
        f"  JOINT Knee\n  {{\n    OFFSET 0 {-leg / 2} 0\n    CHANNELS 3 Zrotation Yrotation Xrotation\n"
        f"    JOINT Foot\n    {{\n      OFFSET 0 {-leg / 2} 0\n      CHANNELS 0\n"
        f"      End Site\n      {{\n        OFFSET 0 0 {leg / 3}\n      }}\n    }}\n  }}\n"
        f"  JOINT Head\n  {{\n    OFFSET 0 {torso} 0\n    CHANNELS 0\n  }}\n"
        "}\nMOTION\nFrames: 1\nFrame Time: 0.008333333\n"
        f"0 {leg} 0 0 0 0 0 0 0\n"
    )


@pytest.mark.parametrize(
    ("height", "unit", "factor"),
    [(1.7, "m", 1.0), (170.0, "cm", 0.01), (1700.0, "mm", 0.001), (67.0, "inch", 0.0254)],
)
def test_auto_units_pick_the_plausible_named_unit(
    tmp_path: Path, height: float, unit: str, factor: float
) -> None:
    clip = load_bvh(write(tmp_path, standing_bvh(height)))
    assert float(clip.meta["metres_per_unit"]) == pytest.approx(factor)
    assert clip.meta["units"].startswith(f"auto: {unit} ")
    pos = clip.positions_w[0]
    assert pos[clip.index("Head"), 2] - pos[clip.index("Foot"), 2] == pytest.approx(height * factor)


def test_auto_units_fall_back_to_leg_length(tmp_path: Path) -> None:
    # 30 units tall: 30 m, 0.3 m, 0.03 m and 0.76 m are all implausible.
    clip = load_bvh(write(tmp_path, standing_bvh(30.0)))
    assert clip.meta["units"].startswith("auto: leg scaled to 0.9 m")
    assert float(clip.meta["metres_per_unit"]) == pytest.approx(0.9 / 15.0, rel=1e-5)
    pos = clip.positions_w[0]
    # The horizontal End Site past the foot does not count towards the leg.
    assert pos[clip.index("Hips"), 2] - pos[clip.index("Foot"), 2] == pytest.approx(0.9)


def test_explicit_units(tmp_path: Path) -> None:
    path = write(tmp_path, standing_bvh(170.0))
    cm = load_bvh(path, units="cm")
    metres = load_bvh(path, units="m")
    half = load_bvh(path, units=0.5)
    np.testing.assert_allclose(cm.positions_w, metres.positions_w * 0.01)
    np.testing.assert_allclose(half.positions_w, metres.positions_w * 0.5)
    assert half.meta["metres_per_unit"] == "0.5"
    assert cm.quats_w is not None and metres.quats_w is not None
    np.testing.assert_allclose(cm.quats_w, metres.quats_w)
    for bad in ("furlong", -1.0, float("nan")):
        with pytest.raises(InputError, match="units"):
            load_bvh(path, units=bad)


def test_y_up_to_z_up_is_a_proper_rotation(tmp_path: Path) -> None:
    text = (
        "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Zrotation Yrotation Xrotation\n"
        "  JOINT Up\n  {\n    OFFSET 0 1 0\n    CHANNELS 0\n  }\n"
        "  JOINT Side\n  {\n    OFFSET 1 0 0\n    CHANNELS 0\n  }\n"
        "  JOINT Front\n  {\n    OFFSET 0 0 1\n    CHANNELS 0\n  }\n"
        "}\nMOTION\nFrames: 2\nFrame Time: 0.1\n0 0 0\n0 30 0\n"
    )
    path = write(tmp_path, text)
    clip = load_bvh(path, units="m", up="y")
    same = load_bvh(path, units="m", up="z")
    p = clip.positions_w[0]
    up, side, front = p[clip.index("Up")], p[clip.index("Side")], p[clip.index("Front")]
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-12)  # File +y is up.
    np.testing.assert_allclose(side, [1, 0, 0], atol=1e-12)  # x stays x.
    np.testing.assert_allclose(front, [0, -1, 0], atol=1e-12)
    assert np.linalg.det(np.stack([side, up, front], axis=1)) == pytest.approx(1.0)
    np.testing.assert_allclose(same.positions_w[0, same.index("Up")], [0, 1, 0], atol=1e-12)
    # A yaw about the file's y axis becomes a yaw about z; orientations stay proper.
    assert clip.quats_w is not None
    rot = quat_to_matrix(clip.quats_w)
    assert np.allclose(np.linalg.det(rot), 1.0)
    yaw = Rotation.from_euler("Y", 30, degrees=True).as_matrix()
    np.testing.assert_allclose(rot[1, 0], Y_UP_TO_Z_UP @ yaw, atol=1e-12)
    np.testing.assert_allclose(
        clip.positions_w[1, clip.index("Side")],
        Rotation.from_euler("z", 30, degrees=True).as_matrix() @ [1, 0, 0],
        atol=1e-12,
    )
    with pytest.raises(InputError, match="up axis"):
        load_bvh(path, up="x")


def test_skeleton_argument_overrides_detection(tmp_path: Path) -> None:
    clip = load_bvh(write(tmp_path, two_joint_bvh(GOOD_FRAMES)), units="m", skeleton="mine")
    assert clip.skeleton == "mine"


# ------------------------------------------------------------------------------------ errors


def check_error(path: Path, line: int | None, *fragments: str, **kw: object) -> BvhParseError:
    with pytest.raises(BvhParseError) as info:
        load_bvh(path, units="m", **kw)  # type: ignore[arg-type]
    err = info.value
    message = str(err)
    assert path.name in message
    if line is not None:
        assert err.line == line, message
        assert f"{path}:{line}:" in message
    for fragment in fragments:
        assert fragment in message, message
    return err


def test_truncated_file_names_where_data_ends(tmp_path: Path) -> None:
    text = two_joint_bvh(GOOD_FRAMES, count=5)
    path = write(tmp_path, text)
    last = len(text.rstrip("\n").split("\n"))  # The data ends at the file's last line.
    check_error(path, last, "truncated", "5", "3")


def test_truncated_mid_line(tmp_path: Path) -> None:
    text = two_joint_bvh(["0 0 0 0 0 0 0 0 0", "1 2 3 4"], count=2)
    path = write(tmp_path, text)
    check_error(path, line_of(text, "1 2 3 4"), "expected 9 values", "found 4")


def test_malformed_number_names_the_line(tmp_path: Path) -> None:
    text = two_joint_bvh(["0 0 0 0 0 0 0 0 0", "0 0 0 0 1.2.3 0 0 0 0"])
    path = write(tmp_path, text)
    check_error(path, line_of(text, "1.2.3"), "'1.2.3'", "column 5")


def test_malformed_offset_names_the_line(tmp_path: Path) -> None:
    text = two_joint_bvh(GOOD_FRAMES).replace("OFFSET 0 1 0", "OFFSET 0 x1 0")
    path = write(tmp_path, text)
    check_error(path, line_of(text, "x1"), "expected a number", "'x1'")


def test_unknown_channel(tmp_path: Path) -> None:
    text = two_joint_bvh(GOOD_FRAMES).replace("3 Zrotation Yrotation", "3 Wrotation Yrotation")
    path = write(tmp_path, text)
    check_error(path, line_of(text, "Wrotation"), "unknown channel 'Wrotation'", "Chest")


def test_channel_count_larger_than_names(tmp_path: Path) -> None:
    text = two_joint_bvh(GOOD_FRAMES).replace("CHANNELS 3 Zrotation", "CHANNELS 4 Zrotation")
    path = write(tmp_path, text)
    check_error(path, line_of(text, "End Site"), "unknown channel 'End'")


def test_missing_closing_brace(tmp_path: Path) -> None:
    lines = two_joint_bvh(GOOD_FRAMES).split("\n")
    lines.remove("    }")  # The End Site's closing brace.
    text = "\n".join(lines)
    path = write(tmp_path, text)
    check_error(path, line_of(text, "MOTION"), "unbalanced braces", "'}'")


def test_extra_closing_brace(tmp_path: Path) -> None:
    text = two_joint_bvh(GOOD_FRAMES).replace("}\nMOTION", "}\n}\nMOTION")
    path = write(tmp_path, text)
    check_error(path, line_of(text, "MOTION") - 1, "unbalanced braces")


def test_unclosed_brace_at_end_of_file(tmp_path: Path) -> None:
    text = "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 0\n"
    path = write(tmp_path, text)
    check_error(path, 5, "unbalanced braces", "'Hips'", "line 3")


def test_nan_values(tmp_path: Path) -> None:
    text = two_joint_bvh(["0 0 0 0 0 0 0 0 0", "0 0 0 0 0 nan 0 0 0", "0 0 0 0 0 0 0 0 0"])
    path = write(tmp_path, text)
    check_error(path, line_of(text, "nan"), "finite", "column 6")


def test_inf_values(tmp_path: Path) -> None:
    text = two_joint_bvh(["0 0 0 0 0 0 0 0 0", "0 0 -inf 0 0 0 0 0 0"])
    path = write(tmp_path, text)
    check_error(path, line_of(text, "-inf"), "finite")


def test_zero_frames(tmp_path: Path) -> None:
    text = two_joint_bvh([])
    path = write(tmp_path, text)
    check_error(path, line_of(text, "Frames:"), "zero frames")


@pytest.mark.parametrize("frame_time", ["0", "-0.01", "abc"])
def test_bad_frame_time(tmp_path: Path, frame_time: str) -> None:
    text = two_joint_bvh(GOOD_FRAMES, frame_time=frame_time)
    path = write(tmp_path, text)
    check_error(path, line_of(text, "Frame Time"), "frame time")


def test_missing_sections(tmp_path: Path) -> None:
    good = two_joint_bvh(GOOD_FRAMES)
    no_hierarchy = write(tmp_path, good.replace("HIERARCHY\n", ""), name="a.bvh")
    check_error(no_hierarchy, 1, "expected 'HIERARCHY'")
    no_root = write(tmp_path, good.replace("ROOT Hips", "JOINT Hips"), name="b.bvh")
    check_error(no_root, 2, "expected 'ROOT' or 'MOTION'")
    no_motion = good.replace("MOTION\n", "")
    check_error(write(tmp_path, no_motion, name="c.bvh"), line_of(no_motion, "Frames"), "MOTION")
    empty = write(tmp_path, "", name="d.bvh")
    check_error(empty, 1, "HIERARCHY")
    no_frames = write(tmp_path, good.split("Frames:")[0], name="e.bvh")
    check_error(no_frames, None, "Frames:")


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.bvh"
    with pytest.raises(InputError, match=r"nope\.bvh"):
        load_bvh(path)


def test_auto_units_need_a_skeleton_with_height(tmp_path: Path) -> None:
    text = (
        "HIERARCHY\nROOT Only\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xposition Yposition Zposition\n}\n"
        "MOTION\nFrames: 1\nFrame Time: 0.1\n1 2 3\n"
    )
    path = write(tmp_path, text, name="flat.bvh")
    with pytest.raises(InputError, match=r"flat\.bvh.*units="):
        load_bvh(path)
    clip = load_bvh(path, units="m")
    np.testing.assert_allclose(clip.positions_w[0, 0], [1, -3, 2])
