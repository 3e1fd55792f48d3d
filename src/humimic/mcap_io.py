"""MCAP files that Foxglove opens: motion references, rollouts and robot logs.

One module reads and writes them, with the ``mcap`` package, JSON message encoding and
``jsonschema`` schemas (checked by a small compiled validator: the ``jsonschema`` package
costs 3 ms per message here). Topics and their schemas are fixed here (:data:`TOPICS`), so a file
written by humimic, by a robot's logger or by a user's script is read and validated the same
way. Quaternions in humimic's own schemas are ``wxyz`` (fields named ``w, x, y, z``); the
``foxglove.FrameTransforms`` messages written for Foxglove's 3D panel use Foxglove's field names.

Log times are nanoseconds. Message headers carry ``stamp: {sec, nanosec}``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer

from humimic.errors import HumimicError, InputError, OutputPathError
from humimic.io import check_writable, file_mode

_NUM = {"type": "number"}
_NUMS = {"type": "array", "items": _NUM}
_NAMES = {"type": "array", "items": {"type": "string"}}
_VEC3 = {
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["x", "y", "z"],
}
_QUAT = {
    "type": "object",
    "properties": {"w": _NUM, "x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["w", "x", "y", "z"],
}
_HEADER = {
    "type": "object",
    "properties": {
        "stamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nanosec": {"type": "integer"}},
            "required": ["sec", "nanosec"],
        },
        "frame_id": {"type": "string"},
    },
    "required": ["stamp"],
}


def _object(properties: dict[str, Any], required: list[str], title: str) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": properties,
        "required": required,
    }


SCHEMAS: dict[str, dict[str, Any]] = {
    "humimic.JointState": _object(
        {"header": _HEADER, "name": _NAMES, "position": _NUMS, "velocity": _NUMS, "effort": _NUMS},
        ["header", "name", "position"],
        "Joint positions [rad], velocities [rad/s], efforts [N m]",
    ),
    "humimic.JointCommand": _object(
        {
            "header": _HEADER,
            "name": _NAMES,
            "position": _NUMS,
            "velocity": _NUMS,
            "effort": _NUMS,
            "kp": _NUMS,
            "kd": _NUMS,
        },
        ["header", "name", "position"],
        "PD targets, feed-forward torques and the gains the drives were told to use",
    ),
    "humimic.Pose": _object(
        {"header": _HEADER, "position": _VEC3, "orientation": _QUAT},
        ["header", "position", "orientation"],
        "A pose in the world frame (orientation w, x, y, z)",
    ),
    "humimic.Imu": _object(
        {
            "header": _HEADER,
            "orientation": _QUAT,
            "angular_velocity": _VEC3,
            "linear_acceleration": _VEC3,
        },
        ["header"],
        "IMU: orientation (w, x, y, z), angular velocity [rad/s], linear acceleration [m/s^2]",
    ),
    "humimic.Qpos": _object(
        {"header": _HEADER, "qpos": _NUMS},
        ["header", "qpos"],
        "MuJoCo generalized positions (free joint: x y z qw qx qy qz, then joints)",
    ),
    "humimic.BodyStates": _object(
        {
            "header": _HEADER,
            "name": _NAMES,
            "position": {"type": "array", "items": _NUMS},
            "orientation": {"type": "array", "items": _NUMS},
            "linear_velocity": {"type": "array", "items": _NUMS},
            "angular_velocity": {"type": "array", "items": _NUMS},
        },
        ["header", "name", "position", "orientation"],
        "World-frame body states; orientation rows are w, x, y, z",
    ),
    "humimic.NamedArrays": _object(
        {"header": _HEADER, "arrays": {"type": "object"}},
        ["header", "arrays"],
        "Named arrays (nested lists) for one time step",
    ),
    "humimic.RewardTerms": _object(
        {"header": _HEADER, "terms": {"type": "object", "additionalProperties": _NUM}},
        ["header", "terms"],
        "Per-step reward terms of one environment",
    ),
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms",
        "type": "object",
        "properties": {
            "transforms": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "timestamp": {
                            "type": "object",
                            "properties": {
                                "sec": {"type": "integer"},
                                "nsec": {"type": "integer"},
                            },
                        },
                        "parent_frame_id": {"type": "string"},
                        "child_frame_id": {"type": "string"},
                        "translation": _VEC3,
                        "rotation": _QUAT,
                    },
                },
            }
        },
        "required": ["transforms"],
    },
}

TOPICS: dict[str, str] = {
    "/joint_states": "humimic.JointState",
    "/joint_commands": "humimic.JointCommand",
    "/base_pose": "humimic.Pose",
    "/imu": "humimic.Imu",
    "/qpos": "humimic.Qpos",
    "/body_states": "humimic.BodyStates",
    "/reward_terms": "humimic.RewardTerms",
    "/reference/qpos": "humimic.Qpos",
    "/reference/joint_states": "humimic.JointState",
    "/reference/body_states": "humimic.BodyStates",
    "/reference/extras": "humimic.NamedArrays",
    "/dynamics/step": "humimic.NamedArrays",
    "/tf": "foxglove.FrameTransforms",
}
"""Known topics -> schema name. Other topics may be written with an explicit schema."""

Checker = Any  # Callable[[object, str], str | None]: value, path -> error or None


def compile_schema(schema: dict[str, Any]) -> Checker:
    """A fast checker for the JSON Schema subset humimic's schemas use.

    Supported keywords: ``type`` (object, array, number, integer, string, boolean),
    ``properties``, ``required``, ``items``, ``additionalProperties`` (a schema). Others are
    ignored. The checker returns ``None`` or a message that starts with the failing field's
    dotted path. Arrays of numbers are checked in one pass (they dominate the messages).
    """
    kind = schema.get("type")
    props = {k: compile_schema(v) for k, v in schema.get("properties", {}).items()}
    required = list(schema.get("required", []))
    items = compile_schema(schema["items"]) if isinstance(schema.get("items"), dict) else None
    addl = schema.get("additionalProperties")
    addl_check = compile_schema(addl) if isinstance(addl, dict) else None
    numeric_items = (
        isinstance(schema.get("items"), dict) and schema["items"].get("type") == "number"
    )

    def where(path: str) -> str:
        return path or "(message)"

    def check(value: object, path: str = "") -> str | None:
        if kind == "object":
            if not isinstance(value, dict):
                return f"{where(path)}: expected an object, got {type(value).__name__}"
            for k in required:
                if k not in value:
                    return f"{where(path + '.' + k if path else k)}: required field missing"
            for k, v in value.items():
                sub = f"{path}.{k}" if path else k
                c = props.get(k, addl_check)
                if c is not None:
                    err = c(v, sub)
                    if err:
                        return err
            return None
        if kind == "array":
            if not isinstance(value, list):
                return f"{where(path)}: expected an array, got {type(value).__name__}"
            if numeric_items:
                for i, x in enumerate(value):
                    if type(x) not in (int, float):
                        return f"{path}.{i}: expected a number, got {x!r}"
                return None
            if items is not None:
                for i, x in enumerate(value):
                    err = items(x, f"{path}.{i}")
                    if err:
                        return err
            return None
        if kind == "number":
            if type(value) not in (int, float):
                return f"{where(path)}: expected a number, got {value!r}"
        elif kind == "integer":
            if type(value) is not int:
                return f"{where(path)}: expected an integer, got {value!r}"
        elif kind == "string":
            if not isinstance(value, str):
                return f"{where(path)}: expected a string, got {value!r}"
        elif kind == "boolean" and not isinstance(value, bool):
            return f"{where(path)}: expected true or false, got {value!r}"
        return None

    return check


_VALIDATORS: dict[str, Checker] = {name: compile_schema(s) for name, s in SCHEMAS.items()}


class McapFormatError(InputError):
    """An MCAP file is truncated, corrupt, or its messages do not match their schemas."""


def stamp(t_ns: int) -> dict[str, int]:
    """A header stamp from nanoseconds."""
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


class McapWriter:
    """Write an MCAP file atomically: a temporary file renamed into place on success only.

    Use as a context manager. Each message is validated against its topic's schema; the first
    invalid message raises :class:`McapFormatError` naming the topic and the field, and no
    file is left behind.
    """

    def __init__(self, path: str | os.PathLike[str], *, profile: str = "humimic") -> None:
        if Path(path).suffix != ".mcap":  # Before any folder is made for it.
            raise InputError(f"{path}: MCAP files must end in .mcap")
        self.path = check_writable(path, create=True)
        try:
            fd, tmp = tempfile.mkstemp(
                prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent
            )
        except OSError as e:
            raise OutputPathError(f"{self.path}: cannot write here: {e.strerror or e}") from None
        self._tmp = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        self._writer = Writer(self._file)
        self._writer.start(profile=profile, library="humimic")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._seq: dict[str, int] = {}

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (string to string)."""
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def _channel(self, topic: str, schema: str | None) -> tuple[int, str]:
        if topic in self._channels:
            return self._channels[topic]
        name = schema or TOPICS.get(topic)
        if name is None or name not in SCHEMAS:
            raise InputError(
                f"topic {topic}: no schema known; pass one of {sorted(SCHEMAS)} or use a known "
                f"topic ({', '.join(sorted(TOPICS))})"
            )
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode()
            )
        cid = self._writer.register_channel(
            topic=topic, message_encoding="json", schema_id=self._schemas[name]
        )
        self._channels[topic] = (cid, name)
        return cid, name

    def write(
        self, topic: str, log_time_ns: int, message: dict[str, Any], *, schema: str | None = None
    ) -> None:
        """Validate and write one message."""
        cid, name = self._channel(topic, schema)
        err = _VALIDATORS[name](message)
        if err is not None:
            raise McapFormatError(f"topic {topic} ({name}): field {err}")
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        data = json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
        self._writer.add_message(
            channel_id=cid, log_time=int(log_time_ns), data=data, publish_time=int(log_time_ns),
            sequence=seq,
        )  # fmt: skip

    def close(self) -> Path:
        """Finish the file and move it into place (with the usual permissions, 0666 less the
        umask, as :func:`humimic.io.atomic_write` gives)."""
        try:
            self._writer.finish()
            self._file.close()
            os.chmod(self._tmp, file_mode())
            os.replace(self._tmp, self.path)
        except OSError as e:
            self.abort()
            raise OutputPathError(f"{self.path}: cannot write: {e.strerror or e}") from None
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self) -> None:
        """Discard everything written."""
        with contextlib.suppress(Exception):
            self._file.close()
        with contextlib.suppress(OSError):
            self._tmp.unlink()


