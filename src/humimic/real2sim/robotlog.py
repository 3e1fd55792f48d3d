"""Robot logs: joint states and drive commands over time, read from and written to MCAP
(:class:`RobotLog`, :func:`read_robot_log`, :func:`write_robot_log`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from humimic.errors import InputError
from humimic.formats.mcap import McapFormatError, McapWriter, read_mcap, stamp

QUAT_TOL = 0.1
"""A logged orientation whose length differs from 1 by more than this is refused (a wrong
field, not noise); others are normalized."""

GAP = 1.5
"""A step between state samples longer than this many median intervals is a gap in the log."""


@dataclass(frozen=True, kw_only=True)
class ImuLog:
    """IMU samples of a floating-base log (topic ``/imu``). Times in seconds on the log's clock.

    Attributes:
        site: The model site the IMU sits at (metadata ``robot.imu_site``), e.g.
            ``imu_in_pelvis``; it must sit on the root body.
        t: Sample times. Shape: (N,).
        quat_w: Orientation, world from IMU (w x y z, unit length). Shape: (N, 4).
        gyro_b: Angular velocity in the IMU frame [rad/s]. Shape: (N, 3).
        acc_b: Specific force in the IMU frame [m/s^2] (gravity included: +9.81 up when
            still), or ``None`` when not logged. Shape: (N, 3).
    """

    site: str
    t: np.ndarray
    quat_w: np.ndarray
    gyro_b: np.ndarray
    acc_b: np.ndarray | None


@dataclass(frozen=True, kw_only=True)
class PoseTrack:
    """The root body's pose from motion capture (topic ``/base_pose``).

    Attributes:
        t: Sample times [s]. Shape: (N,).
        pos_w: Position in the world [m]. Shape: (N, 3).
        quat_w: Orientation, world from root body (w x y z). Shape: (N, 4).
    """

    t: np.ndarray
    pos_w: np.ndarray
    quat_w: np.ndarray


@dataclass(frozen=True, kw_only=True)
class RobotLog:
    """A robot log in the model's joint order. Times in seconds from the first message.

    The file's schema (docs/viewer.md lists the topics): a metadata record ``robot``
    (``name``, ``base`` = ``fixed`` or ``floating``, ``base_pose`` for a fixed base),
    ``/joint_states`` (position, velocity, optional effort) and ``/joint_commands`` (position,
    velocity, effort, kp, kd), each stamped; MCAP log time is the time base. A floating-base
    log of a robot on the floor adds ``/imu`` (with metadata ``robot.imu_site``) and, when a
    motion-capture system tracked the root body, ``/base_pose`` (docs/real2sim.md, "Logs").

    Attributes:
        robot: Registry name. base: ``fixed`` or ``floating``.
        base_pose: For a fixed base: x y z qw qx qy qz of the root body. Shape: (7,).
        joint_names: Shape: (J,).
        t: State times. Shape: (N,). q, qd: Shape: (N, J). effort: Shape: (N, J) or None.
        t_cmd: Command times. Shape: (M,). Commands (M, J): cmd_q, cmd_qd, cmd_tau, kp, kd.
        source: The file it was read from (empty when made in code), for messages.
        imu: The IMU of a floating base (``None``: not logged).
        mocap: The root body's pose from motion capture (``None``: not logged).
    """

    robot: str
    base: str
    base_pose: np.ndarray
    joint_names: tuple[str, ...]
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    effort: np.ndarray | None
    t_cmd: np.ndarray
    cmd_q: np.ndarray
    cmd_qd: np.ndarray
    cmd_tau: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    source: str = ""
    imu: ImuLog | None = None
    mocap: PoseTrack | None = None

    @property
    def where(self) -> str:
        """The log, as messages name it (its file, when it has one)."""
        return self.source or "the log"

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def gaps(self) -> np.ndarray:
        """Where the state stream breaks: indices ``i`` with more than :data:`GAP` median
        state intervals between sample ``i`` and ``i + 1`` (dropped messages, or several
        episodes logged one after another). Shape: (G,)."""
        if self.t.size < 2:
            return np.zeros(0, dtype=np.int64)
        dt = np.diff(self.t)
        return np.flatnonzero(dt > GAP * float(np.median(dt)))

    def unbroken(
        self, starts: np.ndarray, samples: int | np.ndarray, settle: float = 0.0
    ) -> np.ndarray:
        """Which stretches ``starts[k] .. starts[k] + samples`` of the state samples lie
        within one unbroken part of the log, starting at least ``settle`` seconds after that
        part's first sample when a gap precedes it (what came before a gap is not what the
        drives held). Shape: (len(starts),), bool."""
        starts = np.asarray(starts, dtype=np.int64)
        gaps = self.gaps()
        if gaps.size == 0:
            return np.ones(starts.shape, dtype=bool)
        part = np.searchsorted(gaps, starts, side="left")  # Gaps before each start.
        same = part == np.searchsorted(gaps, starts + samples, side="left")
        first = np.concatenate([[0], gaps + 1])[part]
        settled = (part == 0) | (self.t[starts] - self.t[first] >= settle - 1e-9)
        return same & settled

    def command_index(self, times: np.ndarray) -> np.ndarray:
        """Index of the command in force at each time (the drive holds the last one)."""
        return np.clip(np.searchsorted(self.t_cmd, times, side="right") - 1, 0, len(self.t_cmd) - 1)


def join_logs(logs: list[RobotLog], pause: float = 1.0) -> RobotLog:
    """Several logs of one robot as one, each after the last with ``pause`` seconds between
    (every stream shifted alike): episodes recorded one after another. The joins are gaps
    (:meth:`RobotLog.gaps`) that no prediction window spans.

    Raises:
        InputError: No logs, a pause that is not longer than a state interval, or logs of
            other robots, bases, joints, IMU sites or streams.
    """
    if not logs:
        raise InputError("join_logs: no logs to join")
    first = logs[0]
    dt = float(np.median(np.diff(first.t))) if first.t.size > 1 else 0.0
    if not (np.isfinite(pause) and pause > GAP * dt):
        raise InputError(f"join_logs: pause {pause} s must exceed {GAP} state intervals")

    def kind(lg: RobotLog) -> tuple:
        """What logs joined into one must share."""
        return (lg.robot, lg.base, lg.joint_names, tuple(lg.base_pose), lg.effort is None,
                lg.imu and lg.imu.site, lg.imu and lg.imu.acc_b is None, lg.mocap is None)  # fmt: skip

    for other in logs[1:]:
        if kind(other) != kind(first):
            raise InputError(f"join_logs: {other.where} is not a log of the same robot, "
                             f"joints and streams as {first.where}")  # fmt: skip
    shifted, end = [], 0.0
    for k, lg in enumerate(logs):
        starts = [lg.t[0], lg.t_cmd[0], *(x.t[0] for x in (lg.imu, lg.mocap) if x is not None)]
        ends = [lg.t[-1], lg.t_cmd[-1], *(x.t[-1] for x in (lg.imu, lg.mocap) if x is not None)]
        shift = 0.0 if k == 0 else end + pause - min(starts)
        shifted.append((lg, shift))
        end = max(ends) + shift

    def cat(get) -> np.ndarray:
        return np.concatenate([get(lg) for lg, _ in shifted])

    def times(get) -> np.ndarray:
        return np.concatenate([get(lg) + d for lg, d in shifted])

    imu = mocap = None
    if first.imu is not None:
        acc = None if first.imu.acc_b is None else cat(lambda lg: lg.imu.acc_b)
        imu = ImuLog(site=first.imu.site, t=times(lambda lg: lg.imu.t),
                     quat_w=cat(lambda lg: lg.imu.quat_w), gyro_b=cat(lambda lg: lg.imu.gyro_b),
                     acc_b=acc)  # fmt: skip
    if first.mocap is not None:
        mocap = PoseTrack(t=times(lambda lg: lg.mocap.t), pos_w=cat(lambda lg: lg.mocap.pos_w),
                          quat_w=cat(lambda lg: lg.mocap.quat_w))  # fmt: skip
    return RobotLog(
        robot=first.robot, base=first.base, base_pose=first.base_pose,
        joint_names=first.joint_names, t=times(lambda lg: lg.t), q=cat(lambda lg: lg.q),
        qd=cat(lambda lg: lg.qd),
        effort=None if first.effort is None else cat(lambda lg: lg.effort),
        t_cmd=times(lambda lg: lg.t_cmd), cmd_q=cat(lambda lg: lg.cmd_q),
        cmd_qd=cat(lambda lg: lg.cmd_qd), cmd_tau=cat(lambda lg: lg.cmd_tau),
        kp=cat(lambda lg: lg.kp), kd=cat(lambda lg: lg.kd), source=first.source, imu=imu,
        mocap=mocap,
    )  # fmt: skip


def write_robot_log(log: RobotLog, path: str | os.PathLike[str]) -> Path:
    """Write a robot log as MCAP (atomically)."""
    names = list(log.joint_names)
    t0 = min(log.t[0], log.t_cmd[0], *(x.t[0] for x in (log.imu, log.mocap) if x is not None))
    meta = {
        "name": log.robot,
        "base": log.base,
        "base_pose": " ".join(repr(float(x)) for x in log.base_pose),
    }
    if log.imu is not None:
        meta["imu_site"] = log.imu.site
    with McapWriter(path) as w:
        w.add_metadata("robot", meta)
        if log.imu is not None:
            imu = log.imu
            for i, ti in enumerate(imu.t):
                ns = round((ti - t0) * 1e9)
                msg = {"header": {"stamp": stamp(ns)}, "orientation": _wxyz(imu.quat_w[i]),
                       "angular_velocity": _xyz(imu.gyro_b[i])}  # fmt: skip
                if imu.acc_b is not None:
                    msg["linear_acceleration"] = _xyz(imu.acc_b[i])
                w.write("/imu", ns, msg)
        if log.mocap is not None:
            mc = log.mocap
            for i, ti in enumerate(mc.t):
                ns = round((ti - t0) * 1e9)
                w.write("/base_pose", ns, {"header": {"stamp": stamp(ns)},
                                           "position": _xyz(mc.pos_w[i]),
                                           "orientation": _wxyz(mc.quat_w[i])})  # fmt: skip
        for i, ti in enumerate(log.t_cmd):
            ns = round((ti - t0) * 1e9)
            w.write("/joint_commands", ns, {
                "header": {"stamp": stamp(ns)}, "name": names,
                "position": log.cmd_q[i].tolist(), "velocity": log.cmd_qd[i].tolist(),
                "effort": log.cmd_tau[i].tolist(), "kp": log.kp[i].tolist(), "kd": log.kd[i].tolist(),
            })  # fmt: skip
        for i, ti in enumerate(log.t):
            ns = round((ti - t0) * 1e9)
            msg = {
                "header": {"stamp": stamp(ns)}, "name": names,
                "position": log.q[i].tolist(), "velocity": log.qd[i].tolist(),
            }  # fmt: skip
            if log.effort is not None:
                msg["effort"] = log.effort[i].tolist()
            w.write("/joint_states", ns, msg)
    return Path(path)


def _xyz(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _wxyz(q: np.ndarray) -> dict[str, float]:
    return {"w": float(q[0]), "x": float(q[1]), "y": float(q[2]), "z": float(q[3])}


def _vectors(log_path: Path, topic: str, msgs: list, field: str, keys: str) -> np.ndarray:
    """One vector field (``{x, y, z}`` or ``{w, x, y, z}``) of a topic's messages.
    Shape: (len(msgs), len(keys)).

    Raises:
        McapFormatError: The field missing or not finite (naming topic, message and field).
    """
    out = np.empty((len(msgs), len(keys)))
    for i, (_, m) in enumerate(msgs):
        v = m.get(field)
        if not isinstance(v, dict) or any(k not in v for k in keys):
            raise McapFormatError(
                f"{log_path}: topic {topic}, message {i}: field {field} missing (expected "
                f"{', '.join(keys)})"
            )
        out[i] = [v[k] for k in keys]
    bad = np.argwhere(~np.isfinite(out))
    if bad.size:
        i, k = (int(x) for x in bad[0])
        raise McapFormatError(
            f"{log_path}: topic {topic}, message {i}: field {field}.{keys[k]} is {out[i, k]}, "
            "expected a finite number"
        )
    return out


def _unit_quats(log_path: Path, topic: str, q: np.ndarray, field: str) -> np.ndarray:
    """Quaternions normalized; refuses ones far from unit length (a wrong field, not noise).

    Raises:
        McapFormatError: Naming the topic, message and field.
    """
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOL)
    if bad.size:
        i = int(bad[0])
        raise McapFormatError(
            f"{log_path}: topic {topic}, message {i}: field {field} has length {norm[i]:.3g}, "
            "expected a unit quaternion (w, x, y, z)"
        )
    return q / norm[:, None]


def _matrix(
    log_path: Path, topic: str, msgs: list, field: str, names: tuple[str, ...]
) -> np.ndarray:
    """One field of a topic's messages for the model's joints. Shape: (len(msgs), J).

    Raises:
        McapFormatError: Joints missing, a field missing or not matching ``name``, or a
            non-finite value (naming the topic, the message index, the field and the joint).
    """
    out = np.zeros((len(msgs), len(names)))
    first = msgs[0][1]["name"]
    missing = [n for n in names if n not in first]
    if missing:
        raise McapFormatError(
            f"{log_path}: topic {topic}: field name lacks {len(missing)} of the robot's joints "
            f"({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}): a log of "
            "another robot, or of part of it?"
        )
    for i, (_, m) in enumerate(msgs):
        if field not in m:
            raise McapFormatError(f"{log_path}: topic {topic}, message {i}: field {field} missing")
        index = {n: k for k, n in enumerate(m["name"])}
        try:
            out[i] = [m[field][index[n]] for n in names]
        except (KeyError, IndexError):
            raise McapFormatError(
                f"{log_path}: topic {topic}, message {i}: field {field} does not match name"
            ) from None
    bad = np.argwhere(~np.isfinite(out))
    if bad.size:
        i, j = (int(x) for x in bad[0])
        raise McapFormatError(
            f"{log_path}: topic {topic}, message {i}: field {field} of {names[j]!r} is "
            f"{out[i, j]}, expected a finite number"
        )
    return out


def _check_increasing(log_path: object, topic: str, ns: np.ndarray, what: str, plural: str) -> None:
    """Refuse the first of ``ns`` (nanoseconds, one per message) not after the one before.

    Raises:
        McapFormatError: Naming the file, topic, message and ``what``.
    """
    back = np.flatnonzero(np.diff(ns) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise McapFormatError(
            f"{log_path}: topic {topic}, message {i}: {what} ({ns[i]} ns) is not after "
            f"message {i - 1}'s ({ns[i - 1]} ns); expected strictly increasing {plural}"
        )


def _times(log_path: Path, topic: str, msgs: list) -> np.ndarray:
    """Log times [ns] of a topic's messages, checked: log times and header stamps strictly
    increase (a robot samples forwards in time; equal or reversed stamps are a broken log).

    Raises:
        McapFormatError: Naming the topic and the first message out of order.
    """
    times = np.array([ts for ts, _ in msgs], dtype=np.int64)
    _check_increasing(log_path, topic, times, "log time", "times")
    stamps = np.empty(len(msgs), dtype=np.int64)
    for i, (_, m) in enumerate(msgs):
        st = m["header"]["stamp"]
        if not (st["sec"] >= 0 and 0 <= st["nanosec"] < 1_000_000_000):
            raise McapFormatError(
                f"{log_path}: topic {topic}, message {i}: field header.stamp is {st}, expected "
                "sec >= 0 and 0 <= nanosec < 1e9"
            )
        stamps[i] = st["sec"] * 1_000_000_000 + st["nanosec"]
    _check_increasing(log_path, topic, stamps, "field header.stamp", "stamps")
    return times


def parse_base_pose(meta: dict[str, str], log_path: Path) -> np.ndarray:
    """The fixed base's pose from the ``robot`` metadata (x y z qw qx qy qz). A floating-base
    log's is a placeholder (its base moves), held to 7 finite numbers only.

    Raises:
        McapFormatError: Not 7 finite numbers, or a zero quaternion for a fixed base.
    """
    text = meta.get("base_pose", "0 0 0 1 0 0 0")
    try:
        pose = np.array([float(x) for x in text.split()])
    except ValueError:
        pose = np.zeros(0)
    if pose.shape != (7,) or not np.isfinite(pose).all():
        raise McapFormatError(
            f"{log_path}: metadata robot.base_pose is {text!r}, expected 7 finite numbers "
            "(x y z qw qx qy qz)"
        )
    if meta.get("base") == "fixed" and np.linalg.norm(pose[3:]) < 1e-9:
        raise McapFormatError(
            f"{log_path}: metadata robot.base_pose has a zero quaternion, expected qw qx qy qz "
            "of unit length"
        )
    return pose


def read_robot_log(path: str | os.PathLike[str], joint_names: tuple[str, ...]) -> RobotLog:
    """Read a robot log, in the order of ``joint_names`` (the model's).

    Joints are matched to the model by name. Reading refuses what would mislead the numbers
    downstream: non-finite values, negative gains, and log times or header stamps that do not
    increase.

    Raises:
        InputError / McapFormatError: Missing file, topics, metadata or joints, a non-finite
            value, a negative gain, log times or stamps that do not increase, naming the file,
            the topic, the message and the field.
    """
    log = read_mcap(path, topics=["/joint_states", "/joint_commands", "/imu", "/base_pose"],
                    require=["/joint_states", "/joint_commands"])  # fmt: skip
    meta = log.meta("robot")
    base = meta.get("base", "")
    if base not in ("fixed", "floating"):
        raise McapFormatError(
            f"{log.path}: metadata robot.base is {base!r}, expected fixed or floating"
        )
    base_pose = parse_base_pose(meta, log.path)
    states = log.topic("/joint_states")
    cmds = log.topic("/joint_commands")
    ts_states = _times(log.path, "/joint_states", states)
    ts_cmds = _times(log.path, "/joint_commands", cmds)
    imu_msgs, pose_msgs = log.messages.get("/imu", []), log.messages.get("/base_pose", [])
    ts_imu = _times(log.path, "/imu", imu_msgs) if imu_msgs else None
    ts_pose = _times(log.path, "/base_pose", pose_msgs) if pose_msgs else None
    t_all0 = min(ts_states[0], ts_cmds[0],
                 *(x[0] for x in (ts_imu, ts_pose) if x is not None))  # fmt: skip
    t = (ts_states - t_all0).astype(np.float64) * 1e-9
    t_cmd = (ts_cmds - t_all0).astype(np.float64) * 1e-9
    imu = mocap = None
    if ts_imu is not None:
        imu = _read_imu(log.path, meta, imu_msgs, (ts_imu - t_all0).astype(np.float64) * 1e-9)
    if ts_pose is not None:
        mocap = _read_mocap(log.path, pose_msgs, (ts_pose - t_all0).astype(np.float64) * 1e-9)
    has_effort = all("effort" in m for _, m in states)
    zero = np.zeros((len(cmds), len(joint_names)))

    def cmd(field: str) -> np.ndarray:
        return (
            _matrix(log.path, "/joint_commands", cmds, field, joint_names)
            if all(field in m for _, m in cmds)
            else zero.copy()
        )

    gains = _read_gains(log.path, cmds, joint_names)
    return RobotLog(
        robot=meta.get("name", ""),
        base=base,
        base_pose=base_pose,
        joint_names=joint_names,
        t=t,
        q=_matrix(log.path, "/joint_states", states, "position", joint_names),
        qd=_matrix(log.path, "/joint_states", states, "velocity", joint_names),
        effort=_matrix(log.path, "/joint_states", states, "effort", joint_names)
        if has_effort
        else None,
        t_cmd=t_cmd,
        cmd_q=_matrix(log.path, "/joint_commands", cmds, "position", joint_names),
        cmd_qd=cmd("velocity"),
        cmd_tau=cmd("effort"),
        kp=gains["kp"],
        kd=gains["kd"],
        source=str(log.path),
        imu=imu,
        mocap=mocap,
    )


def _read_imu(log_path: Path, meta: dict[str, str], msgs: list, t: np.ndarray) -> ImuLog:
    """The ``/imu`` messages ``msgs`` (at log times ``t``) as an :class:`ImuLog`, its
    accelerometer only if every message has ``linear_acceleration``.

    Raises:
        McapFormatError: No metadata ``robot.imu_site``, or a bad field (naming the message).
    """
    site = meta.get("imu_site", "")
    if not site:
        raise McapFormatError(
            f"{log_path}: topic /imu is logged but metadata robot.imu_site is missing "
            "(the model site the IMU sits at, e.g. imu_in_pelvis)"
        )
    acc = None
    if all("linear_acceleration" in m for _, m in msgs):
        acc = _vectors(log_path, "/imu", msgs, "linear_acceleration", "xyz")
    return ImuLog(
        site=site,
        t=t,
        quat_w=_unit_quats(
            log_path, "/imu", _vectors(log_path, "/imu", msgs, "orientation", "wxyz"), "orientation"
        ),
        gyro_b=_vectors(log_path, "/imu", msgs, "angular_velocity", "xyz"),
        acc_b=acc,
    )


def _read_mocap(log_path: Path, msgs: list, t: np.ndarray) -> PoseTrack:
    """The ``/base_pose`` messages ``msgs`` (at log times ``t``) as a :class:`PoseTrack`.

    Raises:
        McapFormatError: A bad field (naming the message).
    """
    pos = _vectors(log_path, "/base_pose", msgs, "position", "xyz")
    quat = _vectors(log_path, "/base_pose", msgs, "orientation", "wxyz")
    return PoseTrack(
        t=t, pos_w=pos, quat_w=_unit_quats(log_path, "/base_pose", quat, "orientation")
    )


def _read_gains(log_path: Path, cmds: list, joint_names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The commands' ``kp`` and ``kd`` per message and joint (M, J).

    Raises:
        McapFormatError: A missing or negative gain, naming the message and the joint.
    """
    gains = {}
    for field in ("kp", "kd"):
        g = _matrix(log_path, "/joint_commands", cmds, field, joint_names)
        neg = np.argwhere(g < 0)
        if neg.size:
            i, j = (int(x) for x in neg[0])
            raise McapFormatError(
                f"{log_path}: topic /joint_commands, message {i}: field {field} of "
                f"{joint_names[j]!r} is {g[i, j]:g}, expected a gain >= 0"
            )
        gains[field] = g
    return gains
