"""Fuzz the human-clip loaders with seeded mutations of small valid files.

BVH text, ``.npy``/``.npz`` position arrays and YAML files (a map, a scene, a physics file)
are mutated at random (byte flips, truncations, line edits, hostile numbers and tokens, header
edits, wrong dtypes and shapes). Each mutant must load or raise a :class:`HumimicError`, never
another exception, and must leave no file beside itself. A failure lists the kind, the seed and
the mutations; ``MUTATORS[kind](seed)`` rebuilds that exact input.
"""

from __future__ import annotations

import io
import os
import random
import re
import traceback
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from numpy.lib import format as npformat

from archives import zip_bytes
from humimic.datasets import load_bvh, load_clip, load_positions
from humimic.datasets.scene import load_scene
from humimic.errors import HumimicError
from humimic.io import read_yaml
from humimic.robots.maps import get_map, load_map_file, map_data

# --------------------------------------------------------------------------- valid inputs

BVH = (
    "HIERARCHY\n"
    "ROOT Hips\n"
    "{\n"
    "  OFFSET 0 0 0\n"
    "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
    "  JOINT Chest\n"
    "  {\n"
    "    OFFSET 0 10 0\n"
    "    CHANNELS 3 Zrotation Xrotation Yrotation\n"
    "    End Site\n"
    "    {\n"
    "      OFFSET 0 5 0\n"
    "    }\n"
    "  }\n"
    "  JOINT LeftLeg\n"
    "  {\n"
    "    OFFSET 2 -40 0\n"
    "    CHANNELS 3 Zrotation Xrotation Yrotation\n"
    "  }\n"
    "}\n"
    "MOTION\n"
    "Frames: 3\n"
    "Frame Time: 0.0333333\n"
    "0 90 0 0 0 0 0 0 0 0 0 0\n"
    "1 90 0 10 20 30 5 6 7 -10 0 4\n"
    "2 91 0 0 0 0 0 0 0 0 0 0\n"
)

NAMES = ["a", "b", "c", "d"]
POSITIONS = np.linspace(-1.0, 1.0, 3 * 4 * 3).reshape(3, 4, 3)

SCENE = (
    "schema_version: 1\n"
    "fps: 10\n"
    "objects:\n"
    "  - {name: step, box: [1.0, 0.8, 0.2], pos: [0.5, 0, 0.1]}\n"
    "  - name: pad\n"
    "    box: [0.4, 0.4, 0.05]\n"
    "    quat: [1, 0, 0, 0]\n"
)

PHYSICS = (
    "description: a test robot\n"
    "robot: g1\n"
    "floor_friction: 0.25\n"
    "com_offset: {torso_link: [-0.08, 0.0, -0.03]}\n"
    "effects:\n"
    "  - payload_mass:torso_link=6.0\n"
)

MAP_TEXT = yaml.safe_dump(map_data(get_map("cmu", "g1")), sort_keys=False)
MAP_BODIES = set(re.findall(r"^\s+body: (\S+)$", MAP_TEXT, flags=re.MULTILINE))

# Values that break parsers: not numbers, not finite, too large for a float, negative, empty.
HOSTILE_NUMBERS = [
    "nan", "inf", "-inf", "1e308", "-1e308", "1e400", "99999999999999999999999999", "-1", "-0",
    "0", "", "1_0", "0x10", "1e-320", ".nan", ".inf", "2001-13-01", "!!int abc", "~", "true",
]  # fmt: skip
BVH_TOKENS = ["{", "}", "JOINT", "End", "Site", "ROOT", "MOTION", "CHANNELS", "OFFSET", "Frames:",
              "HIERARCHY", "Frame Time:", "CHANNELS 999999999", "Xrotation", "Xposition", "\t",
              "CHANNELS -3", "Frames: 100000000000", "Frames: 0"]  # fmt: skip
