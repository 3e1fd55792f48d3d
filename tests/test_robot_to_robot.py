"""Robot-to-robot retargeting (issue 56): a humimic motion of one robot is a clip of its
canonical key points (where its robot map puts them), which any robot's map retargets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.motion import load_motion
from humimic.pipeline.robot_clip import is_motion_file, robot_motion_clip
from test_hostile_cli import _refused


@pytest.fixture(scope="module")
def g1_walk(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("r2r") / "g1_walk.npz"
    assert main(["retarget", str(shared_data / "cmu" / "35_01.bvh"), "--out", str(out),
                 "--quiet"]) == 0  # fmt: skip
    return out


def _run(src: Path, robot: str, out: Path) -> dict:
    report = out.with_suffix(".json")
    argv = ["retarget", str(src), "--robot", robot, "--out", str(out), "--report", str(report),
            "--quiet"]  # fmt: skip
    assert main(argv) == 0
    return json.loads(report.read_text())


def test_a_g1_walk_retargets_to_the_t1_with_the_quality_bar(g1_walk: Path, tmp_path: Path) -> None:
    r = _run(g1_walk, "t1", tmp_path / "t1.npz")
    assert r["skeleton"] == "canonical" and r["robot"] == "t1"
    assert r["joint_limit_violations"] == 0
    assert r["max_ground_penetration_mm"] <= 5.0
    assert r["self_collision_frames"] == 0
    assert r["keypoint_error_mm_mean"] < 15.0
    assert load_motion(tmp_path / "t1.npz").num_frames == load_motion(g1_walk).num_frames


def test_a_robot_to_itself_reproduces_its_motion(g1_walk: Path, tmp_path: Path) -> None:
    """The G1's walk retargeted to the G1: its own key points are the targets at scale 1, so
    the output is the input up to where the retargeter puts a clip (its start at the origin,
    facing +x: a turn about z and a shift, removed here by a least-squares fit) and the IK's
    tolerance; checked on the key points by FK of both motions, not by the report."""
    a = robot_motion_clip(g1_walk).positions_w.reshape(-1, 3)
    _run(g1_walk, "g1", tmp_path / "same.npz")
    b = robot_motion_clip(tmp_path / "same.npz").positions_w.reshape(-1, 3)
    # Best turn about z and shift taking b onto a (2-D Procrustes, then the mean height).
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (b[:, :2] - cb[:2]).T @ (a[:, :2] - ca[:2])
    u, _, vt = np.linalg.svd(h)
    rot = (u @ vt).T
    fit = np.column_stack([(b[:, :2] - cb[:2]) @ rot.T + ca[:2], b[:, 2] - cb[2] + ca[2]])
    err = np.linalg.norm(fit - a, axis=1)
    assert err.mean() < 0.008, err.mean()
    assert np.percentile(err, 95) < 0.025


def test_a_legs_only_motion_cannot_drive_arms(
    g1_walk: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    legs = tmp_path / "bh.npz"
    _run(g1_walk, "berkeley_humanoid", legs)
    _refused(["retarget", str(legs), "--robot", "g1", "--out", str(tmp_path / "g1.npz")],
             capsys, "no joint 'left_shoulder' in the clip")  # fmt: skip
    assert not (tmp_path / "g1.npz").exists()


def test_only_humimic_motions_are_read_as_robot_motions(g1_walk: Path, tmp_path: Path) -> None:
    positions = tmp_path / "human.npz"
    np.savez(positions, positions=np.zeros((3, 4, 3)))
    assert is_motion_file(g1_walk) and not is_motion_file(positions)
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    assert not is_motion_file(tmp_path / "broken.npz")
