"""ROS 2 bags (a rosbag2 folder, sqlite3 or MCAP storage) as a robot log
(:mod:`humimic.real2sim.imports`): ``sensor_msgs`` joint states, targets and IMU, or Unitree's
own low-level messages, with optional motion capture.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from humimic.errors import InputError, first_line
from humimic.real2sim.imports_common import (
    ImportMap,
    Target,
    assemble_log,
    check_finite,
    check_gains,
    check_increasing,
    check_map_used,
    check_overlap,
    source_columns,
    unit_quaternions,
)
from humimic.real2sim.robotlog import RobotLog


@dataclass(frozen=True, kw_only=True)
class RosTopics:
    """The topics of a ROS 2 bag that hold the log (``--*-topic`` flags).

    Attributes:
        joint_states: ``sensor_msgs/msg/JointState``, or a Unitree ``LowState`` (motors and
            IMU in one message).
        commands: ``sensor_msgs/msg/JointState`` of targets (position, velocity, effort:
            feedforward torque; gains from the map) or a Unitree ``LowCmd``.
        imu: ``sensor_msgs/msg/Imu`` (empty: none, or the ``LowState``'s).
        base_pose: ``geometry_msgs/msg/PoseStamped`` from motion capture (empty: none).
    """

    joint_states: str = "/joint_states"
    commands: str = "/joint_commands"
    imu: str = "/imu"
    base_pose: str = ""


def _stamp_ns(msg: Any, logtime: int) -> int:
    """A message's header stamp in nanoseconds, or the bag's receive time without one."""
    h = getattr(msg, "header", None)
    if h is None:
        return logtime
    ns = int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)
    return ns if ns > 0 else logtime


def _read_bag(path: Path, topics: Iterable[str]) -> tuple[dict[str, list], dict[str, str]]:
    """Messages per wanted topic as (stamp ns, message), and the type of every topic in the
    bag."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(
            "importing ROS 2 bags needs the rosbags package: pip install 'humimic[ros]'"
        ) from None
    wanted = [t for t in topics if t]
    out: dict[str, list] = {t: [] for t in wanted}
    types: dict[str, str] = {}
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
            conns = [c for c in reader.connections if c.topic in out]
            for conn, logtime, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                out[conn.topic].append((_stamp_ns(msg, logtime), msg))
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        hint = "; humimic's own logs need no import" if "not ros2" in str(e) else ""
        raise InputError(f"{path}: not a readable ROS 2 bag ({first_line(e)}){hint}") from None
    return out, types


def _sorted_by_stamp(where: str, topic: str, msgs: list) -> list:
    msgs = sorted(msgs, key=lambda m: m[0])
    ns = np.array([m[0] for m in msgs], dtype=np.int64)
    dup = np.flatnonzero(np.diff(ns) <= 0)
    if dup.size:
        raise InputError(f"{where}: topic {topic}, message {int(dup[0]) + 1}: stamp repeats "
                         f"({ns[dup[0]]} ns)")  # fmt: skip
    return msgs


def _times_s(msgs: list, t0_ns: int) -> np.ndarray:
    """Stamps in seconds from ``t0_ns`` (subtracted in integers: a float64 of nanoseconds
    since 1970 resolves only 256 ns)."""
    return (np.array([m[0] for m in msgs], dtype=np.int64) - t0_ns).astype(np.float64) * 1e-9


def _message(i: int) -> str:
    return f"message {i}"


def _joint_rows(
    where: str, topic: str, msgs: list, imap: ImportMap, target: Target, fields: tuple[str, ...],
    seen: set[str],
) -> dict[str, np.ndarray | None]:  # fmt: skip
    """Model-ordered (N, J) arrays of ``sensor_msgs/JointState`` fields; a field empty in
    every message is ``None``. Adds the source joints to ``seen``."""
    out: dict[str, np.ndarray | None] = {}
    cols: dict[tuple[str, ...], np.ndarray] = {}
    for f in fields:
        rows = np.full((len(msgs), len(target.joint_names)), np.nan)
        empty = 0
        for i, (_, m) in enumerate(msgs):
            names = tuple(m.name)
            if names not in cols:
                cols[names] = source_columns(f"{where}: topic {topic}, message {i}", list(names), imap,
                                       target, motors=False)  # fmt: skip
                seen.update(names)
            v = np.asarray(getattr(m, f), dtype=np.float64)
            if v.size == 0:
                empty += 1
                continue
            if v.size != len(names):
                raise InputError(f"{where}: topic {topic}, message {i}: {f} has {v.size} values "
                                 f"for {len(names)} names")  # fmt: skip
            rows[i] = v[cols[names]]
        if empty == len(msgs):
            out[f] = None
            continue
        if empty:
            raise InputError(f"{where}: topic {topic}: field {f} is empty in {empty} of "
                             f"{len(msgs)} messages")  # fmt: skip
        out[f] = check_finite(
            where, f"topic {topic}, field {f}", rows, _message, target.joint_names
        )
    return out


