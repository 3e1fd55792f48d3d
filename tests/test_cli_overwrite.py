"""No command overwrites its own input: the output paths are checked against the inputs first."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.datasets import load_clip
from humimic.motion import save_motion
from humimic.retarget import Retargeter


def _digest(root: Path) -> dict[str, str]:
    """Every file under ``root`` with its content's hash."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in root.rglob("*")
        if p.is_file()
    }


@pytest.fixture(scope="module")
def walk_npz(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """A short G1 motion (.npz) retargeted from the CMU walk."""
    from humimic.configs import retarget_default

    clip = load_clip(shared_data / "cmu" / "35_01.bvh").slice(1, 41)
    out = Retargeter("g1", "cmu", retarget_default()).run(clip)
    path = tmp_path_factory.mktemp("walk") / "walk_g1.npz"
    save_motion(out.motion, path)
    return path


def _run(argv: list[str], root: Path, capsys: pytest.CaptureFixture[str]) -> str:
    before = _digest(root)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("humimic: error: ") and err.count("\n") == 1, err
    assert _digest(root) == before  # Nothing overwritten, nothing new, no temp files.
    return err


def test_retarget_out_equal_to_its_input(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "walk.bvh"
    shutil.copy(shared_data / "cmu" / "35_01.bvh", src)
    # A .npz input (positions) written over by its own motion.
    clip = tmp_path / "clip.npz"
    np.savez(clip, positions=np.zeros((3, 2, 3)), joint_names=np.array(["a", "b"]))
    err = _run(["retarget", str(clip), "--out", str(clip)], tmp_path, capsys)
    assert "--out" in err and "clip.npz" in err
    err = _run(
        ["retarget", str(src), "--out", str(tmp_path / "m.npz"), "--report", str(src)],
        tmp_path,
        capsys,
    )
    assert "--report" in err and "walk.bvh" in err


def test_retarget_report_equal_to_out(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "walk.bvh"
    shutil.copy(shared_data / "cmu" / "35_01.bvh", src)
    out = tmp_path / "m.npz"
    err = _run(["retarget", str(src), "--out", str(out), "--report", str(out)], tmp_path, capsys)
    assert "--report" in err and "--out" in err
    # The same file spelt another way is the same file.
    rel = Path("..") / tmp_path.name / "m.npz"
    err = _run(
        ["retarget", str(src), "--out", str(out), "--report", str(tmp_path / rel)],
        tmp_path,
        capsys,
    )
    assert "--report" in err


def test_refine_and_convert_do_not_overwrite_the_motion(
    walk_npz: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = walk_npz.parent
    err = _run(["refine", str(walk_npz), "--out", str(walk_npz)], root, capsys)
    assert "--out" in err and "walk_g1.npz" in err
    rep = root / "r.json"
    err = _run(
        ["refine", str(walk_npz), "--out", str(root / "x.npz"), "--report", str(walk_npz)],
        root,
        capsys,
    )
    assert "--report" in err
    assert not rep.exists()
    err = _run(["convert", str(walk_npz), str(walk_npz)], root, capsys)
    assert "walk_g1.npz" in err


def test_sysid_residual_report_is_not_the_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "log.mcap"
    assert main(["sysid", "simulate", "--duration", "2", "--out", str(log)]) == 0
    capsys.readouterr()
    err = _run(["sysid", "residual", str(log), "--report", str(log)], tmp_path, capsys)
    assert "--report" in err and "log.mcap" in err


def test_view_screenshot_is_not_the_motion(
    walk_npz: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _run(
        ["view", str(walk_npz), "--screenshot", str(walk_npz), "--port", "0"],
        walk_npz.parent,
        capsys,
    )
    assert "--screenshot" in err


def test_unknown_robot_names_the_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The parser refuses a robot the registry lacks (exit 2), listing the registered ones."""
    with pytest.raises(SystemExit) as info:
        main(["sysid", "simulate", "--robot", "atlas", "--out", str(tmp_path / "x.mcap")])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--robot" in err and "'atlas'" in err and "g1" in err and "t1" in err
    assert list(tmp_path.iterdir()) == []


def test_a_failed_command_leaves_no_empty_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The up-front checks of an output path create nothing: the folders appear with the file."""
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    err = _run(["retarget", str(bad), "--out", str(tmp_path / "new" / "sub" / "m.npz")],
               tmp_path, capsys)  # fmt: skip
    assert "bad.bvh" in err
    assert not (tmp_path / "new").exists()
    # A file where a folder must be is named.
    (tmp_path / "afile").write_text("x")
    clip = tmp_path / "walk.npy"
    np.save(clip, np.zeros((3, 2, 3)))
    err = _run(["retarget", str(clip), "--out", str(tmp_path / "afile" / "m.npz")],
               tmp_path, capsys)  # fmt: skip
    assert "afile" in err and "not a folder" in err
