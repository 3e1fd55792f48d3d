"""Whole datasets (issue 57): a folder retargeted clip by clip into a manifest; a bad clip fails
alone; a rerun redoes nothing that finished and redoes what changed; kill -9 mid-run and
resume; one worker and two give the same motions."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.motion import load_motion
from humimic.pipeline.dataset import MANIFEST_NAME
from test_cli import _trimmed_bvh


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / MANIFEST_NAME).read_text().splitlines()]


def _folder(root: Path, shared_data: Path, frames: dict[str, int]) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for name, n in frames.items():
        _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", root / f"{name}.bvh", n)
    return root


def test_a_bad_clip_fails_alone(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two good clips, a NaN array and a cut BVH: the good ones are written, the bad ones
    recorded with their reasons, the summary printed, exit 2 naming the manifest."""
    root = _folder(tmp_path / "in", shared_data, {"a_walk": 20, "d_walk": 25})
    np.save(root / "b_nan.npy", np.full((5, 53, 3), np.nan))
    (root / "c_cut.bvh").write_text((root / "a_walk.bvh").read_text()[:400])
    out = tmp_path / "out"
    code = main(["retarget", str(root), "--out", str(out), "--workers", "1", "--quiet"])
    captured = capsys.readouterr()
    assert code == 2
    assert "2 of 4 clips failed" in captured.err and MANIFEST_NAME in captured.err
    assert "2 clips retargeted" in captured.out and "failed: " in captured.out
    assert "quality over 2 clips" in captured.out
    recs = {r["key"]: r for r in _records(out)}
    assert recs.keys() == {"a_walk", "b_nan", "c_cut", "d_walk"}
    assert recs["a_walk"]["status"] == recs["d_walk"]["status"] == "done"
    assert recs["b_nan"]["status"] == "failed" and "NaN" in recs["b_nan"]["error"]
    assert recs["c_cut"]["status"] == "failed" and "c_cut.bvh" in recs["c_cut"]["error"]
    assert recs["b_nan"]["error_kind"] == "input"
    for name in ("a_walk", "d_walk"):
        report = json.loads((out / f"{name}.json").read_text())
        assert load_motion(out / f"{name}.npz").num_frames == report["frames"]
        assert recs[name]["headline"]["frames"] == report["frames"]
    assert not (out / "b_nan.npz").exists() and not (out / "c_cut.npz").exists()