YAML_TOKENS = ["[", "]", "{", "}", ": ", "- ", "&a ", "*a", "!!binary x", "'", '"', "\t", "? ",
               "!!python/object/apply:os.system ['true']", "<<: *a", "!!set {a}", "%TAG",
               "[" * 300, "{a: " * 100, "&r [*r]", "|", ">", "#", "\x00", "\ufeff", "---"]  # fmt: skip
DTYPES = ["<f4", ">f8", "|O", "<U8", "|b1", "<c16", "|V0", "<m8", "<M8[s]", "(3,)<f8", "<f2",
          "<i8", "|u1", "|S4", "[('x', '<f8')]", "'garbage'", "<V24"]  # fmt: skip
SHAPES = ["(100000000000, 53, 3)", "(3, 4, 3, 1)", "(-1, 4, 3)", "()", "(0, 4, 3)", "(3, 4)",
          "(2, 4, 3)", "(4, 4, 3)", "(3, 4, 'a')", "(1e3,)", "(3, 0, 3)", "(3, -4, -3)",
          "(10**9, 10**9, 10**9)", "(3, 4, 3" + ", 1" * 40 + ")", "[3, 4, 3]", "None"]  # fmt: skip


# --------------------------------------------------------------------------- mutations


def _flip(rng: random.Random, data: bytes, log: list[str]) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(b))
        b[i] = rng.randrange(256) if rng.random() < 0.5 else rng.randrange(32, 127)  # Or ASCII.
        log.append(f"byte {i} = {b[i]}")
    return bytes(b)


def _truncate(rng: random.Random, data: bytes, log: list[str]) -> bytes:
    n = rng.randrange(len(data))
    log.append(f"truncate to {n} bytes")
    return data[:n]


def _text_mutations(
    rng: random.Random, text: str, tokens: list[str], log: list[str], rounds: int
) -> str:
    """Line and token edits on text (the caller may flip or truncate the bytes after)."""
    for _ in range(rounds):
        lines = text.split("\n")
        op = rng.choice(["dup", "del", "swap", "number", "token", "indent"])
        i = rng.randrange(len(lines))
        if op == "dup":
            lines.insert(i, lines[i])
        elif op == "del":
            del lines[i]
        elif op == "swap":
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "number":
            spans = [m.span() for m in re.finditer(r"-?\d+(\.\d+)?(e-?\d+)?", text)]
            if spans:
                a, b = rng.choice(spans)
                new = rng.choice(HOSTILE_NUMBERS)
                log.append(f"number at {a} {text[a:b]!r} -> {new!r}")
                text = text[:a] + new + text[b:]
                continue
        elif op == "token":
            words = lines[i].split(" ")
            k = rng.randrange(len(words))
            new = rng.choice(tokens)
            if rng.random() < 0.5:
                words.insert(k, new)
                op = f"insert {new!r} at word {k}"
            else:
                words[k] = new
                op = f"replace word {k} with {new!r}"
            lines[i] = " ".join(words)
        elif op == "indent":
            lines[i] = " " * rng.randint(0, 9) + lines[i].lstrip()
        log.append(f"{op} line {i + 1}")
        text = "\n".join(lines)
    return text


def _bytes_mutations(rng: random.Random, data: bytes, log: list[str]) -> bytes:
    if rng.random() < 0.3:
        data = _flip(rng, data, log)
    if rng.random() < 0.15 and data:
        data = _truncate(rng, data, log)
    return data


def mutate_bvh(seed: int) -> tuple[bytes, list[str]]:
    """A mutant of :data:`BVH` and the list of its mutations."""
    rng = random.Random(f"bvh-{seed}")
    log: list[str] = []
    text = _text_mutations(rng, BVH, BVH_TOKENS, log, rng.randint(0, 3))
    data = _bytes_mutations(rng, text.encode(), log)
    if rng.random() < 0.05:  # Nesting deeper than Python's recursion limit.
        deep = "".join(f"JOINT J{k}\n{{\nOFFSET 0 1 0\n" for k in range(1500))
        data = data.replace(b"  JOINT LeftLeg\n", deep.encode() + b"}\n" * 1500 + b"JOINT L\n")
        log.append("1500 nested joints")
    return data, log


