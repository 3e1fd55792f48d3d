"""Fuzz the robot motion readers: seeded mutations of a small valid motion, as ``.npz`` and as
MCAP, fed to :func:`load_motion` / :func:`read_motion_mcap` and to ``humimic convert``.

Each case fails on an exception that is not a :class:`HumimicError`, on an exit code other
than 0 or 2 (and on 0 where the reader refused the file, or 2 where it read it), on a message
that is not one line naming the input, on any file left beside the input when the conversion
is refused, on an output that does not read back, and on a changed input. Failures name the
format, the kind of mutation, the seed and what was changed.
"""

from __future__ import annotations

import io
import json
import math
import traceback
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer

from archives import flip_bytes, truncate_bytes
from humimic.cli.main import main
from humimic.errors import HumimicError
from humimic.formats.mcap import SCHEMAS, TOPICS, read_mcap, read_motion_mcap, write_motion_mcap
from humimic.motion import Motion, load_motion, motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model
from humimic.robots.model import motion_model

FRAMES = 4
CASES_PER_KIND = 20  # 13 .npz kinds and 10 MCAP kinds: 460 cases.


@dataclass(frozen=True)
class Base:
    """The valid motion, its files' bytes, its arrays and its MCAP records."""

    motion: Motion
    npz: bytes
    mcap: bytes
    arrays: dict[str, np.ndarray]
    metadata: dict[str, dict[str, str]]
    messages: list[tuple[str, str, int, Any]]  # (topic, schema, log time, message)


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Base:
    return make_base(tmp_path_factory.mktemp("base"))


def make_base(d: Path) -> Base:
    """The G1 at its nominal pose for a few frames, with extras and a dynamic section."""
    model = nominal_model(get_robot("g1"))
    qpos = np.tile(model.qpos0, (FRAMES, 1))
    qpos[:, 0] = np.linspace(0.0, 0.06, FRAMES)
    qpos[:, 2] = 0.79
    extras = {
        "human_contacts": np.array([[True, False]] * FRAMES),
        "keypoint_targets": np.full((FRAMES, 2, 3), 0.5),
    }
    m = motion_from_qpos(model, qpos, 50.0, "g1", extras=extras, info={"clip": "fuzz"})
    steps = (FRAMES - 1) * 4
    dynamics = {
        "initial_state": np.concatenate([[0.0], qpos[0], np.zeros(model.nv)]),
        "ctrl": np.repeat(qpos[1:, 7:], 4, axis=0),
        "qpos": np.repeat(qpos[1:], 4, axis=0),
        "qvel": np.zeros((steps, model.nv)),
        "physics_dt": np.array(0.005),
    }
    m = replace(m, dynamics=dynamics)
    npz = save_motion(m, d / "m.npz")
    mcap = write_motion_mcap(m, d / "m.mcap")
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    log = read_mcap(mcap)
    messages = [(t, TOPICS[t], lt, msg) for t, msgs in log.messages.items() for lt, msg in msgs]
    return Base(m, npz.read_bytes(), mcap.read_bytes(), arrays, log.metadata, messages)


# --- .npz mutations ------------------------------------------------------------------------------


def _savez(arrays: dict[str, Any]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=True, **arrays)
    return buf.getvalue()


def _npy(header: bytes, data: bytes = b"", version: int = 1) -> bytes:
    size = len(header).to_bytes(2 if version == 1 else 4, "little")
    return b"\x93NUMPY" + bytes([version, 0]) + size + header + data


def _with_member(arrays: dict[str, np.ndarray], name: str, data: bytes) -> bytes:
    buf = io.BytesIO(_savez(arrays))
    with zipfile.ZipFile(buf, "a") as z, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # A duplicate name is the point of some cases.
        z.writestr(name, data)
    return buf.getvalue()


def _pick(rng: np.random.Generator, keys: list[str]) -> str:
    return keys[int(rng.integers(len(keys)))]


