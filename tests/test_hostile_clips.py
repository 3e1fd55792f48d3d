"""Hostile human-clip, map, scene and physics files: refused with one line naming the file.

Deep nesting, headers that lie about their data, frame counts that do not match the data, and
messages that must name the file. CLI cases check exit code 2, the message and that nothing
was written; library cases check the error type, the message and the right behaviour of valid
files next to the refused ones.
"""

from __future__ import annotations

import io
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npformat

from archives import zip_bytes
from humimic.cli.main import main
from humimic.datasets import HumanClip, load_bvh, load_clip, load_positions
from humimic.datasets.positions import MAX_ARRAY_BYTES
from humimic.datasets.scene import load_scene
from humimic.errors import BvhParseError, InputError, MapError, MotionDataError
from humimic.io import read_yaml
from humimic.robots.maps import load_map_file
from humimic.sim.physics import load_physics


def _files(root: Path) -> set[str]:
    """Every regular file under ``root`` (hidden temp files included), relative."""
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def _cli_refuses(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: list[str], *needles: str
) -> str:
    """Run ``humimic retarget ARGS --out tmp/out/m.npz``: exit 2, one line naming ``needles``,
    and no file written. Returns the message."""
    before = _files(tmp_path)
    code = main(["retarget", *args, "--out", str(tmp_path / "out" / "m.npz")])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("humimic: error: ") and "\n" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    assert _files(tmp_path) == before
    return err


def _bvh(num_frames: int, *, data_lines: int | None = None, depth: int = 1) -> str:
    """A chain of ``depth`` joints below the root (3 rotation channels each) with ``num_frames``
    in its header and ``data_lines`` frame lines (default: as many)."""
    text = "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n"
    text += "".join(f"JOINT J{k}\n{{\nOFFSET 0 1 0\n" for k in range(depth))
    text += "}\n" * depth + "}\n"
    rows = num_frames if data_lines is None else data_lines
    text += f"MOTION\nFrames: {num_frames}\nFrame Time: 0.01\n"
    return text + "".join(f"{k} 0 0\n" for k in range(rows))


# ----------------------------------------------------------- 1. nesting deeper than recursion