def _npy(array: np.ndarray | np.generic, *, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=allow_pickle)
    return buf.getvalue()


def _header(header: dict[str, object], version: tuple[int, int] = (1, 0)) -> bytes:
    buf = io.BytesIO()
    write = (
        npformat.write_array_header_1_0 if version == (1, 0) else npformat.write_array_header_2_0
    )
    write(buf, header)
    return buf.getvalue()


def _odd_array(rng: random.Random, log: list[str]) -> bytes:
    """A well-formed .npy whose array has the wrong shape, dtype or values."""
    choices: list[tuple[str, Callable[[], bytes]]] = [
        ("2-D", lambda: _npy(np.zeros((3, 4)))),
        ("0 frames", lambda: _npy(np.zeros((0, 4, 3)))),
        ("0 joints", lambda: _npy(np.zeros((3, 0, 3)))),
        ("xy only", lambda: _npy(np.zeros((3, 4, 2)))),
        ("0-d", lambda: _npy(np.float64(1.0))),
        ("strings", lambda: _npy(np.full((3, 4, 3), "x"))),
        ("bool", lambda: _npy(np.ones((3, 4, 3), bool))),
        ("complex", lambda: _npy(np.ones((3, 4, 3), complex))),
        ("object", lambda: _npy(np.array([{"a": 1}], dtype=object), allow_pickle=True)),
        ("object 3-D", lambda: _npy(np.full((3, 4, 3), None, dtype=object), allow_pickle=True)),
        ("int8", lambda: _npy(np.ones((3, 4, 3), np.int8))),
        ("float16", lambda: _npy(POSITIONS.astype(np.float16))),
        ("big-endian", lambda: _npy(POSITIONS.astype(">f8"))),
        ("fortran", lambda: _npy(np.asfortranarray(POSITIONS))),
        ("nan", lambda: _npy(np.where(POSITIONS > 0.5, np.nan, POSITIONS))),
        ("inf", lambda: _npy(np.full((3, 4, 3), np.inf))),
        ("1e308", lambda: _npy(np.full((3, 4, 3), 1e308))),
        ("timedelta", lambda: _npy(np.ones((3, 4, 3), "m8[s]"))),
        ("datetime", lambda: _npy(np.ones((3, 4, 3), "M8[s]"))),
        ("records", lambda: _npy(np.zeros((3, 4, 3), [("x", "<f8")]))),
        ("53 joints", lambda: _npy(np.zeros((2, 53, 3)))),
        ("many joints", lambda: _npy(np.zeros((1, 20000, 3), np.float32))),
        ("zip", lambda: zip_bytes({"positions.npy": _npy(POSITIONS)})),
        ("random", lambda: rng.randbytes(rng.randrange(200))),
        ("empty", lambda: b""),
        ("version 3.0", lambda: b"\x93NUMPY\x03\x00" + _header(_valid_header())[8:]),
        ("version 9.9", lambda: b"\x93NUMPY\x09\x09" + _header(_valid_header())[8:]),
    ]
    name, make = rng.choice(choices)
    log.append(f"array: {name}")
    return make()


def _valid_header() -> dict[str, object]:
    return {"descr": "<f8", "fortran_order": False, "shape": POSITIONS.shape}