def test_a_rerun_redoes_nothing_finished_and_redoes_a_changed_input(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _folder(tmp_path / "in", shared_data, {"a": 20, "b": 22})
    np.save(root / "bad.npy", np.full((5, 53, 3), np.nan))
    out = tmp_path / "out"
    argv = ["retarget", str(root), "--out", str(out), "--workers", "1", "--quiet"]
    assert main(argv) == 2
    first = _records(out)
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    # Unchanged: nothing redone, nothing appended (the refused input stays refused).
    assert main(argv) == 0
    assert _records(out) == first
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == stamps
    assert "0 clips retargeted, 3 unchanged" in capsys.readouterr().out
    # One input changed: that one alone is redone.
    _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", root / "b.bvh", 30)
    assert main(argv) == 0
    new = _records(out)[len(first) :]
    assert [r["key"] for r in new] == ["b"] and new[0]["status"] == "done"
    assert load_motion(out / "b.npz").num_frames > load_motion(out / "a.npz").num_frames
    assert (out / "a.npz").stat().st_mtime_ns == stamps["a.npz"]
    # Changed settings redo everything (the bad input is refused again).
    assert main([*argv, "--ik.smooth-weight", "0.02"]) == 2
    assert sorted(r["key"] for r in _records(out)[len(first) + 1 :]) == ["a", "b", "bad"]


def test_kill_9_mid_run_then_resume(tmp_path: Path, shared_data: Path) -> None:
    """The run is killed (SIGKILL) after its first clips are recorded: every output present
    is whole (a motion and its report), and the rerun finishes the rest, redoing none of the
    clips recorded done."""
    names = {f"clip{i}": 150 for i in range(8)}
    root = _folder(tmp_path / "in", shared_data, names)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "humimic.cli.main", "retarget", str(root), "--out", str(out),
           "--workers", "1", "--quiet"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    manifest = out / MANIFEST_NAME
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if manifest.is_file() and len(manifest.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = {r["key"]: r for r in _records(out)}
    assert 2 <= len(before) < len(names)
    for p in out.glob("*.npz"):  # whole, or not there at all
        assert load_motion(p).num_frames > 0
    done_before = {k for k, r in before.items() if r["status"] == "done"}
    assert subprocess.run(cmd, capture_output=True, timeout=600).returncode == 0
    recs = _records(out)
    keys = [r["key"] for r in recs]
    assert set(keys) == set(names)
    for k in done_before:  # not redone
        assert keys.count(k) == 1
    assert not list(out.glob(".*.tmp"))


def test_two_workers_write_what_one_writes(tmp_path: Path, shared_data: Path) -> None:
    root = _folder(tmp_path / "in", shared_data, {"a": 20, "b": 30, "c": 25})
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["retarget", str(root), "--out", str(one), "--workers", "1", "--quiet"]) == 0
    assert main(["retarget", str(root), "--out", str(two), "--workers", "2", "--quiet"]) == 0
    for name in ("a", "b", "c"):
        np.testing.assert_array_equal(load_motion(one / f"{name}.npz").qpos,
                                      load_motion(two / f"{name}.npz").qpos)  # fmt: skip
    # Largest first: the pool takes the 30-frame clip before the others.
    assert len(_records(two)) == 3


def test_bad_dataset_flags_exit_2_before_anything_is_written(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _folder(tmp_path / "in", shared_data, {"a": 20, "b": 20})
    afile = tmp_path / "afile"
    afile.write_text("x")
    for argv, expect in (
        (["--out", str(afile)], "a file, not a folder"),
        (["--out", str(tmp_path / "o"), "--workers", "0"], "--workers 0: must be in 1 to"),
        (["--out", str(tmp_path / "o"), "--report", str(tmp_path / "r.json")], "--report"),
        (["--out", str(root / "inside")], "inside the input folder"),
    ):
        assert main(["retarget", str(root), *argv, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("humimic: error: ") and expect in err, err
    assert not (tmp_path / "o").exists() and not (root / "inside").exists()


def test_refine_a_folder_with_the_manifest(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``humimic refine FOLDER``: every robot motion refined on its own (a human-positions
    ``.npz`` beside them is not a motion and is left alone, a cut motion fails alone), outcomes
    in the manifest, a rerun redoes nothing."""
    from humimic.motion import save_motion
    from test_dynamics import _walk

    root = tmp_path / "motions"
    (root / "sub").mkdir(parents=True)
    walk = _walk(shared_data)
    save_motion(walk, root / "walk.npz")
    save_motion(walk, root / "sub" / "walk2.npz")
    np.savez(root / "human.npz", positions=np.zeros((3, 2, 3)))
    (root / "cut.npz").write_bytes((root / "walk.npz").read_bytes()[:300])
    out = tmp_path / "refined"
    argv = ["refine", str(root), "--out", str(out), "--quiet", "--workers", "2",
            "--dyn.samples", "8", "--dyn.iterations", "1", "--dyn.polish_iterations", "1",
            "--robustness", "0"]  # fmt: skip
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert "2 motions refined" in captured.out and "1 of 3 motions failed" in captured.err
    recs = {r["key"]: r for r in _records(out)}
    assert recs.keys() == {"walk", "sub/walk2", "cut"}
    assert recs["walk"]["status"] == recs["sub/walk2"]["status"] == "done"
    assert recs["cut"]["status"] == "failed" and "cut.npz" in recs["cut"]["error"]
    assert main(["replay", str(out / "sub" / "walk2.npz")]) == 0
    assert main(argv) == 0  # the cut file was refused as input: not redone, not failed again
    assert len(_records(out)) == 3
    assert "0 motions refined, 3 unchanged" in capsys.readouterr().out


def test_a_manifest_line_cut_by_a_kill_costs_only_that_clip(tmp_path: Path) -> None:
    """A record cut mid-line (the run killed while writing it) is ignored, and the next record
    starts on a line of its own."""
    from humimic.pipeline.dataset import Manifest

    path = tmp_path / MANIFEST_NAME
    path.write_text('{"key": "a", "status": "done"}\n{"key": "b", "sta')
    m = Manifest(path)
    assert set(m.last) == {"a"} and m.unreadable == 1
    m.append({"key": "c", "status": "done"})
    again = Manifest(path)
    assert set(again.last) == {"a", "c"} and again.unreadable == 1