def test_deeply_nested_bvh_is_refused_by_the_cli(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    src = tmp_path / "deep.bvh"
    src.write_text(_bvh(1, depth=5000))
    _cli_refuses(capsys, tmp_path, [str(src)], "deep.bvh:", "nested more than 200 levels")


def test_bvh_nesting_limit_names_the_line_and_accepts_real_depths(tmp_path: Path) -> None:
    deep = tmp_path / "deep.bvh"
    deep.write_text(_bvh(1, depth=201))
    with pytest.raises(BvhParseError, match=r"deep\.bvh:\d+: joints nested more than 200") as e:
        load_bvh(deep)
    assert e.value.line is not None and e.value.line > 200 * 3
    ok = tmp_path / "ok.bvh"
    ok.write_text(_bvh(2, depth=200))
    clip = load_bvh(ok, units="m")
    assert clip.num_frames == 2 and len(clip.names) == 201
    assert clip.positions_w[0, -1, 2] == pytest.approx(200.0)  # y up turned to z up.


DEEP_YAML = {
    "flow": "a: " + "[" * 20000 + "]" * 20000 + "\n",
    "flow_mapping": "a: " + "{b: " * 2000 + "1" + "}" * 2000 + "\n",
    "block": "".join(" " * k + "a:\n" for k in range(3000)),
    "block_list": "".join(" " * k + "- \n" for k in range(3000)),
    "just_over": "a: " + "[" * 65 + "]" * 65 + "\n",
}


@pytest.mark.parametrize("shape", sorted(DEEP_YAML))
def test_deeply_nested_yaml_is_refused_quickly(tmp_path: Path, shape: str) -> None:
    path = tmp_path / "deep.yaml"
    path.write_text(DEEP_YAML[shape])
    start = time.perf_counter()
    with pytest.raises(InputError, match=r"deep\.yaml: nested too deeply") as e:
        read_yaml(path)
    # PyYAML's scanner is quadratic in the [ { depth: 20000 levels would take minutes.
    assert time.perf_counter() - start < 5.0
    assert "\n" not in str(e.value)


def test_yaml_at_the_depth_limit_loads(tmp_path: Path) -> None:
    path = tmp_path / "ok.yaml"
    path.write_text("a: " + "[" * 63 + "1" + "]" * 63 + "\n")
    data = read_yaml(path)
    for _ in range(64):
        data = data["a"] if isinstance(data, dict) else data[0]
    assert data == 1
    text = tmp_path / "text.yaml"  # Brackets in quoted text are not nesting unless unclosed.
    text.write_text("note: '" + "[]" * 500 + "'\n")
    assert read_yaml(text) == {"note": "[]" * 500}


def test_a_key_given_twice_is_refused_naming_it_and_its_line(tmp_path: Path) -> None:
    """A physics file naming floor_friction twice kept the last value in silence; a merge key
    (<<) that an explicit key overrides is ordinary YAML and still loads."""
    dup = tmp_path / "physics.yaml"
    dup.write_text("name: twice\nfloor_friction: 0.2\nmass_scale: 1.0\nfloor_friction: 1.0\n")
    for load in (read_yaml, load_physics):
        with pytest.raises(
            InputError, match=r"physics\.yaml.*'floor_friction' appears twice.*line 4"
        ):
            load(dup)
    nested = tmp_path / "nested.yaml"
    nested.write_text("a:\n  b: 1\n  b: 2\n")
    with pytest.raises(InputError, match="'b' appears twice"):
        read_yaml(nested)
    merged = tmp_path / "merged.yaml"
    merged.write_text("base: &x {b: 1, c: 3}\nmine:\n  <<: *x\n  b: 2\n")
    assert read_yaml(merged) == {"base": {"b": 1, "c": 3}, "mine": {"b": 2, "c": 3}}


def test_deeply_nested_map_is_refused_by_the_cli(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    src = tmp_path / "walk.bvh"
    src.write_text(_bvh(3, depth=3))
    deep = tmp_path / "deep_map.yaml"
    deep.write_text(DEEP_YAML["block"])
    args = [str(src), "--units", "m", "--map", str(deep)]
    _cli_refuses(capsys, tmp_path, args, "deep_map.yaml: nested too deeply")


@pytest.mark.parametrize("kind", ["map", "scene", "physics"])
def test_deeply_nested_map_scene_and_physics_files(tmp_path: Path, kind: str) -> None:
    path = tmp_path / f"deep_{kind}.yaml"
    path.write_text(DEEP_YAML["flow"])
    load = {"map": load_map_file, "scene": load_scene, "physics": load_physics}[kind]
    error = MapError if kind == "map" else InputError
    with pytest.raises(error, match=rf"deep_{kind}\.yaml: nested too deeply"):
        load(path)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("a: &a [*a]\n", "alias refers to the mapping or list that contains it"),
        ("a: &a {b: *a}\n", "alias refers to the mapping or list that contains it"),
        (
            "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
            + "".join(
                f"{chr(98 + k)}: &{chr(98 + k)} [{', '.join([f'*{chr(97 + k)}'] * 10)}]\n"
                for k in range(8)
            ),
            "too large once its aliases are expanded",
        ),
        ("when: 2001-13-01\n", "invalid YAML value (month must be in 1..12)"),
        ("n: !!int abc\n", "invalid YAML value"),
        ("a: [unclosed\nb: 1\n", "invalid YAML ("),
    ],
)
def test_hostile_yaml_values(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        read_yaml(path)
    message = str(e.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message


def test_yaml_aliases_that_share_without_cycles_load(tmp_path: Path) -> None:
    path = tmp_path / "shared.yaml"
    path.write_text("base: &b {x: 1}\nfirst: *b\nsecond: [*b, *b]\n")
    data = read_yaml(path)
    assert data["first"] == {"x": 1} and data["second"] == [{"x": 1}, {"x": 1}]


# ------------------------------------------------------- 2. array headers that lie about size


def _npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    buf = io.BytesIO()
    npformat.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_npy_header_claiming_1e11_frames_is_refused_by_the_cli(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    src = tmp_path / "huge.npy"
    src.write_bytes(_npy_header((10**11, 53, 3)) + np.zeros((2, 53, 3)).tobytes())
    _cli_refuses(capsys, tmp_path, [str(src)], "huge.npy", "(100000000000, 53, 3)", "GiB limit")


def test_npy_shorter_or_longer_than_its_header(tmp_path: Path) -> None:
    data = np.zeros((3, 4, 3)).tobytes()
    short = tmp_path / "short.npy"
    short.write_bytes(_npy_header((1000, 4, 3)) + data)
    with pytest.raises(MotionDataError, match=r"short\.npy: truncated: .*\(1000, 4, 3\).* 288 b"):
        load_positions(short, joint_names="abcd")
    long = tmp_path / "long.npy"
    long.write_bytes(_npy_header((2, 4, 3)) + data)
    with pytest.raises(MotionDataError, match=r"long\.npy: longer than its header says"):
        load_positions(long, joint_names="abcd")


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


@pytest.mark.parametrize("member", ["positions", "joint_names", "parents"])
def test_npz_member_header_claiming_huge_data_is_refused(tmp_path: Path, member: str) -> None:
    arrays = {
        "positions": np.zeros((2, 3, 3)),
        "joint_names": np.array(["a", "b", "c"]),
        "parents": np.array([-1, 0, 0]),
    }
    members = {f"{k}.npy": _npy(v) for k, v in arrays.items()}
    descr = arrays[member].dtype.str
    members[f"{member}.npy"] = _npy_header((10**11, 53, 3), descr) + b"\0" * 64
    path = tmp_path / "huge.npz"
    path.write_bytes(zip_bytes(members, zipfile.ZIP_DEFLATED))
    with pytest.raises(MotionDataError, match=rf"huge\.npz: array '{member}': header claims"):
        load_clip(path)


def test_npz_member_shorter_than_its_header(tmp_path: Path) -> None:
    members = {
        "positions.npy": _npy_header((50, 3, 3)) + np.zeros((2, 3, 3)).tobytes(),
        "joint_names.npy": _npy(np.array(["a", "b", "c"])),
    }
    path = tmp_path / "short.npz"
    path.write_bytes(zip_bytes(members))
    with pytest.raises(MotionDataError, match=r"short\.npz: array 'positions': truncated"):
        load_clip(path)


def test_npz_member_whose_zip_directory_lies_about_its_size(tmp_path: Path) -> None:
    frames = 10**6  # 1.2 GiB claimed, under the limit; the archive holds a few bytes.
    header = _npy_header((frames, 53, 3))
    archive = bytearray(zip_bytes({"positions.npy": header + b"\0" * 8}))
    claimed = len(header) + frames * 53 * 3 * 8
    central = archive.index(b"PK\x01\x02")
    for offset in (18, 22):  # Local header: compressed, uncompressed size.
        archive[offset : offset + 4] = claimed.to_bytes(4, "little")
    for offset in (20, 24):  # Central directory: the same.
        archive[central + offset : central + offset + 4] = claimed.to_bytes(4, "little")
    path = tmp_path / "liar.npz"
    path.write_bytes(bytes(archive))
    tracemalloc.start()
    try:
        with pytest.raises(
            MotionDataError, match=r"liar\.npz: array 'positions': cannot read \(\w"
        ):
            load_clip(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 200 * 2**20  # Memory follows the bytes really there, not the claim.


def test_npy_over_the_size_limit_is_refused_before_reading(tmp_path: Path) -> None:
    frames = MAX_ARRAY_BYTES // (53 * 3 * 8) + 1
    path = tmp_path / "big.npy"
    path.write_bytes(_npy_header((frames, 53, 3)))  # No data at all: the header alone decides.
    with pytest.raises(MotionDataError, match=r"big\.npy: header claims .* GiB limit"):
        load_clip(path)


@pytest.mark.parametrize(
    "array",
    [
        np.linspace(0, 1, 36).reshape(3, 4, 3),
        np.linspace(0, 1, 36).reshape(3, 4, 3).astype(np.float32),
        np.linspace(0, 1, 36).reshape(3, 4, 3).astype(">f8"),
        np.asfortranarray(np.linspace(0, 1, 36).reshape(3, 4, 3)),
        np.arange(36, dtype=np.int16).reshape(3, 4, 3),
    ],
    ids=["f8", "f4", "big-endian", "fortran", "int16"],
)
def test_valid_arrays_load_exactly(tmp_path: Path, array: np.ndarray) -> None:
    npy = tmp_path / "c.npy"
    np.save(npy, array)
    clip = load_positions(npy, joint_names="abcd")
    np.testing.assert_array_equal(clip.positions_w, array.astype(np.float64))
    v2 = tmp_path / "v2.npy"  # Format version 2.0 (a header over 64 KiB) reads the same.
    with open(v2, "wb") as f:
        npformat.write_array(f, array, version=(2, 0))
    np.testing.assert_array_equal(load_positions(v2, joint_names="abcd").positions_w, array)
    npz = tmp_path / "c.npz"
    np.savez_compressed(npz, positions=array, joint_names=np.array(list("abcd")), fps=50)
    clip = load_clip(npz)
    np.testing.assert_array_equal(clip.positions_w, array.astype(np.float64))
    assert clip.names == ("a", "b", "c", "d") and clip.fps == 50.0


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("fps", np.ones(3), "'fps' must be one number"),
        ("fps", np.array("thirty"), "'fps' must be one number"),
        ("parents", np.array([-1, np.inf, 0]), "'parents' must hold whole numbers"),
        ("parents", np.array([-1, 0.5, 0]), "'parents' must hold whole numbers"),
        ("parents", np.array([[-1, 0, 0]]), "'parents' must be a 1-D array of integers"),
        ("joint_names", np.array([b"a", b"b", b"c"]), "'joint_names': dtype |S1 is not"),
        ("positions", np.array([None] * 3, dtype=object), "holds Python objects"),
    ],
)
def test_npz_members_of_the_wrong_kind(
    tmp_path: Path, key: str, value: np.ndarray, expected: str
) -> None:
    arrays = {
        "positions": np.zeros((2, 3, 3)),
        "joint_names": np.array(["a", "b", "c"]),
        "fps": np.float64(30.0),
        key: value,
    }
    members = {f"{k}.npy": _npy(v) for k, v in arrays.items() if v.dtype != object}
    if value.dtype == object:
        buf = io.BytesIO()
        np.save(buf, value, allow_pickle=True)
        members[f"{key}.npy"] = buf.getvalue()
    path = tmp_path / "odd.npz"
    path.write_bytes(zip_bytes(members))
    with pytest.raises(MotionDataError) as e:
        load_clip(path)
    assert str(e.value).startswith(f"{path}: ") and expected in str(e.value)


def test_parents_of_many_joints_are_checked_in_linear_time(tmp_path: Path) -> None:
    num_joints = 20000
    path = tmp_path / "chain.npy"
    np.save(path, np.zeros((1, num_joints, 3), np.float32))
    chain = [-1, *range(num_joints - 1)]  # Each joint's parent is the one before it.
    start = time.perf_counter()
    clip = load_positions(path, joint_names=[f"j{k}" for k in range(num_joints)], parents=chain)
    assert clip.parents[-1] == num_joints - 2
    assert time.perf_counter() - start < 2.0  # Quadratic checks took seconds to minutes here.
    with pytest.raises(MotionDataError, match=r"chain\.npy: parents form a cycle"):
        load_positions(path, joint_names=[f"j{k}" for k in range(num_joints)],
                       parents=[num_joints - 1, *range(num_joints - 1)])  # fmt: skip


# --------------------------------------------- 3. BVH frame lines that do not match Frames:


def test_bvh_with_more_frame_lines_than_frames_is_refused_by_the_cli(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    src = tmp_path / "more.bvh"
    text = _bvh(3, data_lines=5)
    src.write_text(text)
    first_extra = text.split("\n").index("3 0 0") + 1
    _cli_refuses(
        capsys, tmp_path, [str(src)], f"more.bvh:{first_extra}:", "5 non-empty lines", "says 3"
    )


def test_bvh_with_fewer_frame_lines_than_frames_is_refused_by_the_cli(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    src = tmp_path / "fewer.bvh"
    text = _bvh(5, data_lines=3)
    src.write_text(text)
    last = text.split("\n").index("2 0 0") + 1
    _cli_refuses(capsys, tmp_path, [str(src)], f"fewer.bvh:{last}:", "after 3 frames", "says 5")


def test_bvh_frame_counts_that_match_load(tmp_path: Path) -> None:
    path = tmp_path / "ok.bvh"
    path.write_text(_bvh(3) + "\n  \n\t\n")  # Trailing blank lines are not frames.
    clip = load_bvh(path, units="m")
    assert clip.num_frames == 3 and "ignored_lines" not in clip.meta
    extra = tmp_path / "junk.bvh"
    extra.write_text(_bvh(3) + "end of capture\n")
    with pytest.raises(BvhParseError, match=r"junk\.bvh:\d+: more frame lines .* says 3"):
        load_bvh(extra, units="m")


# ------------------------------------------------------------- 4. messages that name the file


def test_units_errors_name_the_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    src = tmp_path / "walk.bvh"
    src.write_text(_bvh(3, depth=3))
    _cli_refuses(capsys, tmp_path, [str(src), "--units", "furlong"], "walk.bvh: unknown units")
    _cli_refuses(capsys, tmp_path, [str(src), "--units", "-2"], "walk.bvh: units must be")
    npy = tmp_path / "c.npy"
    np.save(npy, np.zeros((2, 4, 3)))
    with pytest.raises(InputError, match=r"c\.npy: unknown units 'parsec'"):
        load_positions(npy, joint_names="abcd", units="parsec")


def test_clip_value_errors_name_the_source(tmp_path: Path) -> None:
    clip = HumanClip(
        names=("a",), parents=(-1,), positions_w=np.zeros((3, 1, 3)), fps=30.0, source="x.bvh"
    )
    with pytest.raises(MotionDataError, match=r"x\.bvh: target fps must be a positive number"):
        clip.resample(-1.0)
    with pytest.raises(MotionDataError, match=r"x\.bvh: resampling .* more than"):
        clip.resample(1e300)
    npz = tmp_path / "slow.npz"
    np.savez(npz, positions=np.zeros((3, 2, 3)), joint_names=np.array(["a", "b"]), fps=1e-320)
    with pytest.raises(MotionDataError, match=r"slow\.npz: fps [\d.e-]+ is too small"):
        load_clip(npz)


@pytest.mark.parametrize(
    ("name", "data"),
    [
        ("folder.npy", None),
        ("zip.npy", zip_bytes({"positions.npy": b"x"})),
        ("notzip.npz", b"not a zip"),
        ("pickle.npy", b"\x80\x04K\x01."),
        ("empty.bvh", b""),
        ("binary.bvh", bytes(range(256))),
        ("tiny.bvh", _bvh(1).replace("OFFSET 0 1 0", "OFFSET 0 -1e-320 0").encode()),
    ],
)
def test_loader_errors_name_the_file(tmp_path: Path, name: str, data: bytes | None) -> None:
    path = tmp_path / name
    if data is None:
        path.mkdir()
    else:
        path.write_bytes(data)
    with pytest.raises(InputError) as e:
        load_clip(path, **({"joint_names": "abcd"} if name.endswith(".npy") else {}))
    assert str(e.value).startswith(f"{path}") and "\n" not in str(e.value), str(e.value)