def _npy_mutant(rng: random.Random, log: list[str], valid: bytes) -> bytes:
    """A mutant of the .npy bytes ``valid`` (holding :data:`POSITIONS`)."""
    data_start = len(_header(_valid_header()))
    payload = valid[data_start:]
    op = rng.choice(["shape", "descr", "fortran", "header_text", "bytes", "array", "version2"])
    if op == "shape":
        shape = rng.choice(SHAPES)
        text = repr(_valid_header()).replace(repr(POSITIONS.shape), shape)
        log.append(f"header shape {shape}")
        data = _raw_header(text) + payload
    elif op == "descr":
        descr = rng.choice(DTYPES)
        text = repr(_valid_header()).replace("'<f8'", descr if descr[0] in "['" else repr(descr))
        log.append(f"header descr {descr}")
        data = _raw_header(text) + payload
    elif op == "fortran":
        log.append("fortran_order True")
        data = _header({**_valid_header(), "fortran_order": True}) + payload
    elif op == "header_text":
        text = repr(_valid_header())
        i = rng.randrange(len(text))
        new = rng.choice(["{", "}", "(", ")", ",", "'", "x", "9" * 30, "(" * 300, ""])
        log.append(f"header text at {i} -> {new!r}")
        data = _raw_header(text[:i] + new + text[i + 1 :]) + payload
    elif op == "version2":
        log.append("format version 2.0")
        data = _header(_valid_header(), (2, 0)) + payload
    elif op == "array":
        data = _odd_array(rng, log)
    else:
        data = valid
    data = _bytes_mutations(rng, data, log) if data else data
    if rng.random() < 0.1:
        extra = rng.randbytes(rng.randrange(1, 64))
        log.append(f"append {len(extra)} bytes")
        data += extra
    return data


def _raw_header(text: str) -> bytes:
    """A version 1.0 header holding ``text`` as is (padded as numpy pads it)."""
    body = text.encode("latin-1", "replace")
    pad = -(10 + len(body) + 1) % 64
    body = body + b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + len(body).to_bytes(2, "little") + body


def mutate_npy(seed: int) -> tuple[bytes, list[str]]:
    """A mutant ``.npy`` of :data:`POSITIONS` and the list of its mutations."""
    rng = random.Random(f"npy-{seed}")
    log: list[str] = []
    return _npy_mutant(rng, log, _npy(POSITIONS)), log


def mutate_npz(seed: int) -> tuple[bytes, list[str]]:
    """A mutant ``.npz`` clip (positions, joint_names, fps, parents) and its mutations."""
    rng = random.Random(f"npz-{seed}")
    log: list[str] = []
    members = {
        "positions.npy": _npy(POSITIONS),
        "joint_names.npy": _npy(np.array(NAMES)),
        "fps.npy": _npy(np.float64(30.0)),
        "parents.npy": _npy(np.array([-1, 0, 1, 1])),
    }
    odd_members: dict[str, list[tuple[str, np.ndarray | np.generic]]] = {
        "joint_names.npy": [
            ("ints", np.arange(4)),
            ("2-D", np.array([NAMES, NAMES])),
            ("bytes", np.array([n.encode() for n in NAMES])),
            ("0-d", np.array("abcd")),
            ("3 names", np.array(NAMES[:3])),
            ("repeated", np.array(["a", "a", "b", "c"])),
            ("empty strings", np.array(["", "", "", ""])),
        ],
        "fps.npy": [
            ("3 values", np.ones(3)),
            ("text", np.array("thirty")),
            ("nan", np.float64(np.nan)),
            ("-1", np.float64(-1.0)),
            ("0", np.int64(0)),
            ("1e-320", np.float64(1e-320)),
            ("1e308", np.float64(1e308)),
            ("complex", np.complex128(1j)),
            ("bool", np.bool_(True)),
            ("empty", np.zeros(0)),
        ],
        "parents.npy": [
            ("cycle", np.array([-1, 2, 1, 0])),
            ("self", np.array([-1, 1, 0, 0])),
            ("out of range", np.array([-1, 0, 9, 0])),
            ("below -1", np.array([-1, -5, 0, 0])),
            ("halves", np.array([-1, 0.5, 0, 0])),
            ("inf", np.array([-1, np.inf, 0, 0])),
            ("nan", np.array([-1, np.nan, 0, 0])),
            ("2-D", np.array([[-1, 0], [0, 0]])),
            ("0-d", np.array(-1)),
            ("too few", np.array([-1, 0])),
            ("huge", np.array([-1, 2**62, 0, 0])),
            ("text", np.array(["-1", "0", "0", "0"])),
            ("no root", np.array([1, 2, 3, 0])),
        ],
    }
    for _ in range(rng.randint(1, 3)):
        op = rng.choice(["member", "odd", "delete", "extra", "rename", "object"])
        name = rng.choice(sorted(members))
        if op == "member":
            log.append(f"{name}:")
            members[name] = _npy_mutant(rng, log, members[name])
        elif op == "odd" and name in odd_members:
            what, value = rng.choice(odd_members[name])
            log.append(f"{name} = {what}")
            members[name] = _npy(value)
        elif op == "delete":
            log.append(f"delete {name}")
            members.pop(name)
        elif op == "extra":
            log.append("extra member")
            members["extra.npy"] = rng.randbytes(32)
        elif op == "rename" and name.endswith(".npy"):
            log.append(f"rename {name} -> {name[:-4]}")
            members[name[:-4]] = members.pop(name)
        elif op == "object":
            log.append(f"{name} = object array")
            members[name] = _npy(np.array([None, 1], dtype=object), allow_pickle=True)
        if not members:
            break
    compression = zipfile.ZIP_DEFLATED if rng.random() < 0.3 else zipfile.ZIP_STORED
    if compression == zipfile.ZIP_DEFLATED:
        log.append("deflated")
    data = _bytes_mutations(rng, zip_bytes(members, compression), log)
    return data, log


