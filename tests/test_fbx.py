"""FBX motion in (issue 56): files the tests write (tests/fbx_ascii.py) from a real CMU clip,
read back through pufbx and compared with the BVH reader's joint positions of the same clip,
name by name; then retargeted; then bad files."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fbx_ascii import FbxSkeleton, Take, skeleton_from_clip, write_fbx
from humimic.datasets import HumanClip, load_bvh, load_clip
from humimic.datasets import fbx as fbx_mod
from humimic.datasets.fbx import detect_up, load_fbx
from humimic.errors import InputError
from humimic.transforms import Y_UP_TO_Z_UP, quat_to_matrix

Z_UP_TO_Y_UP = Y_UP_TO_Z_UP.T


@pytest.fixture(scope="module")
def walk(shared_data: Path) -> HumanClip:
    """The CMU walk, its T-pose frame first (the FBX's rest pose), 60 frames."""
    return load_bvh(shared_data / "cmu" / "35_01.bvh").slice(0, 60)


def _skeleton(clip: HumanClip, to_file: np.ndarray = Z_UP_TO_Y_UP, scale: float = 100.0):
    assert clip.quats_w is not None
    return skeleton_from_clip(clip.names, clip.parents, clip.positions_w,
                              quat_to_matrix(clip.quats_w), clip.fps, to_file=to_file,
                              scale=scale)  # fmt: skip


def _by_name(a: HumanClip, b: HumanClip) -> np.ndarray:
    """``a``'s positions in ``b``'s joint order (the trees must agree)."""
    idx = [a.names.index(n) for n in b.names]
    for j, k in enumerate(idx):
        pa = a.parents[k]
        assert (-1 if pa < 0 else b.names.index(a.names[pa])) == b.parents[j], b.names[j]
    return a.positions_w[:, idx]


def test_cmu_walk_as_fbx_reads_back_to_the_bvh_joints(tmp_path: Path, walk: HumanClip) -> None:
    """Y up, centimetres, 120 fps, rotation order XYZ (a MotionBuilder/Motive export's
    conventions): every joint within 1e-6 m of the BVH reader's, every frame; units, up axis
    and frame rate found from the file."""
    path = write_fbx(tmp_path / "walk.fbx", _skeleton(walk))
    clip = load_fbx(path)
    assert clip.num_frames == walk.num_frames
    assert clip.fps == pytest.approx(walk.fps, rel=1e-6)
    np.testing.assert_allclose(_by_name(clip, walk), walk.positions_w, atol=1e-6)
    assert clip.meta["units"].startswith("auto: cm")
    assert clip.meta["up"] == "auto: +y"
    assert clip.skeleton == "fbx" and clip.quats_w is None
    # load_clip dispatches on the suffix.
    np.testing.assert_array_equal(load_clip(path).positions_w, clip.positions_w)


@pytest.mark.parametrize("order", ["ZXY", "YZX"])
def test_rotation_orders_z_up_metres_and_a_scaled_wrapper_node(
    tmp_path: Path, walk: HumanClip, order: str
) -> None:
    """Another rotation order, a z-up file in metres under a Blender-like ``Armature`` node
    scaled by 0.01 (joints written in centimetres): the same joints, up found as +z."""
    sk = _skeleton(walk, to_file=np.eye(3), scale=100.0)
    sk.rotation_order = order
    sk.up_axis = 2
    sk.unit_scale_cm = 100.0
    sk.wrapper = ("Armature", 0.01)
    clip = load_fbx(write_fbx(tmp_path / "walk.fbx", sk))
    np.testing.assert_allclose(_by_name(clip, walk), walk.positions_w, atol=1e-6)
    assert clip.meta["up"] == "auto: +z" and clip.meta["units"].startswith("auto: m ")
    assert "Armature" not in clip.names


def test_given_units_and_up_override_detection(tmp_path: Path, walk: HumanClip) -> None:
    path = write_fbx(tmp_path / "walk.fbx", _skeleton(walk))
    clip = load_fbx(path, units="mm", up="y")
    np.testing.assert_allclose(_by_name(clip, walk), walk.positions_w / 10.0, atol=1e-7)
    assert clip.meta["up"] == "y" and clip.meta["units"] == "given: mm"


def test_several_takes_the_first_by_default_or_by_name(tmp_path: Path, walk: HumanClip) -> None:
    sk = _skeleton(walk)
    first = sk.takes[0]
    later = Take(name="later", fps=first.fps, rotations=first.rotations[20:],
                 root_translation=first.root_translation[20:])  # fmt: skip
    sk.takes = [replace(first, name="walk"), later]
    path = write_fbx(tmp_path / "two.fbx", sk)
    a = load_fbx(path)
    b = load_fbx(path, take="later")
    assert a.meta["take"] == "walk" and a.meta["takes"] == "walk, later"
    assert b.num_frames == walk.num_frames - 20
    np.testing.assert_allclose(_by_name(b, walk)[1:], walk.positions_w[21:], atol=1e-6)
    with pytest.raises(InputError, match=r"no take 'run'.*walk, later"):
        load_fbx(path, take="run")


def test_a_mixamo_fbx_retargets_like_the_bvh_walk(tmp_path: Path, walk: HumanClip) -> None:
    """End to end through the CLI: the walk as a Mixamo export names it (``mixamorig:``
    prefix; CMU's own three joints renamed so it is not taken for CMU) is matched to the Mixamo
    skeleton map by its joint names, and the G1 motion equals the BVH walk's."""
    import json

    sk = _skeleton(walk)
    cmu_only = {"LHipJoint": "LeftPelvisLink", "RHipJoint": "RightPelvisLink",
                "LowerBack": "Waist"}  # fmt: skip
    sk.names = [cmu_only.get(n, n) for n in sk.names]
    sk.prefix = "mixamorig:"
    fbx = write_fbx(tmp_path / "walk.fbx", sk)
    from humimic.configs import retarget_default
    from humimic.retarget import Retargeter

    ref = Retargeter("g1", "cmu", retarget_default()).run(walk.slice(1)).motion.qpos
    out, report = tmp_path / "g1.npz", tmp_path / "g1.json"
    cmd = [sys.executable, "-m", "humimic.cli.main", "retarget", str(fbx), "--robot", "g1",
           "--out", str(out), "--report", str(report), "--start", "1", "--quiet"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(report.read_text())["skeleton"] == "mixamo"
    qpos = np.load(out)["qpos"]
    assert qpos.shape == ref.shape
    np.testing.assert_allclose(qpos, ref, atol=1e-4)


def test_detect_up_on_written_skeletons() -> None:
    """T-pose skeletons in each axis convention: the spine above the legs gives the axis."""
    names = ["hips", "spine", "head", "l_arm", "r_arm", "l_leg", "l_foot", "r_leg", "r_foot"]
    parents = (-1, 0, 1, 1, 1, 0, 5, 0, 7)
    z_up = np.array([[0, 0, 1], [0, 0, 1.3], [0, 0, 1.6], [0, 0.7, 1.4], [0, -0.7, 1.4],
                     [0, 0.1, 0.5], [0, 0.1, 0.05], [0, -0.1, 0.5], [0, -0.1, 0.05]])  # fmt: skip
    assert len(names) == len(parents)
    assert detect_up(Path("x"), z_up, parents) == "+z"
    assert detect_up(Path("x"), z_up @ Z_UP_TO_Y_UP.T, parents) == "+y"
    assert detect_up(Path("x"), -z_up, parents) == "-z"
    swap = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]])  # z up becomes x up
    assert detect_up(Path("x"), z_up @ swap.T, parents) == "+x"
    # A chain (no hips with three branches) cannot tell.
    with pytest.raises(InputError, match=r"pass the up axis"):
        detect_up(Path("x"), z_up[:3], (-1, 0, 1))
    # The spine lying down (a sleeper's rest pose) points along no axis clearly.
    tilted = z_up.copy()
    tilted[:, 0] = tilted[:, 2]
    with pytest.raises(InputError, match=r"cannot tell the up axis"):
        detect_up(Path("x"), tilted, parents)