@dataclass
class McapLog:
    """An MCAP file in memory: metadata records and validated JSON messages per topic.

    Attributes:
        path: The file.
        metadata: Record name -> string map.
        messages: Topic -> list of (log time [ns], message).
        schemas: Topic -> schema name.
    """

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)

    def topic(self, name: str) -> list[tuple[int, dict[str, Any]]]:
        """Messages of one topic; :class:`McapFormatError` names the topics present if absent."""
        if name not in self.messages or not self.messages[name]:
            present = ", ".join(sorted(self.messages)) or "none"
            raise McapFormatError(f"{self.path}: no messages on topic {name} (topics: {present})")
        return self.messages[name]

    def meta(self, name: str) -> dict[str, str]:
        """One metadata record; :class:`McapFormatError` if absent."""
        if name not in self.metadata:
            raise McapFormatError(
                f"{self.path}: no metadata record {name!r} "
                f"(records: {', '.join(sorted(self.metadata)) or 'none'})"
            )
        return self.metadata[name]


class _Bounded:
    """A read-only file that never asks the OS for more bytes than the file has left: a
    corrupt record length then costs a short read, not an allocation of its size."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self._size = os.fstat(f.fileno()).st_size

    def read(self, n: int = -1) -> bytes:
        left = max(self._size - self._f.tell(), 0)
        return self._f.read(left if n is None or n < 0 else min(n, left))

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True


def _check_is_mcap(p: Path) -> None:
    """Refuse, saying what it is, a file that is not MCAP (an ``.npz`` motion, text...)."""
    from humimic.motion import sniff

    try:
        kind = sniff(p)
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror}") from None
    if kind == "mcap":
        return
    if kind == "npz":
        raise McapFormatError(
            f"{p}: is a zip archive (an .npz motion?), not an MCAP file; rename it to "
            f"{p.with_suffix('.npz').name}"
        )
    what = {"empty": "an empty file", "text": "a text file", "npy": "an .npy array"}
    raise McapFormatError(f"{p}: {what.get(kind, 'not an MCAP file')}: expected an MCAP file")


def read_mcap(
    path: str | os.PathLike[str],
    *,
    topics: Iterable[str] | None = None,
    require: Iterable[str] = (),
) -> McapLog:
    """Read an MCAP file, validating every JSON message against its schema.

    Args:
        path: The file.
        topics: Only these topics (default: all).
        require: Topics that must have at least one message.

    Raises:
        InputError: Missing file.
        McapFormatError: Truncated or corrupt file; a known topic with the wrong schema; a
            message that does not match its schema (names topic, message index and field); a
            required topic without messages.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    _check_is_mcap(p)
    log = McapLog(path=p)
    wanted = None if topics is None else set(topics)
    validators: dict[str, Checker] = {}
    try:
        with p.open("rb") as raw:
            reader = make_reader(_Bounded(raw), validate_crcs=True)  # type: ignore[arg-type]
            for schema, channel, message in reader.iter_messages(
                topics=None if wanted is None else sorted(wanted)
            ):
                topic = channel.topic
                if topic not in validators:
                    validators[topic] = _validator_for(p, topic, schema)
                    log.schemas[topic] = schema.name if schema is not None else ""
                if channel.message_encoding != "json":
                    raise McapFormatError(
                        f"{p}: topic {topic}: message encoding {channel.message_encoding!r}, "
                        "expected 'json'"
                    )
                try:
                    msg = json.loads(message.data)
                except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
                    raise McapFormatError(
                        f"{p}: topic {topic}: message is not JSON ({e})"
                    ) from None
                msgs = log.messages.setdefault(topic, [])
                err = validators[topic](msg)
                if err is not None:
                    raise McapFormatError(
                        f"{p}: topic {topic} ({log.schemas[topic]}), message {len(msgs)}: "
                        f"field {err}"
                    )
                msgs.append((message.log_time, msg))
            for record in reader.iter_metadata():
                log.metadata[record.name] = dict(record.metadata)
    except HumimicError:
        raise
    except Exception as e:  # The mcap package, its decompressors and seeks raise many types.
        text = " ".join(f"{type(e).__name__}: {e}".split())[:200]
        raise McapFormatError(
            f"{p}: not a readable MCAP file (truncated or corrupt): {text}"
        ) from None
    for topic in require:
        log.topic(topic)
    return log