_YAML_BASES = {"map": MAP_TEXT, "scene": SCENE, "physics": PHYSICS}


def mutate_yaml(seed: int) -> tuple[bytes, list[str], str]:
    """A mutant of a map, scene or physics YAML file; its mutations and which file it was."""
    rng = random.Random(f"yaml-{seed}")
    kind = rng.choice(sorted(_YAML_BASES))
    log: list[str] = [kind]
    text = _text_mutations(rng, _YAML_BASES[kind], YAML_TOKENS, log, rng.randint(1, 4))
    if rng.random() < 0.05:  # Aliases that expand a thousand-fold at each level.
        text = "a: &a [x]\n" + "".join(
            f"{chr(98 + k)}: &{chr(98 + k)} [{', '.join([f'*{chr(97 + k)}'] * 10)}]\n"
            for k in range(9)
        )
        log.append("billion laughs")
    elif rng.random() < 0.05:  # Nesting deeper than a parser's recursion allows.
        n = rng.choice([70, 300, 5000])
        text = "a: " + rng.choice(["[", "{b: "]) * n + "1" + rng.choice(["]", "}"]) * n + "\n"
        log.append(f"nested {n} deep")
    return _bytes_mutations(rng, text.encode(), log), log, kind


MUTATORS: dict[str, Callable[[int], tuple]] = {
    "bvh": mutate_bvh,
    "npy": mutate_npy,
    "npz": mutate_npz,
    "yaml": mutate_yaml,
}


# --------------------------------------------------------------------------- the harness


def _run(folder: Path, name: str, data: bytes, load: Callable[[Path], object]) -> str | None:
    """Write ``data`` as ``folder/name`` and load it. Returns what went wrong, else None: an
    exception that is not a :class:`HumimicError`, a message that is not one line naming the
    file, or a file left beside the input."""
    path = folder / name
    path.write_bytes(data)
    problem = None
    try:
        load(path)
    except HumimicError as e:
        if name not in str(e) or "\n" in str(e):
            problem = f"{type(e).__name__} not one line naming {name}: {str(e)[:300]!r}"
    except Exception as e:  # Any other exception is the failure being hunted.
        where = traceback.extract_tb(e.__traceback__)[-1]
        problem = f"{type(e).__name__}: {str(e)[:200]} (at {where.filename}:{where.lineno})"
    left = sorted(set(os.listdir(folder)) - {name})
    if left:
        problem = f"{problem or 'no error'}; left files {left}"
        for f in left:
            (folder / f).unlink()
    path.unlink()
    return problem