def npz_flip(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    return flip_bytes(rng, b.npz)


def npz_truncate(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    return truncate_bytes(rng, b.npz)


def npz_delete(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    k = _pick(rng, sorted(b.arrays))
    return _savez({n: v for n, v in b.arrays.items() if n != k}), f"key {k} deleted"


_DTYPES: list[Any] = [np.float32, np.float16, np.int8, np.int64, np.uint8, bool, np.complex128,
                      "<U3", ">f8", object]  # fmt: skip


def npz_dtype(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    k = _pick(rng, sorted(b.arrays))
    dt = _DTYPES[int(rng.integers(len(_DTYPES)))]
    with np.errstate(all="ignore"):
        v = b.arrays[k].astype(dt) if b.arrays[k].dtype.kind != "U" or dt in ("<U3", object) \
            else np.full(b.arrays[k].shape, 1, dtype=dt)  # fmt: skip
    return _savez({**b.arrays, k: v}), f"{k} as {np.dtype(dt)}"


def npz_shape(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    k = _pick(rng, sorted(b.arrays))
    v = b.arrays[k]
    ops: dict[str, Callable[[np.ndarray], np.ndarray]] = {
        "ravel": lambda a: a.ravel(),
        "add_axis": lambda a: a[None],
        "drop_row": lambda a: a[:-1] if a.ndim else a,
        "drop_column": lambda a: a[:, :-1] if a.ndim > 1 else a.reshape(-1)[:0],
        "transpose": lambda a: a.T,
        "empty": lambda a: a[:0] if a.ndim else np.zeros(0),
        "scalar": lambda a: a.reshape(-1)[:1].reshape(()) if a.size else np.array(0.0),
        "repeat": lambda a: np.concatenate([a, a]) if a.ndim else np.stack([a, a]),
        "fortran": lambda a: np.asfortranarray(a),
    }
    op = _pick(rng, sorted(ops))
    return _savez({**b.arrays, k: ops[op](v)}), f"{k} {op}"


def npz_values(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    keys = sorted(k for k, v in b.arrays.items() if v.dtype.kind == "f" and v.size)
    k = _pick(rng, keys)
    v = b.arrays[k].copy()
    value = [math.nan, math.inf, -math.inf, 1e300, 0.0, -1.0, 1e-300][int(rng.integers(7))]
    if rng.random() < 0.5:
        v.reshape(-1)[int(rng.integers(v.size))] = value
    else:
        v[...] = value
    return _savez({**b.arrays, k: v}), f"{k} set to {value}"


def npz_quaternion(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    a = dict(b.arrays)
    t = int(rng.integers(FRAMES))
    if rng.random() < 0.5:
        q = a["qpos"].copy()
        q[t, 3:7] = [0.0, 0.0, 0.0, 0.0] if rng.random() < 0.5 else [2.0, 0.0, 0.0, 0.0]
        a["qpos"] = q
        return _savez(a), f"qpos frame {t} quaternion"
    q = a["body_quat_w"].copy()
    q[t, int(rng.integers(q.shape[1]))] = 0.0
    a["body_quat_w"] = q
    return _savez(a), f"body_quat_w frame {t} zero"


def npz_objects(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    k = _pick(rng, [*sorted(b.arrays), "extra_new", "dynamics_ctrl", "info_json"])
    v = np.empty(FRAMES, dtype=object)
    v[:] = [{"x": 1}, [1, 2], "s", None][:FRAMES] + [None] * (FRAMES - 4)
    return _savez({**b.arrays, k: v}), f"{k} as a pickled object array"


def npz_header(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    headers = {
        "giant_shape": _npy(
            b"{'descr': '<f8', 'fortran_order': False, 'shape': (10**12, 36), }".replace(
                b"10**12", b"1000000000000"
            )
        ),
        "huge_length_v2": b"\x93NUMPY\x02\x00" + (1 << 32 - 1).to_bytes(4, "little"),
        "long_header": _npy(
            b"{'descr': '<f8', 'fortran_order': False, 'shape': (4,), }" + b" " * 20000 + b"\n"
        ),
        "nested": _npy(b"(" * 5000 + b")" * 5000),
        "not_a_dict": _npy(b"[1, 2, 3]\n"),
        "bad_descr": _npy(b"{'descr': '<q99', 'fortran_order': False, 'shape': (4,), }\n"),
        "object_descr": _npy(b"{'descr': '|O', 'fortran_order': False, 'shape': (4,), }\n"),
        "struct_descr": _npy(
            b"{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (4,), }\n", b"\0" * 32
        ),
        "negative_shape": _npy(b"{'descr': '<f8', 'fortran_order': False, 'shape': (-4,), }\n"),
        "fortran_str": _npy(
            b"{'descr': '<f8', 'fortran_order': 'yes', 'shape': (1,), }\n", b"\0" * 8
        ),
        "version_9": b"\x93NUMPY\x09\x00\x10\x00" + b" " * 16,
        "short_data": _npy(
            b"{'descr': '<f8', 'fortran_order': False, 'shape': (4, 36), }\n", b"\0" * 40
        ),
        "no_magic": b"PK not an array at all",
    }
    name = _pick(rng, sorted(headers))
    key = _pick(rng, [*sorted(b.arrays), "extra_x"])
    arrays = {k: v for k, v in b.arrays.items() if k != key}
    return _with_member(arrays, f"{key}.npy", headers[name]), f"{key} with header {name}"


def npz_zip(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    raw = bytearray(b.npz)
    kind = _pick(rng, ["duplicate", "stray_member", "encrypted", "method", "size", "empty_zip"])
    if kind == "duplicate":
        return _with_member(b.arrays, "qpos.npy", b"\x93NUMPY"), kind
    if kind == "stray_member":
        return _with_member(b.arrays, "notes.txt", b"hello"), kind
    if kind == "empty_zip":
        buf = io.BytesIO()
        zipfile.ZipFile(buf, "w").close()
        return buf.getvalue(), kind
    # Patch the central directory entries (signature PK\1\2).
    offsets = [i for i in range(len(raw) - 4) if raw[i : i + 4] == b"PK\x01\x02"]
    i = offsets[int(rng.integers(len(offsets)))]
    if kind == "encrypted":
        raw[i + 8] |= 1  # General purpose flag bit 0.
    elif kind == "method":
        raw[i + 10 : i + 12] = (99).to_bytes(2, "little")
    else:
        raw[i + 24 : i + 28] = (0xFFFFFFF0).to_bytes(4, "little")  # Uncompressed size.
    return bytes(raw), f"central directory {kind} at {i}"


def npz_semantic(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    a = dict(b.arrays)
    changes: dict[str, Callable[[], Any]] = {
        "fps_string": lambda: a.update(fps=np.array("fifty")),
        "fps_zero": lambda: a.update(fps=np.array(0.0)),
        "fps_tiny": lambda: a.update(fps=np.array(1e-300)),
        "fps_huge": lambda: a.update(fps=np.array(1e300)),
        "fps_bool": lambda: a.update(fps=np.array(True)),
        "version_2": lambda: a.update(schema_version=np.array(2)),
        "version_float": lambda: a.update(schema_version=np.array(1.5)),
        "version_nan": lambda: a.update(schema_version=np.array(math.nan)),
        "version_str": lambda: a.update(schema_version=np.array("1")),
        "robot_array": lambda: a.update(robot=np.array(["g1", "g1"])),
        "robot_empty": lambda: a.update(robot=np.array("")),
        "robot_unknown": lambda: a.update(robot=np.array("nobody")),
        "names_repeat": lambda: a.update(joint_names=np.array(["j"] * len(a["joint_names"]))),
        "names_ints": lambda: a.update(body_names=np.arange(len(a["body_names"]))),
        "names_short": lambda: a.update(joint_names=a["joint_names"][:-1]),
        "info_bad_json": lambda: a.update(info_json=np.array("{not json")),
        "info_list": lambda: a.update(info_json=np.array("[1, 2]")),
        "info_deep": lambda: a.update(info_json=np.array("[" * 100000 + "]" * 100000)),
        "dt_zero": lambda: a.update(dynamics_physics_dt=np.array(0.0)),
        "dt_subnormal": lambda: a.update(dynamics_physics_dt=np.array(5e-324)),
        "dt_other": lambda: a.update(dynamics_physics_dt=np.array(0.003)),
        "dt_array": lambda: a.update(dynamics_physics_dt=np.array([0.005, 0.005])),
        "dyn_missing": lambda: a.pop("dynamics_qvel"),
        "dyn_unknown": lambda: a.update(dynamics_extra=np.zeros(3)),
        "dyn_state_short": lambda: a.update(dynamics_initial_state=np.zeros(3)),
        "dyn_ctrl_1d": lambda: a.update(dynamics_ctrl=np.zeros(12)),
        "extra_short": lambda: a.update(extra_human_contacts=np.zeros((FRAMES - 1, 2), bool)),
        "extra_scalar": lambda: a.update(extra_k=np.array(1.0)),
        "extra_empty_name": lambda: a.update(extra_=np.zeros(FRAMES)),
        "extra_strings": lambda: a.update(extra_k=np.array(["a"] * FRAMES)),
        "zero_frames": lambda: a.update(
            {
                k: a[k][:0]
                for k in a
                if k.startswith(("qpos", "joint_p", "joint_v", "body_", "root_"))
            }
        ),
    }
    name = _pick(rng, sorted(changes))
    changes[name]()
    return _savez(a), name


NPZ_KINDS: dict[str, Callable[[np.random.Generator, Base], tuple[bytes, str]]] = {
    "flip": npz_flip,
    "truncate": npz_truncate,
    "delete": npz_delete,
    "dtype": npz_dtype,
    "shape": npz_shape,
    "values": npz_values,
    "quaternion": npz_quaternion,
    "objects": npz_objects,
    "header": npz_header,
    "zip": npz_zip,
    "semantic": npz_semantic,
    "semantic2": npz_semantic,
    "dtype2": npz_dtype,
}


# --- MCAP mutations ------------------------------------------------------------------------------


def _mcap(metadata: dict[str, dict[str, str]], messages: list[tuple[str, str, int, Any]],
          encoding: str = "json") -> bytes:  # fmt: skip
    """An MCAP file written with the mcap package directly: no validation, NaN allowed, and
    a message that is ``bytes`` written as is."""
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="fuzz", library="fuzz")
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    for topic, schema, t, msg in messages:
        if schema not in schemas:
            data = json.dumps(SCHEMAS.get(schema, {})).encode()
            schemas[schema] = w.register_schema(name=schema, encoding="jsonschema", data=data)
        if topic not in channels:
            channels[topic] = w.register_channel(topic=topic, message_encoding=encoding,
                                                 schema_id=schemas[schema])  # fmt: skip
        data = msg if isinstance(msg, bytes) else json.dumps(msg).encode()
        w.add_message(channel_id=channels[topic], log_time=t, publish_time=t, data=data)
    for name, record in metadata.items():
        w.add_metadata(name, record)
    w.finish()
    return buf.getvalue()


_BAD_JSON = ["nan", "-1", "inf", "1e400", "", "[]", "{}", '"x"', "[1, 2]", "null", '["a", 1]',
             "[[1]]", '{"k": ["object", []]}', '{"human_contacts": ["object", [2]]}',
             '{"human_contacts": ["<U4", [2]]}', '{"human_contacts": ["float64", [7]]}',
             '{"k": "float64"}', "[" * 50000, "0", "true", "1.5"]  # fmt: skip
_BAD_VALUES: list[Any] = [math.nan, math.inf, -math.inf, 1e308, -1e300, "x", None, [], [[]],
                          {}, True, [1] * 500, [math.nan] * 3, [[1, 2], [3]], 0, -1,
                          10**40]  # fmt: skip


def mcap_flip(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    return flip_bytes(rng, b.mcap)


def mcap_truncate(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    return truncate_bytes(rng, b.mcap)


def mcap_lengths(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    """A record or string length (8 or 4 bytes) made huge: reads past the end."""
    raw = bytearray(b.mcap)
    i = int(rng.integers(8, len(raw) - 8))
    width = 8 if rng.random() < 0.5 else 4
    raw[i : i + width] = b"\xff" * (width - 1) + b"\x7f"
    return bytes(raw), f"{width}-byte length 0x7f.. at {i}"


def mcap_metadata(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    meta = {k: dict(v) for k, v in b.metadata.items()}
    record = _pick(rng, sorted(meta))
    key = _pick(rng, sorted(meta[record]))
    if rng.random() < 0.2:
        del meta[record][key]
        what = f"metadata {record}.{key} deleted"
    elif rng.random() < 0.1:
        del meta[record]
        what = f"metadata {record} deleted"
    else:
        value = _BAD_JSON[int(rng.integers(len(_BAD_JSON)))]
        meta[record][key] = value
        what = f"metadata {record}.{key} = {value[:20]!r}"
    return _mcap(meta, b.messages), what


def _set(msg: Any, path: list[Any], value: Any) -> None:
    for p in path[:-1]:
        msg = msg[p]
    if value is _DELETE:
        del msg[path[-1]]
    else:
        msg[path[-1]] = value


_DELETE = object()


def _paths(msg: Any, prefix: list[Any]) -> list[list[Any]]:
    """Every field path in a message (dict keys and list indices, the first 3 of a list)."""
    out = [prefix] if prefix else []
    if isinstance(msg, dict):
        for k, v in msg.items():
            out += _paths(v, [*prefix, k])
    elif isinstance(msg, list):
        for i, v in enumerate(msg[:3]):
            out += _paths(v, [*prefix, i])
    return out


def mcap_message(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    messages = [(t, s, lt, json.loads(json.dumps(m))) for t, s, lt, m in b.messages]
    topics = sorted({t for t, *_ in messages if t != "/tf"})
    topic = _pick(rng, topics)
    idx = [i for i, (t, *_) in enumerate(messages) if t == topic]
    i = idx[int(rng.integers(len(idx)))]
    paths = _paths(messages[i][3], [])
    path = paths[int(rng.integers(len(paths)))]
    value = _DELETE if rng.random() < 0.15 else _BAD_VALUES[int(rng.integers(len(_BAD_VALUES)))]
    _set(messages[i][3], path, value)
    shown = "deleted" if value is _DELETE else repr(value)[:20]
    return _mcap(b.metadata, messages), f"{topic} message {i}: {path} = {shown}"


def mcap_messages(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    messages = list(b.messages)
    topic = _pick(rng, sorted({t for t, *_ in messages}))
    idx = [i for i, (t, *_) in enumerate(messages) if t == topic]
    op = _pick(rng, ["drop_one", "drop_all", "duplicate", "not_json", "other_schema",
                     "zero_quaternion"])  # fmt: skip
    i = idx[int(rng.integers(len(idx)))]
    if op == "drop_one":
        del messages[i]
    elif op == "drop_all":
        messages = [m for m in messages if m[0] != topic]
    elif op == "duplicate":
        messages.insert(i, messages[i])
    elif op == "not_json":
        t, s, lt, _ = messages[i]
        messages[i] = (t, s, lt, b"\xff{not json")
    elif op == "other_schema":
        messages = [(t, "humimic.Pose" if t == topic else s, lt, m) for t, s, lt, m in messages]
    else:
        qi = [j for j, (t, *_) in enumerate(messages) if t == "/reference/qpos"]
        t, s, lt, m = messages[qi[int(rng.integers(len(qi)))]]
        m = json.loads(json.dumps(m))
        m["qpos"][3:7] = [0, 0, 0, 0]
        messages[qi[0]] = (t, s, lt, m)
        topic = "/reference/qpos"
    return _mcap(b.metadata, messages), f"{topic}: {op} (message {i})"


def mcap_encoding(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    enc = _pick(rng, ["cbor", "ros1", "protobuf"])
    return _mcap(b.metadata, b.messages, encoding=enc), f"message encoding {enc}"


def mcap_garbage(rng: np.random.Generator, b: Base) -> tuple[bytes, str]:
    kind = _pick(rng, ["random", "npz", "empty", "magic_only", "text"])
    data = {
        "random": rng.bytes(int(rng.integers(1, 4000))),
        "npz": b.npz,
        "empty": b"",
        "magic_only": b"\x89MCAP0\r\n",
        "text": b"schema_version: 1\n",
    }[kind]
    return data, f"file of {kind}"


MCAP_KINDS: dict[str, Callable[[np.random.Generator, Base], tuple[bytes, str]]] = {
    "flip": mcap_flip,
    "truncate": mcap_truncate,
    "lengths": mcap_lengths,
    "metadata": mcap_metadata,
    "metadata2": mcap_metadata,
    "message": mcap_message,
    "message2": mcap_message,
    "messages": mcap_messages,
    "encoding": mcap_encoding,
    "garbage": mcap_garbage,
}


# --- The checks ------------------------------------------------------------------------------


def _case(
    b: Base, fmt: str, kind: str, seed: int, folder: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One mutated file through the reader and ``humimic convert``; fails with the seed."""
    kinds = NPZ_KINDS if fmt == "npz" else MCAP_KINDS
    rng = np.random.default_rng([seed, sum(map(ord, kind))])
    data, what = kinds[kind](rng, b)
    label = f"{fmt} {kind} seed {seed} ({what})"
    folder.mkdir()
    src = folder / f"in.{fmt}"
    src.write_bytes(data)
    read = load_motion if fmt == "npz" else read_motion_mcap
    try:
        # convert also refuses a motion whose joints are not those of the robot it names.
        motion_model(read(src), str(src))
        readable = True
    except HumimicError:
        readable = False
    except Exception:
        pytest.fail(f"{label}: the reader raised\n{traceback.format_exc()}")
    # Convert to the other format, and every fourth case to the same one (the writer's path).
    out_fmt = fmt if seed % 4 == 0 else ("mcap" if fmt == "npz" else "npz")
    dst = folder / f"out.{out_fmt}"
    capsys.readouterr()
    try:
        rc = main(["convert", str(src), str(dst)])
    except SystemExit as e:
        if e.code != 2:
            pytest.fail(f"{label}: convert exited with SystemExit({e.code!r})")
        rc = 2
    except Exception:
        pytest.fail(f"{label}: convert raised\n{traceback.format_exc()}")
    err = capsys.readouterr().err
    assert rc in (0, 2), f"{label}: convert returned {rc}: {err}"
    assert (rc == 0) == readable, (
        f"{label}: reader {'read' if readable else 'refused'}, convert {rc}"
    )
    assert src.read_bytes() == data, f"{label}: the input changed"
    left = sorted(p.name for p in folder.iterdir())
    if rc == 2:
        assert left == [src.name], f"{label}: files left after a refusal: {left}"
        assert err.startswith("humimic: error: ") and err.count("\n") == 1, f"{label}: {err!r}"
        assert str(src) in err, f"{label}: the message does not name the file: {err!r}"
        return
    assert left == sorted([src.name, dst.name]), f"{label}: files left: {left}"
    back = load_motion(dst) if out_fmt == "npz" else read_motion_mcap(dst)
    assert back.num_frames >= 1
    if out_fmt == "npz":
        with np.load(dst, allow_pickle=False) as z:  # Raises on a pickled member.
            assert all(z[k].dtype != object for k in z.files), label


@pytest.mark.parametrize("kind", sorted(NPZ_KINDS))
def test_fuzz_npz(
    kind: str, base: Base, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for seed in range(CASES_PER_KIND):
        _case(base, "npz", kind, seed, tmp_path / f"case{seed}", capsys)


@pytest.mark.parametrize("kind", sorted(MCAP_KINDS))
def test_fuzz_mcap(
    kind: str, base: Base, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for seed in range(CASES_PER_KIND):
        _case(base, "mcap", kind, seed, tmp_path / f"case{seed}", capsys)


def test_unmutated_files_convert(base: Base, tmp_path: Path) -> None:
    """The base files are good, so every refusal above comes from its mutation."""
    for fmt, data in (("npz", base.npz), ("mcap", base.mcap)):
        src = tmp_path / f"good.{fmt}"
        src.write_bytes(data)
        other = "mcap" if fmt == "npz" else "npz"
        assert main(["convert", str(src), str(tmp_path / f"out_{fmt}.{other}")]) == 0
    assert load_motion(tmp_path / "out_mcap.npz").dynamics is not None
