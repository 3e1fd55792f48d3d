"""A :class:`humimic.motion.Motion` as MCAP and back, losslessly.

Frames go on ``/reference/*`` topics (plus ``/tf`` for Foxglove), the motion's scalars and names
in a ``motion`` metadata record, a dynamic section on ``/dynamics/step``. Reading checks the
motion as the ``.npz`` reader does.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from humimic.formats.mcap.reader import McapLog, read_mcap
from humimic.formats.mcap.schemas import McapFormatError, stamp, tf_message
from humimic.formats.mcap.writer import McapWriter

if TYPE_CHECKING:  # humimic.motion imports MuJoCo: imported on use, not to read a plain log.
    from humimic.motion import Motion


def iter_frames(fps: float, n: int) -> Iterator[tuple[int, int]]:
    """(frame index, log time in ns) for ``n`` frames at ``fps``."""
    for i in range(n):
        yield i, round(i * 1e9 / fps)


def write_motion_mcap(motion: Motion, path: str | os.PathLike[str]) -> Path:
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


def write_motion_topics(w: McapWriter, motion: Motion) -> None:
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


def read_motion_mcap(path: str | os.PathLike[str]) -> Motion:
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

    qpos = _topic_field(p, log, "/reference/qpos", "qpos")
    fields = {
        "joint_pos": _topic_field(p, log, "/reference/joint_states", "position"),
        "joint_vel": _topic_field(p, log, "/reference/joint_states", "velocity"),
        "body_pos_w": _topic_field(p, log, "/reference/body_states", "position"),
        "body_quat_w": _topic_field(p, log, "/reference/body_states", "orientation"),
        "body_lin_vel_w": _topic_field(p, log, "/reference/body_states", "linear_velocity"),
        "body_ang_vel_w": _topic_field(p, log, "/reference/body_states", "angular_velocity"),
    }
    extras = _read_extras(p, log, extra_types) if extra_types else {}
    dynamics = _read_dynamics(p, log) if "dynamics" in log.metadata else None
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


def _topic_field(p: Path, log: McapLog, topic: str, key: str) -> np.ndarray:
    """One field of every message of a topic, stacked: one row per frame."""
    msgs = log.topic(topic)
    try:
        rows = [m[key] for _, m in msgs]
    except KeyError:
        raise McapFormatError(f"{p}: topic {topic}: field {key} missing") from None
    return _numbers(p, f"topic {topic}: field {key}", rows)


def _read_extras(p: Path, log: McapLog, extra_types: dict[str, Any]) -> dict[str, np.ndarray]:
    """The extras on ``/reference/extras``, each of the dtype and per-frame shape its entry of
    the ``motion.extras`` metadata names (``[dtype, shape]``; numbers or booleans only, never
    objects, which would be pickled)."""
    extras = {}
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
    return extras


def _read_dynamics(p: Path, log: McapLog) -> dict[str, np.ndarray]:
    """The dynamic section: ``physics_dt`` and ``initial_state`` from the ``dynamics``
    metadata, ``ctrl``, ``qpos`` and ``qvel`` from ``/dynamics/step`` (a message per step)."""
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
    return dynamics