def _fuzz(tmp_path: Path, kind: str, cases: int, load: Callable[..., object]) -> None:
    failures = []
    for seed in range(cases):
        data, log, *rest = MUTATORS[kind](seed)
        problem = _run(tmp_path, f"input.{'yaml' if kind == 'yaml' else kind}", data,
                       lambda p, seed=seed, rest=rest: load(p, seed, *rest))  # fmt: skip
        if problem is not None:
            failures.append(f"{kind} seed {seed} {log}: {problem}")
    assert not failures, f"{len(failures)} of {cases} mutants failed:\n" + "\n".join(failures[:20])


def _load_bvh(path: Path, seed: int) -> object:
    if seed % 3 == 0:
        return load_clip(path)
    return load_bvh(path, units=("cm", 0.01, "auto")[seed % 3], up="yz"[seed % 2])


def _load_npy(path: Path, seed: int) -> object:
    if seed % 3 == 0:
        return load_clip(path)  # Names are needed unless it has 53 joints.
    return load_positions(path, joint_names=NAMES, up="yz"[seed % 2], units="cm")


def _load_npz(path: Path, seed: int) -> object:
    clip = load_clip(path)
    return clip.resample(60.0)


def _load_yaml(path: Path, seed: int, kind: str) -> object:
    data = read_yaml(path)
    if kind == "map":
        load_map_file(path).validate(None, MAP_BODIES)
    elif kind == "scene":
        load_scene(path)
    # The physics loader is fuzzed through read_yaml only: its module imports torch (seconds).
    return data


@pytest.mark.parametrize(
    ("kind", "cases", "load"),
    [
        ("bvh", 600, _load_bvh),
        ("npy", 500, _load_npy),
        ("npz", 400, _load_npz),
        ("yaml", 400, _load_yaml),
    ],
)
def test_mutants_load_or_raise_humimic_errors(
    tmp_path: Path, kind: str, cases: int, load: Callable[..., object]
) -> None:
    _fuzz(tmp_path, kind, cases, load)


def test_unmutated_inputs_load(tmp_path: Path) -> None:
    """The fuzz bases are valid: a mutant that fails fails because of its mutation."""
    (tmp_path / "c.bvh").write_text(BVH)
    assert load_clip(tmp_path / "c.bvh").num_frames == 3
    np.save(tmp_path / "c.npy", POSITIONS)
    assert load_positions(tmp_path / "c.npy", joint_names=NAMES).num_frames == 3
    members = {
        "positions.npy": _npy(POSITIONS),
        "joint_names.npy": _npy(np.array(NAMES)),
        "fps.npy": _npy(np.float64(30.0)),
        "parents.npy": _npy(np.array([-1, 0, 1, 1])),
    }
    (tmp_path / "c.npz").write_bytes(zip_bytes(members))
    clip = load_clip(tmp_path / "c.npz")
    assert clip.names == tuple(NAMES) and clip.fps == 30.0 and clip.parents == (-1, 0, 1, 1)
    for kind, text in _YAML_BASES.items():
        (tmp_path / f"{kind}.yaml").write_text(text)
        assert isinstance(read_yaml(tmp_path / f"{kind}.yaml"), dict)
    load_map_file(tmp_path / "map.yaml").validate(None, MAP_BODIES)
    assert len(load_scene(tmp_path / "scene.yaml").objects) == 2


def test_mutations_are_reproducible() -> None:
    for kind, mutate in MUTATORS.items():
        assert mutate(7) == mutate(7), kind