def test_bad_fbx_files_exit_2_naming_the_file(tmp_path: Path, walk: HumanClip) -> None:
    text = tmp_path / "notes.fbx"
    text.write_text("this is not an FBX file\n")
    with pytest.raises(InputError, match=r"notes.fbx: not a readable FBX file"):
        load_fbx(text)
    binary = tmp_path / "cut.fbx"
    binary.write_bytes(b"Kaydara FBX Binary  \x00\x1a\x00" + bytes(10))
    with pytest.raises(InputError, match=r"cut.fbx: not a readable FBX file"):
        load_fbx(binary)
    with pytest.raises(InputError, match=r"missing.fbx: no such file"):
        load_fbx(tmp_path / "missing.fbx")
    # A skeleton without a take; a file with no joints.
    sk = _skeleton(walk)
    sk.takes = []
    with pytest.raises(InputError, match=r"still.fbx: no animation"):
        load_fbx(write_fbx(tmp_path / "still.fbx", sk))
    empty = FbxSkeleton(names=[], parents=[], offsets=np.zeros((0, 3)))
    with pytest.raises(InputError, match=r"bare.fbx: no skeleton"):
        load_fbx(write_fbx(tmp_path / "bare.fbx", empty))
    path = write_fbx(tmp_path / "walk.fbx", _skeleton(walk))
    with pytest.raises(InputError, match=r"unknown up axis 'w'"):
        load_fbx(path, up="w")
    with pytest.raises(InputError, match=r"unknown units 'furlong'"):
        load_fbx(path, units="furlong")
    # The CLI: exit 2, the file named, no traceback, nothing written.
    out = tmp_path / "out.npz"
    r = subprocess.run([sys.executable, "-m", "humimic.cli.main", "retarget", str(text), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 2 and "notes.fbx" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_without_pufbx_the_error_says_what_to_install(
    tmp_path: Path, walk: HumanClip, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = write_fbx(tmp_path / "walk.fbx", _skeleton(walk))
    monkeypatch.setattr(fbx_mod, "_import_pufbx", lambda: None)
    with pytest.raises(InputError, match=r"walk.fbx: reading FBX needs .*pip install pufbx==0.1.0"):
        load_fbx(path)


def test_mutated_fbx_files_never_crash(tmp_path: Path, walk: HumanClip) -> None:
    """Bytes changed, cut out or put in at random (numbers, braces, quotes): the reader either
    reads the file or raises InputError, never anything else (a mutated key time once asked
    for 179 GiB of frames)."""
    from byte_mutants import byte_mutants, read_or_refused

    sk = _skeleton(walk.slice(0, 8))
    base = write_fbx(tmp_path / "base.fbx", sk).read_bytes()
    mutants = byte_mutants(base, 11, 80, edits=8, cut=50, put=b'0123456789-.,eE{}"\n naNinf')
    outcomes = read_or_refused(mutants, tmp_path / "mutated.fbx", load_fbx, InputError)
    assert outcomes["read"] > 0 and outcomes["refused"] > 0, outcomes
