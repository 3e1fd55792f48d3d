"""Loading arrays of global joint positions (.npy / .npz), holosoma climbing clips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from humimic.datasets import (
    HOLOSOMA_JOINTS,
    HOLOSOMA_PARENTS,
    climb_clip_paths,
    estimate_height,
    load_clip,
    load_positions,
)
from humimic.errors import InputError, MotionDataError


def holosoma_clips(shared_data: Path) -> list[Path]:
    paths = climb_clip_paths(shared_data / "holosoma_climb")
    assert len(paths) == 3, paths
    return paths


def test_holosoma_names_and_tree() -> None:
    assert len(HOLOSOMA_JOINTS) == 53 == len(set(HOLOSOMA_JOINTS))
    assert HOLOSOMA_JOINTS[:5] == ("Hips", "Spine", "Spine1", "Neck", "Head")
    assert HOLOSOMA_JOINTS[9] == "LeftHandThumb1" and HOLOSOMA_JOINTS[23] == "LeftHandPinky3"
    assert HOLOSOMA_JOINTS[28] == "RightHandThumb1" and HOLOSOMA_JOINTS[42] == "RightHandPinky3"
    assert HOLOSOMA_JOINTS[43:] == tuple(
        [
            "LeftUpLeg",
            "LeftLeg",
            "LeftFoot",
            "LeftToeBase",
            "RightUpLeg",
            "RightLeg",
            "RightFoot",
            "RightToeBase",
            "LeftFootMod",
            "RightFootMod",
        ]
    )
    assert HOLOSOMA_PARENTS.count(-1) == 1 and HOLOSOMA_PARENTS[0] == -1

    def parent(name: str) -> str:
        return HOLOSOMA_JOINTS[HOLOSOMA_PARENTS[HOLOSOMA_JOINTS.index(name)]]

    assert parent("Head") == "Neck" and parent("Neck") == "Spine1"
    assert parent("LeftShoulder") == "Spine1" and parent("RightHand") == "RightForeArm"
    assert parent("LeftHandIndex1") == "LeftHand" and parent("RightHandRing3") == "RightHandRing2"
    assert parent("LeftUpLeg") == "Hips" and parent("RightFootMod") == "RightFoot"


@pytest.mark.parametrize("k", [0, 1, 2])
def test_holosoma_clips_load(shared_data: Path, k: int) -> None:
    path = holosoma_clips(shared_data)[k]
    clip = load_clip(path)
    raw = np.load(path)
    assert clip.positions_w.shape == raw.shape == (raw.shape[0], 53, 3)
    assert clip.num_frames > 1000
    assert clip.fps == 120.0
    assert clip.skeleton == "holosoma"
    assert clip.names == HOLOSOMA_JOINTS and clip.parents == HOLOSOMA_PARENTS
    assert clip.quats_w is None
    np.testing.assert_allclose(clip.positions_w, raw, atol=0)
    # z up, metres: the head is above the feet and the performer is adult-sized.
    first = clip.positions_w[0]
    assert first[clip.index("Head"), 2] > first[clip.index("Hips"), 2] > first[45, 2]
    assert 1.5 < estimate_height(clip) < 2.0
    # The tree is real: every bone keeps its length over the clip.
    for j, p in enumerate(clip.parents):
        if p >= 0:
            d = np.linalg.norm(raw[:, j] - raw[:, p], axis=-1)
            assert np.ptp(d) < 1e-3


def test_npz_with_names_and_fps(tmp_path: Path) -> None:
    pos = np.random.default_rng(0).normal(size=(4, 3, 3))
    path = tmp_path / "c.npz"
    np.savez(path, positions=pos, joint_names=np.array(["a", "b", "c"]), fps=np.float64(30.0))
    clip = load_clip(path)
    assert clip.names == ("a", "b", "c")
    assert clip.fps == 30.0
    assert clip.parents == (-1, 0, 0)  # Unknown skeleton: a star rooted at joint 0.
    assert clip.skeleton == "unknown"
    assert load_positions(path, fps=60.0).fps == 60.0


def test_npy_needs_names_unless_holosoma(tmp_path: Path) -> None:
    path = tmp_path / "c.npy"
    np.save(path, np.zeros((2, 4, 3)))
    with pytest.raises(InputError, match=r"c\.npy.*joint_names"):
        load_positions(path)
    clip = load_positions(path, joint_names=["a", "b", "c", "d"], skeleton="custom")
    assert clip.skeleton == "custom" and clip.fps == 120.0


def test_units_and_up_axis(tmp_path: Path) -> None:
    path = tmp_path / "c.npy"
    np.save(path, np.array([[[0.0, 0.0, 0.0], [1.0, 100.0, 3.0]]]))
    clip = load_positions(path, joint_names=["a", "b"], up="y", units="cm")
    np.testing.assert_allclose(clip.positions_w[0, 1], [0.01, -0.03, 1.0])
    with pytest.raises(InputError, match="up axis"):
        load_positions(path, joint_names=["a", "b"], up="x")
    with pytest.raises(InputError, match="units"):
        load_positions(path, joint_names=["a", "b"], units="feet")


def test_nan_names_frame_and_joint(tmp_path: Path) -> None:
    pos = np.zeros((5, 53, 3), dtype=np.float32)
    pos[3, 44, 1] = np.nan
    pos[4, 0, 0] = np.inf
    path = tmp_path / "bad.npy"
    np.save(path, pos)
    with pytest.raises(MotionDataError) as info:
        load_positions(path)
    message = str(info.value)
    assert "bad.npy" in message and "frame 3" in message and "LeftLeg" in message
    assert "2 bad frames" in message


def test_zero_frames(tmp_path: Path) -> None:
    path = tmp_path / "empty.npy"
    np.save(path, np.zeros((0, 53, 3)))
    with pytest.raises(MotionDataError, match=r"empty\.npy.*zero frames"):
        load_positions(path)


@pytest.mark.parametrize("shape", [(10, 53), (10, 53, 2), (2, 10, 53, 3)])
def test_wrong_shape(tmp_path: Path, shape: tuple[int, ...]) -> None:
    path = tmp_path / "shape.npy"
    np.save(path, np.zeros(shape))
    with pytest.raises(MotionDataError, match=r"shape\.npy.*shape"):
        load_positions(path)


def test_names_length_mismatch(tmp_path: Path) -> None:
    path = tmp_path / "n.npy"
    np.save(path, np.zeros((2, 3, 3)))
    with pytest.raises(MotionDataError, match=r"n\.npy: 2 joint names for 3 joints"):
        load_positions(path, joint_names=["a", "b"])


def test_duplicate_names(tmp_path: Path) -> None:
    path = tmp_path / "d.npz"
    np.savez(path, positions=np.zeros((2, 3, 3)), joint_names=np.array(["a", "b", "a"]))
    with pytest.raises(MotionDataError, match=r"d\.npz.*duplicate joint names: a"):
        load_positions(path)


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"missing\.npy"):
        load_positions(tmp_path / "missing.npy")
    txt = tmp_path / "clip.csv"
    txt.write_text("1,2,3\n")
    with pytest.raises(InputError, match=r"clip\.csv.*\.npy"):
        load_positions(txt)
    strings = tmp_path / "s.npy"
    np.save(strings, np.full((2, 3, 3), "x"))
    with pytest.raises(MotionDataError, match=r"s\.npy.*dtype"):
        load_positions(strings, joint_names=["a", "b", "c"])
    pickled = tmp_path / "p.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(MotionDataError, match=r"p\.npy"):
        load_positions(pickled)
    no_key = tmp_path / "k.npz"
    np.savez(no_key, pos=np.zeros((2, 3, 3)))
    with pytest.raises(MotionDataError, match=r"k\.npz.*'positions'"):
        load_positions(no_key)
    garbage = tmp_path / "g.npy"
    garbage.write_bytes(b"not numpy at all")
    with pytest.raises(InputError, match=r"g\.npy"):
        load_positions(garbage)


def test_bad_parents(tmp_path: Path) -> None:
    path = tmp_path / "c.npy"
    np.save(path, np.zeros((2, 3, 3)))
    names = ["a", "b", "c"]
    with pytest.raises(MotionDataError, match="cycle"):
        load_positions(path, joint_names=names, parents=[-1, 2, 1])
    with pytest.raises(MotionDataError, match="parent index 7"):
        load_positions(path, joint_names=names, parents=[-1, 7, 0])
    clip = load_positions(path, joint_names=names, parents=[-1, 0, 1])
    assert clip.parents == (-1, 0, 1)