def _motor_rows(
    where: str, topic: str, msgs: list, imap: ImportMap, target: Target, attr: str,
    fields: tuple[str, ...], seen: set[str],
) -> dict[str, np.ndarray]:  # fmt: skip
    """Model-ordered (N, J) arrays of a Unitree message's per-motor fields. Adds the motor
    indices to ``seen``."""
    motors = len(getattr(msgs[0][1], attr))
    for i, (_, m) in enumerate(msgs):
        if len(getattr(m, attr)) != motors:
            raise InputError(f"{where}: topic {topic}, message {i}: {len(getattr(m, attr))} "
                             f"entries in {attr}, message 0 has {motors}")  # fmt: skip
    col = source_columns(
        f"{where}: topic {topic}", [str(i) for i in range(motors)], imap, target, motors=True
    )
    seen.update(str(i) for i in range(motors))
    out = {}
    for f in fields:
        rows = np.array([[getattr(x, f) for x in getattr(m, attr)] for _, m in msgs], dtype=float)
        out[f] = check_finite(where, f"topic {topic}, {attr}[].{f}", rows[:, col], _message,
                         target.joint_names)  # fmt: skip
    return out


def _gains(where: str, imap: ImportMap, target: Target, rows: int) -> tuple[np.ndarray, np.ndarray]:
    kp = np.full(len(target.joint_names), np.nan)
    kd = kp.copy()
    for j, n in enumerate(target.joint_names):
        g = imap.gains.get(n, imap.gains.get("*"))
        if g is not None:
            kp[j], kd[j] = g
    missing = [n for n, k in zip(target.joint_names, kp, strict=True) if np.isnan(k)]
    if missing:
        raise InputError(
            f"{where}: the command topic carries no gains; give kp and kd for "
            + ", ".join(missing[:3]) + ("..." if len(missing) > 3 else "")
            + " in --map (gains: {'*': {kp: ..., kd: ...}})"
        )  # fmt: skip
    return np.tile(kp, (rows, 1)), np.tile(kd, (rows, 1))


_Imu = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]
"""An IMU stream: times, orientation (w x y z), angular velocity, linear acceleration."""


def _check_bag_path(p: Path) -> None:
    """Refuse a path that is not a bag: missing, a folder without ``metadata.yaml``, or
    neither a file nor a folder."""
    if not p.exists():
        raise InputError(f"{p}: no such ROS 2 bag")
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        raise InputError(f"{p}: a ROS 2 bag folder holds metadata.yaml; none here")
    if not p.is_dir() and not p.is_file():
        raise InputError(f"{p}: not a regular file or a folder")


def _states(
    where: str, topic: str, states: list, types: dict[str, str], imap: ImportMap, target: Target,
    seen: set[str], t: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, _Imu | None]:  # fmt: skip
    """Model-ordered positions, velocities and efforts (``None`` when not recorded) of the
    joint-state messages, and the IMU a Unitree ``LowState`` carries (``None`` otherwise).
    Adds the source joints to ``seen``."""
    imu = None
    first = states[0][1]
    if hasattr(first, "motor_state"):
        rows = _motor_rows(where, topic, states, imap, target, "motor_state",
                           ("q", "dq", "tau_est"), seen)  # fmt: skip
        q, qd, effort = rows["q"], rows["dq"], rows["tau_est"]
        if hasattr(first, "imu_state"):
            arr: Callable[[str], np.ndarray] = lambda f: check_finite(  # noqa: E731
                where, f"topic {topic}, imu_state.{f}",
                np.array([getattr(m.imu_state, f) for _, m in states], dtype=float))  # fmt: skip
            imu = (t, unit_quaternions(where, f"topic {topic}, imu_state.quaternion",
                                       arr("quaternion")),
                   arr("gyroscope"), arr("accelerometer"))  # fmt: skip
    elif hasattr(first, "position") and hasattr(first, "name"):
        rows = _joint_rows(where, topic, states, imap, target,
                           ("position", "velocity", "effort"), seen)  # fmt: skip
        if rows["position"] is None or rows["velocity"] is None:
            raise InputError(f"{where}: topic {topic}: position and velocity "
                             "are both needed")  # fmt: skip
        q, qd, effort = rows["position"], rows["velocity"], rows["effort"]
    else:
        raise InputError(f"{where}: topic {topic} is {types[topic]}, "
                         "expected sensor_msgs/msg/JointState or a Unitree LowState")  # fmt: skip
    return q, qd, effort, imu