def _validator_for(p: Path, topic: str, schema: Any) -> Checker:
    expected = TOPICS.get(topic)
    name = schema.name if schema is not None else None
    if expected is not None and name != expected:
        raise McapFormatError(f"{p}: topic {topic} has schema {name!r}, expected {expected!r}")
    if name in _VALIDATORS:
        return _VALIDATORS[name]
    if schema is None or schema.encoding != "jsonschema":
        return compile_schema({})
    try:
        return compile_schema(json.loads(schema.data))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise McapFormatError(f"{p}: topic {topic}: schema {name!r} is not JSON ({e})") from None


def iter_frames(fps: float, n: int) -> Iterator[tuple[int, int]]:
    """(frame index, log time in ns) for ``n`` frames at ``fps``."""
    for i in range(n):
        yield i, round(i * 1e9 / fps)


def _vec(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(q: np.ndarray) -> dict[str, float]:
    return {"w": float(q[0]), "x": float(q[1]), "y": float(q[2]), "z": float(q[3])}


def tf_message(t_ns: int, names: Iterable[str], pos: np.ndarray, quat: np.ndarray) -> dict:
    """Foxglove FrameTransforms of bodies in the world frame (Foxglove's field names)."""
    ts = {"sec": int(t_ns // 1_000_000_000), "nsec": int(t_ns % 1_000_000_000)}
    return {
        "transforms": [
            {
                "timestamp": ts,
                "parent_frame_id": "world",
                "child_frame_id": n,
                "translation": _vec(p),
                "rotation": _quat(q),
            }
            for n, p, q in zip(names, pos, quat, strict=True)
        ]
    }


def write_motion_mcap(motion: Any, path: str | os.PathLike[str]) -> Path:
    """Write a :class:`humimic.motion.Motion` as MCAP, losslessly (plus ``/tf`` for Foxglove).

    Raises:
        MotionDataError: The motion fails :func:`humimic.motion.validate_motion` (nothing is
            written).
    """
    from humimic.motion import validate_motion

    validate_motion(motion, f"{path}: not written: the motion")
    with McapWriter(path) as w:
        write_motion_topics(w, motion)
    return Path(path)


def write_motion_topics(w: McapWriter, motion: Any) -> None:
    """Write a motion's metadata and ``/reference/*`` and ``/tf`` topics into an open writer
    (what :func:`read_motion_mcap` reads back)."""
    from humimic.motion import SCHEMA_VERSION

    extras = motion.extras or {}
    w.add_metadata(
        "motion",
        {
            "schema_version": str(SCHEMA_VERSION),
            "robot": motion.robot,
            "fps": repr(float(motion.fps)),
            "joint_names": json.dumps(list(motion.joint_names)),
            "body_names": json.dumps(list(motion.body_names)),
            "extras": json.dumps({k: [str(v.dtype), list(v.shape[1:])] for k, v in extras.items()}),
            "info": json.dumps(motion.info or {}),
        },
    )
    for i, t in iter_frames(motion.fps, motion.num_frames):
        header = {"stamp": stamp(t), "frame_id": "world"}
        w.write("/reference/qpos", t, {"header": header, "qpos": motion.qpos[i].tolist()})
        w.write(
            "/reference/joint_states",
            t,
            {
                "header": header,
                "name": list(motion.joint_names),
                "position": motion.joint_pos[i].tolist(),
                "velocity": motion.joint_vel[i].tolist(),
            },
        )
        w.write(
            "/reference/body_states",
            t,
            {
                "header": header,
                "name": list(motion.body_names),
                "position": motion.body_pos_w[i].tolist(),
                "orientation": motion.body_quat_w[i].tolist(),
                "linear_velocity": motion.body_lin_vel_w[i].tolist(),
                "angular_velocity": motion.body_ang_vel_w[i].tolist(),
            },
        )
        if extras:
            w.write(
                "/reference/extras",
                t,
                {"header": header, "arrays": {k: v[i].tolist() for k, v in extras.items()}},
            )
        w.write(
            "/tf", t, tf_message(t, motion.body_names, motion.body_pos_w[i], motion.body_quat_w[i])
        )
    dyn = motion.dynamics
    if dyn:  # The dynamic section (humimic refine): a message per physics step.
        dt = float(dyn["physics_dt"])
        w.add_metadata(
            "dynamics",
            {"physics_dt": repr(dt), "initial_state": json.dumps(dyn["initial_state"].tolist())},
        )
        for k in range(dyn["ctrl"].shape[0]):
            t = round((k + 1) * dt * 1e9)  # The state after step k.
            arrays = {n: dyn[n][k].tolist() for n in ("ctrl", "qpos", "qvel")}
            w.write("/dynamics/step", t, {"header": {"stamp": stamp(t), "frame_id": "world"},
                                          "arrays": arrays})  # fmt: skip


_MOTION_LABELS = {
    "robot": "metadata motion.robot",
    "fps": "metadata motion.fps",
    "joint_names": "metadata motion.joint_names",
    "body_names": "metadata motion.body_names",
    "info_json": "metadata motion.info",
    "qpos": "topic /reference/qpos field qpos",
    "joint_pos": "topic /reference/joint_states field position",
    "joint_vel": "topic /reference/joint_states field velocity",
    "body_pos_w": "topic /reference/body_states field position",
    "body_quat_w": "topic /reference/body_states field orientation",
    "body_lin_vel_w": "topic /reference/body_states field linear_velocity",
    "body_ang_vel_w": "topic /reference/body_states field angular_velocity",
    "extra_": "topic /reference/extras field arrays.",
    "dynamics_": "dynamic section ",
    "dynamics_physics_dt": "metadata dynamics.physics_dt",
    "dynamics_initial_state": "metadata dynamics.initial_state",
    "dynamics_ctrl": "topic /dynamics/step field arrays.ctrl",
    "dynamics_qpos": "topic /dynamics/step field arrays.qpos",
    "dynamics_qvel": "topic /dynamics/step field arrays.qvel",
}
"""How :func:`humimic.motion.validate_motion` names a motion's fields in an MCAP file."""

_EXTRA_KINDS = "biuf"  # Extras are numbers or booleans: never objects, which would be pickled.


def _json_field(p: Path, record: str, meta: dict[str, str], key: str, kind: type) -> Any:
    """A JSON value of a metadata record, of type ``kind``."""
    if key not in meta:
        raise McapFormatError(f"{p}: metadata {record!r}: missing field {key}")
    try:
        value = json.loads(meta[key])
    except (json.JSONDecodeError, RecursionError) as e:
        raise McapFormatError(f"{p}: metadata {record}.{key}: not JSON ({e})") from None
    if not isinstance(value, kind):
        raise McapFormatError(
            f"{p}: metadata {record}.{key}: expected a JSON {kind.__name__}, got "
            f"{type(value).__name__}"
        )
    return value


def _names_field(p: Path, meta: dict[str, str], key: str) -> tuple[str, ...]:
    names = _json_field(p, "motion", meta, key, list)
    if not all(isinstance(n, str) for n in names):
        raise McapFormatError(f"{p}: metadata motion.{key}: expected a list of names")
    return tuple(names)


def _float_field(p: Path, record: str, meta: dict[str, str], key: str) -> float:
    if key not in meta:
        raise McapFormatError(f"{p}: metadata {record!r}: missing field {key}")
    try:
        return float(meta[key])
    except ValueError:
        raise McapFormatError(
            f"{p}: metadata {record}.{key}: expected a number, got {meta[key][:40]!r}"
        ) from None


def _numbers(p: Path, where: str, rows: list[Any], dtype: Any = np.float64) -> np.ndarray:
    """Rows of (nested lists of) numbers as one array; ragged or non-numeric rows refused."""
    try:
        return np.array(rows, dtype=dtype)
    except (ValueError, TypeError, OverflowError) as e:
        text = " ".join(str(e).split())[:120]
        raise McapFormatError(
            f"{p}: {where}: not an array of numbers of one shape ({text})"
        ) from None


def read_motion_mcap(path: str | os.PathLike[str]) -> Any:
    """Read a motion reference written by :func:`write_motion_mcap`, checked as the ``.npz``
    reader checks (:func:`humimic.motion.validate_motion`).

    Raises:
        InputError: Missing file.
        McapFormatError: Not MCAP, corrupt, a missing topic or metadata field, or a field
            of the wrong type or shape (names the topic or record and the field).
        MotionDataError: The motion fails :func:`humimic.motion.validate_motion`.
    """
    from humimic.motion import SCHEMA_VERSION, Motion, validate_motion

    topics = ["/reference/qpos", "/reference/joint_states", "/reference/body_states"]
    log = read_mcap(path, topics=[*topics, "/reference/extras", "/dynamics/step"], require=topics)
    p = log.path
    meta = log.meta("motion")
    try:
        version = int(meta["schema_version"])
        robot = meta["robot"]
    except (KeyError, ValueError) as e:
        raise McapFormatError(f"{p}: metadata 'motion': missing or bad field {e}") from None
    if version != SCHEMA_VERSION:
        raise McapFormatError(f"{p}: schema_version {version}, expected {SCHEMA_VERSION}")
    fps = _float_field(p, "motion", meta, "fps")
    joint_names = _names_field(p, meta, "joint_names")
    body_names = _names_field(p, meta, "body_names")
    extra_types = _json_field(p, "motion", meta, "extras", dict) if "extras" in meta else {}
    info = _json_field(p, "motion", meta, "info", dict) if "info" in meta else {}

    def stack(topic: str, key: str) -> np.ndarray:
        msgs = log.topic(topic)
        try:
            rows = [m[key] for _, m in msgs]
        except KeyError:
            raise McapFormatError(f"{p}: topic {topic}: field {key} missing") from None
        return _numbers(p, f"topic {topic}: field {key}", rows)

    qpos = stack("/reference/qpos", "qpos")
    fields = {
        "joint_pos": stack("/reference/joint_states", "position"),
        "joint_vel": stack("/reference/joint_states", "velocity"),
        "body_pos_w": stack("/reference/body_states", "position"),
        "body_quat_w": stack("/reference/body_states", "orientation"),
        "body_lin_vel_w": stack("/reference/body_states", "linear_velocity"),
        "body_ang_vel_w": stack("/reference/body_states", "angular_velocity"),
    }
    extras = {}
    if extra_types:
        msgs = log.topic("/reference/extras")
        for k, spec in extra_types.items():
            where = f"topic /reference/extras: field arrays.{k}"
            ok = isinstance(spec, list) and len(spec) == 2 and isinstance(spec[0], str)
            try:
                dtype = np.dtype(spec[0]) if ok else None
            except TypeError:
                dtype = None
            if dtype is None or dtype.kind not in _EXTRA_KINDS or dtype.itemsize == 0:
                raise McapFormatError(
                    f"{p}: metadata motion.extras.{k}: expected [dtype of numbers or booleans, "
                    f"shape], got {spec!r}"
                )
            try:
                rows = [m["arrays"][k] for _, m in msgs]
            except (KeyError, TypeError):
                raise McapFormatError(f"{p}: {where} missing") from None
            extras[k] = _numbers(p, where, rows, dtype)
            if list(extras[k].shape[1:]) != spec[1]:
                raise McapFormatError(
                    f"{p}: {where}: shape {list(extras[k].shape[1:])} per frame, the metadata "
                    f"says {spec[1]!r}"
                )
    dynamics = None
    if "dynamics" in log.metadata:
        d = log.meta("dynamics")
        dynamics = {
            "physics_dt": np.array(_float_field(p, "dynamics", d, "physics_dt")),
            "initial_state": _numbers(
                p,
                "metadata dynamics.initial_state",
                _json_field(p, "dynamics", d, "initial_state", list),
            ),
        }
        steps = log.topic("/dynamics/step")
        for key in ("ctrl", "qpos", "qvel"):
            try:
                rows = [m["arrays"][key] for _, m in steps]
            except (KeyError, TypeError):
                raise McapFormatError(
                    f"{p}: topic /dynamics/step: field arrays.{key} missing"
                ) from None
            dynamics[key] = _numbers(p, f"topic /dynamics/step: field arrays.{key}", rows)
    motion = Motion(
        robot=robot,
        fps=fps,
        joint_names=joint_names,
        body_names=body_names,
        qpos=qpos,
        dynamics=dynamics,
        joint_pos=fields["joint_pos"],
        joint_vel=fields["joint_vel"],
        body_pos_w=fields["body_pos_w"],
        body_quat_w=fields["body_quat_w"],
        body_lin_vel_w=fields["body_lin_vel_w"],
        body_ang_vel_w=fields["body_ang_vel_w"],
        extras=extras or None,
        info=info or None,
        source=str(p),
    )
    validate_motion(motion, p, labels=_MOTION_LABELS)
    return motion


def qpos_from_log(log: McapLog, joint_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Generalized positions over time from a rollout or robot log.

    Uses ``/qpos`` when present; otherwise ``/base_pose`` (floating base) and
    ``/joint_states`` matched by joint name, each held at its last value.

    Returns:
        Times [ns] (N,) and qpos (N, 7 + len(joint_names)), on the joint-state times.
    """
    if log.messages.get("/qpos"):
        msgs = log.topic("/qpos")
        times = np.array([t for t, _ in msgs], dtype=np.int64)
        qpos = np.array([m["qpos"] for _, m in msgs], dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != 7 + len(joint_names):
            raise McapFormatError(
                f"{log.path}: topic /qpos: field qpos has {qpos.shape[-1]} values, the robot "
                f"needs {7 + len(joint_names)}"
            )
        return times, qpos
    states = log.topic("/joint_states")
    base = log.topic("/base_pose")
    times = np.array([t for t, _ in states], dtype=np.int64)
    qpos = np.zeros((len(states), 7 + len(joint_names)))
    first = states[0][1]["name"]
    missing = [j for j in joint_names if j not in first]
    if missing:
        raise McapFormatError(f"{log.path}: topic /joint_states: field name lacks joints {missing}")
    for i, (_, m) in enumerate(states):
        index = {n: k for k, n in enumerate(m["name"])}
        try:
            qpos[i, 7:] = [m["position"][index[j]] for j in joint_names]
        except (KeyError, IndexError):
            raise McapFormatError(
                f"{log.path}: topic /joint_states, message {i}: field position does not match name"
            ) from None
    base_t = np.array([t for t, _ in base], dtype=np.int64)
    k = np.clip(np.searchsorted(base_t, times, side="right") - 1, 0, len(base) - 1)
    for i, j in enumerate(k):
        b = base[j][1]
        p, o = b["position"], b["orientation"]
        qpos[i, :7] = [p["x"], p["y"], p["z"], o["w"], o["x"], o["y"], o["z"]]
    return times, qpos


def sample_at(times_ns: np.ndarray, values: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Zero-order hold: the last value at or before each query time (the first before it)."""
    k = np.clip(np.searchsorted(times_ns, query_ns, side="right") - 1, 0, len(times_ns) - 1)
    return values[k]
