"""Motions as CSV (issue 56): the layout BeyondMimic's and GMR's trackers read, written and read
back by ``humimic convert``; rows written by hand here are read as computed by hand; bad files
exit 2 naming the file and the row."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.errors import HumimicError, InputError
from humimic.motion import load_motion, motion_from_qpos, save_motion
from humimic.pipeline.files import read_any_motion
from humimic.robots import get_robot, nominal_model
from test_hostile_cli import _refused


@pytest.fixture(scope="module")
def g1_motion(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The G1 at its keyframe, swaying and turning: 20 frames at 30 fps."""
    m = nominal_model(get_robot("g1"))
    T = 20
    q = np.tile(m.key_qpos[0], (T, 1))
    t = np.arange(T) / 30.0
    q[:, 0] = 0.1 * t
    yaw = 0.5 * t
    q[:, 3], q[:, 6] = np.cos(yaw / 2), np.sin(yaw / 2)
    q[:, 7:] += 0.1 * np.sin(2 * np.pi * t)[:, None]
    path = tmp_path_factory.mktemp("csv") / "g1.npz"
    save_motion(motion_from_qpos(m, q, 30.0, "g1"), path)
    return path


def test_npz_to_csv_to_npz_round_trip(g1_motion: Path, tmp_path: Path) -> None:
    csv, back = tmp_path / "m.csv", tmp_path / "back.npz"
    assert main(["convert", str(g1_motion), str(csv)]) == 0
    assert (tmp_path / "m.csv.yaml").is_file()
    assert main(["convert", str(csv), str(back)]) == 0
    a, b = load_motion(g1_motion), load_motion(back)
    assert (b.robot, b.fps, b.joint_names) == (a.robot, a.fps, a.joint_names)
    np.testing.assert_allclose(b.qpos, a.qpos, atol=1e-8)
    np.testing.assert_allclose(b.body_pos_w, a.body_pos_w, atol=1e-7)


def test_a_row_written_by_hand_is_read_as_computed_by_hand(tmp_path: Path) -> None:
    """Base at (1, 2, 0.8), turned 90 degrees about z, its quaternion given unnormalized
    (x y z w = 0, 0, 2 sin 45, 2 cos 45) and scalar last; joints 0.1 .. 2.9 by 0.1. No
    sidecar: the robot and frame rate come from the command line."""
    m = nominal_model(get_robot("g1"))
    J = m.njnt - 1
    s = 2 * math.sin(math.pi / 4)
    row = [1.0, 2.0, 0.8, 0.0, 0.0, s, s, *[0.1 * (k + 1) for k in range(J)]]
    csv = tmp_path / "hand.csv"
    csv.write_text(("\n".join(",".join(repr(v) for v in row) for _ in range(3))) + "\n")
    motion = read_any_motion(csv, robot="g1", fps=25.0)
    assert motion.fps == 25.0 and motion.robot == "g1"
    c = math.cos(math.pi / 4)
    np.testing.assert_allclose(motion.qpos[0, :7], [1.0, 2.0, 0.8, c, 0.0, 0.0, c], atol=1e-12)
    np.testing.assert_allclose(motion.qpos[0, 7:], [0.1 * (k + 1) for k in range(J)], atol=1e-12)
    # The root body's world position is the base's, its x axis along world y (the turn).
    np.testing.assert_allclose(motion.body_pos_w[0, 0], [1.0, 2.0, 0.8], atol=1e-12)


@pytest.mark.parametrize(
    ("text", "flags", "expect"),
    [
        ("1,2,3\n", ["--robot", "g1", "--fps", "30"], "3 columns"),
        ("a,b,c,d,e,f,g,h\n", ["--robot", "g1", "--fps", "30"], "row 1: not a comma-separated"),
        ("0,0,1,0,0,0,1,0\n0,0,1,0,0,0,1\n", ["--robot", "g1", "--fps", "30"], "row 2 has 7"),
        ("0,0,1,0,0,0,1,nan\n", ["--robot", "g1", "--fps", "30"], "row 1, column 8"),
        ("0,0,1,0,0,0,0,0\n", ["--robot", "g1", "--fps", "30"], "row 1: the base quaternion"),
        ("0,0,1,0,0,0,1,0\n", ["--robot", "g1", "--fps", "30"], "1 joint columns"),
        ("0,0,1,0,0,0,1,0\n", ["--fps", "30"], "which robot? give --robot"),
        ("0,0,1,0,0,0,1,0\n", ["--robot", "g1"], "give --fps"),
        ("0,0,1,0,0,0,1,0\n", ["--robot", "atlas", "--fps", "30"], "unknown robot 'atlas'"),
        ("", ["--robot", "g1", "--fps", "30"], "no rows"),
    ],
)
def test_bad_csv_exits_2_naming_the_file_and_row(
    text: str, flags: list[str], expect: str, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    csv = tmp_path / "bad.csv"
    csv.write_text(text)
    _refused(["convert", str(csv), str(tmp_path / "o.npz"), *flags], capsys, "bad.csv", expect)
    assert not (tmp_path / "o.npz").exists()


def test_a_sidecar_with_another_joint_order_is_refused(g1_motion: Path, tmp_path: Path) -> None:
    csv = tmp_path / "m.csv"
    assert main(["convert", str(g1_motion), str(csv)]) == 0
    side = tmp_path / "m.csv.yaml"
    text = side.read_text()
    side.write_text(text.replace("left_hip_pitch_joint", "x_joint"))
    with pytest.raises(InputError, match="joint order is not robot g1's"):
        read_any_motion(csv)


def test_mutated_csv_files_are_read_or_refused(g1_motion: Path, tmp_path: Path) -> None:
    """Random cuts, inserted characters and swapped bytes: read, or an InputError naming the
    file; never another exception."""
    csv = tmp_path / "m.csv"
    assert main(["convert", str(g1_motion), str(csv)]) == 0
    text = csv.read_text()
    rng = np.random.default_rng(0)
    for case in range(40):
        chars = list(text)
        k = int(rng.integers(len(chars)))
        kind = case % 4
        if kind == 0:
            chars = chars[:k]
        elif kind == 1:
            chars.insert(k, str(rng.choice(list(",.-e\nnaNinf9 "))))
        elif kind == 2:
            del chars[k]
        else:
            j = int(rng.integers(len(chars)))
            chars[k], chars[j] = chars[j], chars[k]
        bad = tmp_path / f"c{case}.csv"
        bad.write_text("".join(chars))
        (tmp_path / f"c{case}.csv.yaml").write_text((tmp_path / "m.csv.yaml").read_text())
        try:
            read_any_motion(bad)
        except InputError as e:
            assert str(bad) in str(e) and "\n" not in str(e), e
        except HumimicError as e:
            pytest.fail(f"case {case}: {type(e).__name__}: {e}")


def test_retarget_format_csv_writes_the_motion_beside_its_npz(
    shared_data: Path, tmp_path: Path
) -> None:
    out = tmp_path / "walk.npz"
    argv = ["retarget", str(shared_data / "cmu" / "35_01.bvh"), "--out", str(out),
            "--report", str(tmp_path / "walk.json"), "--format", "csv", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    import json

    assert json.loads((tmp_path / "walk.json").read_text())["csv_written"] == str(
        tmp_path / "walk.csv"
    )
    a, b = load_motion(out), read_any_motion(tmp_path / "walk.csv")
    assert (b.robot, b.fps) == (a.robot, a.fps)
    np.testing.assert_allclose(b.qpos, a.qpos, atol=1e-8)