def _imu(
    where: str, topic: str, msgs: list, types: dict[str, str], t: np.ndarray, t0_ns: int
) -> _Imu:
    """The ``sensor_msgs/msg/Imu`` messages of ``topic``, refused without an orientation
    (``orientation_covariance[0]`` of -1) or outside the joint states' times ``t``."""
    _expect(where, topic, msgs, types, "sensor_msgs/msg/Imu",
            ("orientation", "orientation_covariance", "angular_velocity",
             "linear_acceleration"))  # fmt: skip
    ims = _sorted_by_stamp(where, topic, msgs)
    ti = check_increasing(where, f"topic {topic}", _times_s(ims, t0_ns))
    check_overlap(where, t, ti, f"IMU messages on {topic}")

    def xyz(m: Any, f: str, keys: str) -> list[float]:
        v = getattr(m, f)
        return [float(getattr(v, k)) for k in keys]

    cov = np.array([m.orientation_covariance[0] for _, m in ims])
    if np.any(cov < 0):
        raise InputError(f"{where}: topic {topic}, message {int(np.argmax(cov < 0))}: "
                         "orientation_covariance[0] is -1 (no orientation); the IMU's "
                         "orientation is needed")  # fmt: skip
    quat = unit_quaternions(where, f"topic {topic}, orientation",
                            check_finite(where, f"topic {topic}, orientation",
                                         np.array([xyz(m, "orientation", "wxyz")
                                                   for _, m in ims])))  # fmt: skip
    gyro = check_finite(where, f"topic {topic}, angular_velocity",
                        np.array([xyz(m, "angular_velocity", "xyz") for _, m in ims]))  # fmt: skip
    acc = check_finite(where, f"topic {topic}, linear_acceleration",
                       np.array([xyz(m, "linear_acceleration", "xyz") for _, m in ims]))  # fmt: skip
    return ti, quat, gyro, acc


def _commands(
    where: str, topic: str, cmds: list, types: dict[str, str], imap: ImportMap, target: Target,
    seen: set[str],
) -> tuple[dict[str, np.ndarray], bool]:  # fmt: skip
    """Model-ordered commands of a Unitree ``LowCmd`` (with their gains) or a ``JointState``
    of targets (gains from the map; velocity targets and feedforward torques zero when
    empty), and whether the gains came from the map. Adds the source joints to ``seen``."""
    c0 = cmds[0][1]
    gains_from_map = False
    if hasattr(c0, "motor_cmd"):
        rows = _motor_rows(where, topic, cmds, imap, target, "motor_cmd",
                           ("q", "dq", "tau", "kp", "kd"), seen)  # fmt: skip
        cmd = {"q": rows["q"], "qd": rows["dq"], "tau": rows["tau"], "kp": rows["kp"],
               "kd": rows["kd"]}  # fmt: skip
    elif hasattr(c0, "position") and hasattr(c0, "name"):
        rows = _joint_rows(where, topic, cmds, imap, target,
                           ("position", "velocity", "effort"), seen)  # fmt: skip
        if rows["position"] is None:
            raise InputError(f"{where}: topic {topic}: position targets are empty")
        zero = np.zeros((len(cmds), len(target.joint_names)))
        kp, kd = _gains(where, imap, target, len(cmds))
        gains_from_map = True
        cmd = {"q": rows["position"], "kp": kp, "kd": kd,
               "qd": zero if rows["velocity"] is None else rows["velocity"],
               "tau": zero if rows["effort"] is None else rows["effort"]}  # fmt: skip
    else:
        raise InputError(f"{where}: topic {topic} is {types[topic]}, "
                         "expected sensor_msgs/msg/JointState or a Unitree LowCmd")  # fmt: skip
    for k in ("kp", "kd"):
        check_gains(where, f"topic {topic}, {k}", cmd[k], target.joint_names)
    return cmd, gains_from_map


def _mocap(
    where: str, topic: str, poses: list | None, types: dict[str, str], t: np.ndarray, t0_ns: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion capture's root pose (times, position, quaternion) from the
    ``geometry_msgs/msg/PoseStamped`` messages of ``topic``, which must have some."""
    if not poses:
        raise InputError(f"{where}: no messages on {topic} (--base-pose-topic)")
    _expect(where, topic, poses, types, "geometry_msgs/msg/PoseStamped", ("pose",))
    poses = _sorted_by_stamp(where, topic, poses)
    tb = check_increasing(where, f"topic {topic}", _times_s(poses, t0_ns))
    check_overlap(where, t, tb, f"poses on {topic}")
    pos = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                    for _, m in poses])  # fmt: skip
    bq = np.array([[m.pose.orientation.w, m.pose.orientation.x, m.pose.orientation.y,
                    m.pose.orientation.z] for _, m in poses])  # fmt: skip
    return (tb, check_finite(where, f"topic {topic}, position", pos),
            unit_quaternions(where, f"topic {topic}, orientation", bq))  # fmt: skip


def import_ros2(
    path: str | os.PathLike[str], target: Target, imap: ImportMap, topics: RosTopics
) -> RobotLog:
    """A ROS 2 bag (a rosbag2 folder, sqlite3 or MCAP storage) as a robot log. Times are the
    messages' header stamps (the bag's receive time for messages without a header).

    Raises:
        InputError: A missing topic or field, a joint that is neither mapped nor ignored,
            non-finite values, repeated stamps, naming the bag, the topic and the message.
    """
    p = Path(path)
    _check_bag_path(p)
    where = str(p)
    seen: set[str] = set()
    msgs, types = _read_bag(p, [topics.joint_states, topics.commands, topics.imu, topics.base_pose])
    for flag, topic in (
        ("--states-topic", topics.joint_states),
        ("--commands-topic", topics.commands),
    ):
        if not msgs.get(topic):
            found = ", ".join(f"{k} ({v})" for k, v in sorted(types.items())) or "no topics"
            raise InputError(f"{where}: no messages on {topic} ({flag}); the bag has {found}")
    states = _sorted_by_stamp(where, topics.joint_states, msgs[topics.joint_states])
    t0_ns = min(m[0] for ms in msgs.values() if ms for m in ms)
    t = check_increasing(where, f"topic {topics.joint_states}", _times_s(states, t0_ns))
    q, qd, effort, imu = _states(where, topics.joint_states, states, types, imap, target, seen, t)
    if msgs.get(topics.imu):
        imu = _imu(where, topics.imu, msgs[topics.imu], types, t, t0_ns)
    elif topics.imu and imu is None and target.base == "floating":
        raise InputError(f"{where}: no messages on {topics.imu} (--imu-topic); a floating-base "
                         "log needs the IMU")  # fmt: skip
    cmds = _sorted_by_stamp(where, topics.commands, msgs[topics.commands])
    t_cmd = check_increasing(where, f"topic {topics.commands}", _times_s(cmds, t0_ns))
    check_overlap(where, t, t_cmd, f"commands on {topics.commands}")
    cmd, gains_from_map = _commands(where, topics.commands, cmds, types, imap, target, seen)
    mocap = None
    if topics.base_pose:
        mocap = _mocap(where, topics.base_pose, msgs.get(topics.base_pose), types, t, t0_ns)
    check_map_used(where, imap, seen, target, gains=gains_from_map)
    return assemble_log(where, target, t=t, q=q, qd=qd, effort=effort, t_cmd=t_cmd, cmd=cmd,
                        imu=imu, mocap=mocap)  # fmt: skip


def _expect(
    where: str, topic: str, msgs: list, types: dict[str, str], kind: str, fields: tuple[str, ...]
) -> None:
    """Refuse a topic whose messages lack the fields of ``kind``."""
    if not all(hasattr(msgs[0][1], f) for f in fields):
        raise InputError(f"{where}: topic {topic} is {types.get(topic)}, expected {kind}")
