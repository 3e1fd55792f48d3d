"""Robot logs from other recorders, turned into humimic's MCAP contract (``humimic sysid
import``): Unitree low-state arrays (NPZ or CSV) and ROS 2 bags (docs/real2sim.md, "Real logs
in").
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from humimic.errors import InputError, first_line
from humimic.io import read_yaml
from humimic.npyio import read_npz_members
from humimic.real2sim.robotlog import QUAT_TOL, ImuLog, PoseTrack, RobotLog

if TYPE_CHECKING:
    from humimic.robots.registry import RobotConfig

UNITREE_KEYS = {
    "time": "state times [s]",
    "q": "motor_state[].q [rad]",
    "dq": "motor_state[].dq [rad/s]",
    "tau_est": "motor_state[].tau_est [N m]",
    "quaternion": "imu_state.quaternion (w x y z)",
    "gyroscope": "imu_state.gyroscope [rad/s]",
    "accelerometer": "imu_state.accelerometer [m/s^2]",
    "cmd_time": "command times [s] (default: the state times)",
    "cmd_q": "motor_cmd[].q [rad]",
    "cmd_dq": "motor_cmd[].dq [rad/s]",
    "cmd_tau": "motor_cmd[].tau [N m]",
    "cmd_kp": "motor_cmd[].kp",
    "cmd_kd": "motor_cmd[].kd",
    "base_time": "motion-capture times [s] (default: the state times)",
    "base_pos": "motion capture: root position, world [m]",
    "base_quat": "motion capture: root orientation, world (w x y z)",
}
"""The arrays of a Unitree low-state log: the names follow unitree_sdk2's ``LowState_`` and
``LowCmd_`` fields. Required: time, q, dq, cmd_q, cmd_kp, cmd_kd."""

_COMPONENTS = {"quaternion": "wxyz", "base_quat": "wxyz", "gyroscope": "xyz",
               "accelerometer": "xyz", "base_pos": "xyz"}  # fmt: skip
_SCALARS = ("time", "cmd_time", "base_time")


@dataclass(frozen=True, kw_only=True)
class ImportMap:
    """How a recorder's joints and gains map onto the robot (the ``--map`` YAML).

    Attributes:
        joints: Source joint -> model joint, where it differs from the default. Source
            joints are motor indices (``"0"``, ``"1"``, ... for Unitree messages; by default
            motor ``i`` is the model's ``i``-th joint) or the names a ROS ``JointState``
            carries (by default the model's joint of that name).
        ignore: Source joints that are not in the model (hands, unused motor slots); any
            other unmapped source joint is an error.
        gains: Model joint (or ``"*"`` for every joint) -> (kp, kd), for command streams
            that carry no gains (a ROS ``JointState`` of targets).
        source: The file it was read from, for messages.
    """

    joints: dict[str, str] = field(default_factory=dict)
    ignore: frozenset[str] = frozenset()
    gains: dict[str, tuple[float, float]] = field(default_factory=dict)
    source: str = ""

    def model_joint(self, source_joint: str, default: str) -> str | None:
        """The model joint a source joint fills (``default`` unless the map names one), or
        ``None`` when it is ignored."""
        if source_joint in self.ignore:
            return None
        return self.joints.get(source_joint, default)


def read_import_map(path: str | os.PathLike[str]) -> ImportMap:
    """Read an import map (YAML with optional keys ``joints``, ``ignore``, ``gains``).

    Raises:
        InputError: Missing file, bad YAML, an unknown key or a malformed entry, naming the
            file and the key.
    """
    p = Path(path)
    data = read_yaml(p)
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise InputError(f"{p}: expected a mapping with keys joints, ignore, gains")
    unknown = set(data) - {"joints", "ignore", "gains"}
    if unknown:
        raise InputError(f"{p}: unknown key {sorted(unknown)[0]!r}; expected joints, ignore, gains")
    joints = data.get("joints") or {}
    if not isinstance(joints, dict) or not all(
        isinstance(k, str | int) and not isinstance(k, bool) and isinstance(v, str)
        for k, v in joints.items()
    ):
        raise InputError(f"{p}: joints must map each source joint (a name or a motor index) to "
                         "a model joint name")  # fmt: skip
    ignore = data.get("ignore") or []
    if not isinstance(ignore, list) or not all(
        isinstance(x, str | int) and not isinstance(x, bool) for x in ignore
    ):
        raise InputError(f"{p}: ignore must be a list of source joints (names or motor indices)")
    gains_in = data.get("gains") or {}
    if not isinstance(gains_in, dict):
        raise InputError(f"{p}: gains must map model joints (or '*') to {{kp: NUMBER, kd: NUMBER}}")
    gains: dict[str, tuple[float, float]] = {}
    for name, g in gains_in.items():
        try:
            if not isinstance(g, dict) or set(g) != {"kp", "kd"}:
                raise TypeError
            if any(isinstance(g[k], bool | str) for k in ("kp", "kd")):
                raise TypeError
            kp, kd = float(g["kp"]), float(g["kd"])
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{p}: gains.{name} must be {{kp: NUMBER, kd: NUMBER}}") from None
        if not (np.isfinite(kp) and np.isfinite(kd) and kp >= 0 and kd >= 0):
            raise InputError(f"{p}: gains.{name}: kp and kd must be finite and >= 0")
        gains[str(name)] = (kp, kd)
    return ImportMap(
        joints={str(k): v for k, v in joints.items()},
        ignore=frozenset(str(x) for x in ignore),
        gains=gains,
        source=str(p),
    )


@dataclass(frozen=True, kw_only=True)
class Target:
    """The robot a log is imported for.

    Attributes:
        robot: Registry name. joint_names: The model's log joints, in model order.
        imu_site: The model site the IMU sits at (floating base).
        base: ``floating`` (on the floor, with an IMU) or ``fixed`` (a gantry).
        base_pose: For a fixed base: x y z qw qx qy qz of the root body. Shape: (7,).
    """

    robot: str
    joint_names: tuple[str, ...]
    imu_site: str
    base: str
    base_pose: np.ndarray


def _columns(
    where: str, sources: list[str], imap: ImportMap, target: Target, *, motors: bool
) -> np.ndarray:
    """The source column that fills each model joint. Shape: (J,). Every model joint must be
    filled exactly once, and every source joint must fill one or be ignored. Sources are motor
    indices (``motors``; motor ``i`` is the model's ``i``-th joint unless mapped) or names."""
    names = target.joint_names
    col = np.full(len(names), -1)
    hint = ' in --map (docs/real2sim.md, "Real logs in")'
    for c, s in enumerate(sources):
        default = (names[c] if c < len(names) else "") if motors else s
        m = imap.model_joint(s, default)
        if m is None:
            continue
        what = f"motor {s}" if motors else f"joint {s!r}"
        if not m:
            raise InputError(f"{where}: {what} has no joint in {target.robot} "
                             f"({len(names)} joints); map it or ignore it" + hint)  # fmt: skip
        if m not in names:
            mapped = f" (mapped to {m!r})" if m != s else ""
            raise InputError(f"{where}: {what}{mapped} is not a joint of {target.robot}; map "
                             "it or ignore it" + hint)  # fmt: skip
        j = names.index(m)
        if col[j] >= 0:
            first = f"motor {sources[col[j]]}" if motors else repr(sources[col[j]])
            raise InputError(f"{where}: model joint {m!r} is filled by both {first} and {what}")
        col[j] = c
    missing = [n for n, c in zip(names, col, strict=True) if c < 0]
    if missing:
        raise InputError(
            f"{where}: no data for {len(missing)} joint(s) of {target.robot}: "
            + ", ".join(missing[:5]) + ("..." if len(missing) > 5 else "") + "; map them" + hint
        )  # fmt: skip
    return col


MAX_SPAN = 1e6
"""Longest span of a log's times [s] (11.6 days): more is a clock in other units (ns)."""


def _row(i: int) -> str:
    return f"row {i}"


def _finite(
    where: str, name: str, a: np.ndarray, row: Callable[[int], str] = _row,
    columns: tuple[str, ...] = (),
) -> np.ndarray:  # fmt: skip
    """``a``, refused when a value is not finite (naming the row, and the column's joint)."""
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        col = f" ({columns[int(bad[0][1])]})" if columns and a.ndim == 2 else ""
        raise InputError(f"{where}: {name}, {row(int(bad[0][0]))}{col}: a value is not finite")
    return a


def _increasing(
    where: str, name: str, t: np.ndarray, row: Callable[[int], str] = _row
) -> np.ndarray:
    if t.ndim != 1 or t.size < 2:
        raise InputError(f"{where}: {name} has shape {t.shape}, expected a 1-D array of at "
                         "least 2 times")  # fmt: skip
    _finite(where, name, t, row)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{where}: {name}, {row(i)}: time {t[i]:.6f} does not increase "
                         f"({row(i - 1)}: {t[i - 1]:.6f})")  # fmt: skip
    if t[-1] - t[0] > MAX_SPAN:
        raise InputError(f"{where}: {name} spans {t[-1] - t[0]:.4g} s; expected seconds (a "
                         "clock in milli- or nanoseconds must be converted)")  # fmt: skip
    return t


def _unit(where: str, name: str, q: np.ndarray, row: Callable[[int], str] = _row) -> np.ndarray:
    n = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(n - 1.0) <= QUAT_TOL))
    if bad.size:
        raise InputError(f"{where}: {name}, {row(int(bad[0]))}: quaternion of length "
                         f"{n[bad[0]]:.3f}, expected unit length (w x y z)")  # fmt: skip
    return q / n[:, None]


def _gains_check(
    where: str, name: str, g: np.ndarray, joints: tuple[str, ...], row: Callable[[int], str] = _row
) -> np.ndarray:
    neg = np.argwhere(g < 0)
    if neg.size:
        i, j = (int(x) for x in neg[0])
        raise InputError(f"{where}: {name}, {row(i)}: gain of {joints[j]!r} is {g[i, j]:g}, "
                         "expected >= 0")  # fmt: skip
    return g


def _overlap(where: str, t: np.ndarray, other: np.ndarray, what: str) -> None:
    """Refuse a stream that does not overlap the joint states in time."""
    if other[0] > t[-1] or other[-1] < t[0]:
        raise InputError(f"{where}: the {what} ({other[0]:.3f}-{other[-1]:.3f} s) do not overlap "
                         f"the joint states ({t[0]:.3f}-{t[-1]:.3f} s): one clock for every "
                         "stream is expected")  # fmt: skip


def _check_map_used(
    where: str, imap: ImportMap, seen: set[str], target: Target, gains: bool
) -> None:
    """Refuse map entries that name nothing: a typo would otherwise be ignored in silence.
    ``gains``: whether the command stream took its gains from the map."""
    for what, keys in (("joints", set(imap.joints)), ("ignore", set(imap.ignore))):
        unused = sorted(keys - seen)
        if unused:
            raise InputError(f"{imap.source}: {what} names {unused[0]!r}, which {where} does not "
                             "have (a source joint name or motor index)")  # fmt: skip
    if imap.gains and not gains:
        raise InputError(f"{imap.source}: gains are given, but the commands in {where} carry "
                         "their own kp and kd; remove them from the map")  # fmt: skip
    unknown = sorted(set(imap.gains) - set(target.joint_names) - {"*"})
    if unknown:
        raise InputError(f"{imap.source}: gains names {unknown[0]!r}, not a joint of "
                         f"{target.robot} (or '*')")  # fmt: skip


def _assemble(
    where: str,
    target: Target,
    *,
    t: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    effort: np.ndarray | None,
    t_cmd: np.ndarray,
    cmd: dict[str, np.ndarray],
    imu: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None,
    mocap: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
) -> RobotLog:
    """A :class:`RobotLog` from model-ordered arrays, times shifted to start at 0."""
    if target.base == "floating" and imu is None:
        raise InputError(
            f"{where}: a floating-base log needs the IMU (orientation and angular velocity); "
            "none was found (or import a gantry log with --base fixed)"
        )
    starts = [t[0], t_cmd[0]] + [x[0][0] for x in (imu, mocap) if x is not None]
    t0 = float(min(starts))
    imu_log = None
    if imu is not None and target.base == "floating":
        ti, quat, gyro, acc = imu
        imu_log = ImuLog(site=target.imu_site, t=ti - t0, quat_w=quat, gyro_b=gyro, acc_b=acc)
    pose = None
    if mocap is not None:
        pose = PoseTrack(t=mocap[0] - t0, pos_w=mocap[1], quat_w=mocap[2])
    return RobotLog(
        robot=target.robot,
        base=target.base,
        base_pose=target.base_pose,
        joint_names=target.joint_names,
        t=t - t0,
        q=q,
        qd=qd,
        effort=effort,
        t_cmd=t_cmd - t0,
        cmd_q=cmd["q"],
        cmd_qd=cmd["qd"],
        cmd_tau=cmd["tau"],
        kp=cmd["kp"],
        kd=cmd["kd"],
        source=where,
        imu=imu_log,
        mocap=pose,
    )


# --- Unitree low-state arrays (NPZ, CSV) ---------------------------------------------------


MAX_LOG_ARRAY_BYTES = 4 << 30
"""Most bytes the arrays of one ``.npz`` robot log may take (as a motion file)."""


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` log, read by :func:`humimic.npyio.read_npz_members`: the
    sizes its headers and zip directory claim are checked before anything is allocated
    (at most :data:`MAX_LOG_ARRAY_BYTES`), never a pickle."""
    try:
        with path.open("rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise InputError(f"{path}: cannot read: {e.strerror or first_line(e)}") from None
    if magic != b"PK\x03\x04":
        raise InputError(
            f"{path}: not a readable .npz archive (not a zip archive of .npy arrays, as "
            "numpy.savez writes)"
        )
    return read_npz_members(path, max_bytes=MAX_LOG_ARRAY_BYTES, kinds="biufc", error=InputError)


def _load_csv(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Columns ``time``, ``q_0`` ... ``q_{M-1}``, ``quaternion_w`` ... (``KEY_INDEX`` or
    ``KEY_AXIS``), one row per control tick, regrouped into the NPZ layout. Returns the
    arrays and each data row's line in the file (blank lines are skipped)."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            lines = [(n, row) for n, row in enumerate(csv.reader(f), start=1) if row]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"{path}: not a readable CSV file ({first_line(e)})") from None
    if len(lines) < 3:
        raise InputError(f"{path}: expected a header row and at least 2 data rows")
    header = [h.strip() for h in lines[0][1]]
    if len(header) == 1 and ";" in header[0]:
        raise InputError(f"{path}: the header is one column holding ';': columns must be "
                         "separated by commas")  # fmt: skip
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(f"{path}: column {dup[0]!r} appears more than once")
    data = np.full((len(lines) - 1, len(header)), np.nan)
    for r, (n, row) in enumerate(lines[1:]):
        if len(row) != len(header):
            raise InputError(f"{path}:{n}: {len(row)} fields, the header has {len(header)}")
        for c, v in enumerate(row):
            try:
                data[r, c] = float(v)
            except ValueError:
                raise InputError(
                    f"{path}:{n}: column {header[c]!r}: {v!r} is not a number"
                ) from None
    groups: dict[str, dict[str, int]] = {}
    for c, h in enumerate(header):
        if h in _SCALARS:
            groups.setdefault(h, {})[""] = c
            continue
        key, _, part = h.rpartition("_")
        axes = _COMPONENTS.get(key)
        index = part.isdigit() and str(int(part)) == part
        if key not in UNITREE_KEYS or key in _SCALARS or not (part in axes if axes else index):
            raise InputError(
                f"{path}: column {h!r}: expected time, cmd_time, base_time or KEY_INDEX / "
                f"KEY_AXIS (q_0, quaternion_w, ...) with KEY one of "
                + ", ".join(k for k in UNITREE_KEYS if k not in _SCALARS)
            )  # fmt: skip
        groups.setdefault(key, {})[part] = c
    out = {}
    for key, parts in groups.items():
        if key in _SCALARS:
            out[key] = data[:, parts[""]]
            continue
        axes = _COMPONENTS.get(key)
        if axes is not None:
            if set(parts) != set(axes):
                raise InputError(f"{path}: columns {key}_{'/'.join(axes)} expected, found "
                                 + ", ".join(f"{key}_{p}" for p in parts))  # fmt: skip
            order = [parts[a] for a in axes]
        else:
            idx = sorted(int(p) for p in parts)
            if idx != list(range(len(idx))):
                raise InputError(
                    f"{path}: columns {key}_*: motor indices must run 0, 1, ... without gaps; "
                    f"found {', '.join(map(str, idx))}"
                )
            order = [parts[str(i)] for i in idx]
        out[key] = data[:, order]
    return out, np.array([n for n, _ in lines[1:]])


def import_unitree(path: str | os.PathLike[str], target: Target, imap: ImportMap) -> RobotLog:
    """A Unitree low-state log (NPZ arrays or a CSV, keys :data:`UNITREE_KEYS`) as a robot
    log. Motor ``i`` is the model's ``i``-th joint unless the map says otherwise.

    Raises:
        InputError: A missing or malformed array, naming the file and the key.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected a .npz or .csv file")
    if not p.is_file():
        raise InputError(f"{p}: no such file" if not p.exists() else f"{p}: not a regular file")
    where = str(p)
    row = _row
    if p.suffix == ".npz":
        arrays = _load_npz(p)
    else:
        arrays, line_of = _load_csv(p)

        def row(i: int) -> str:
            return f"line {int(line_of[i])}"

    unknown = sorted(set(arrays) - set(UNITREE_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown array {unknown[0]!r}; expected "
                         + ", ".join(UNITREE_KEYS))  # fmt: skip

    def opt(key: str) -> np.ndarray | None:
        if key not in arrays:
            return None
        a = np.asarray(arrays[key])
        if a.dtype.kind not in "iuf":
            raise InputError(f"{where}: {key!r} holds {a.dtype}, expected real numbers")
        return a.astype(np.float64)

    def need(key: str) -> np.ndarray:
        a = opt(key)
        if a is None:
            raise InputError(f"{where}: missing {key!r} ({UNITREE_KEYS[key]})")
        return a

    def shaped(a: np.ndarray, key: str, shape: tuple[int, int]) -> np.ndarray:
        if a.shape != shape:
            raise InputError(f"{where}: {key!r} has shape {a.shape}, expected {shape}")
        return _finite(where, repr(key), a, row)

    t = _increasing(where, "'time'", need("time"), row)
    n = t.size
    q = need("q")
    if q.ndim != 2 or q.shape[0] != n or q.shape[1] == 0:
        raise InputError(f"{where}: 'q' has shape {q.shape}, expected ({n}, motors)")
    motors = q.shape[1]
    col = _columns(where, [str(i) for i in range(motors)], imap, target, motors=True)
    zero = np.zeros((1, motors))

    def per_motor(a: np.ndarray, key: str, rows: int) -> np.ndarray:
        if a.shape != (rows, motors):
            raise InputError(f"{where}: {key!r} has shape {a.shape}, expected ({rows}, {motors})")
        return _finite(where, repr(key), a[:, col], row, target.joint_names)  # Used motors only.

    tc = opt("cmd_time")
    t_cmd = t if tc is None else _increasing(where, "'cmd_time'", tc, row)
    _overlap(where, t, t_cmd, "command times")
    m = t_cmd.size
    cmd = {k: per_motor(need(f"cmd_{k}"), f"cmd_{k}", m) for k in ("q", "kp", "kd")}
    for k, key in (("qd", "cmd_dq"), ("tau", "cmd_tau")):
        a = opt(key)
        cmd[k] = per_motor(np.repeat(zero, m, axis=0) if a is None else a, key, m)
    for k in ("kp", "kd"):
        _gains_check(where, f"'cmd_{k}'", cmd[k], target.joint_names, row)
    imu = None
    quat, gyro, acc = opt("quaternion"), opt("gyroscope"), opt("accelerometer")
    if (quat is None) != (gyro is None) or (acc is not None and quat is None):
        raise InputError(f"{where}: the IMU needs both 'quaternion' and 'gyroscope' (and "
                         "'accelerometer' comes with them)")  # fmt: skip
    if quat is not None and gyro is not None:
        imu = (t, _unit(where, "'quaternion'", shaped(quat, "quaternion", (n, 4)), row),
               shaped(gyro, "gyroscope", (n, 3)),
               None if acc is None else shaped(acc, "accelerometer", (n, 3)))  # fmt: skip
    mocap = None
    pos, bq, tb = opt("base_pos"), opt("base_quat"), opt("base_time")
    if pos is None and (bq is not None or tb is not None):
        raise InputError(f"{where}: motion capture needs 'base_pos' with 'base_quat' (and "
                         "'base_time' comes with them)")  # fmt: skip
    if pos is not None:
        tb = t if tb is None else _increasing(where, "'base_time'", tb, row)
        _overlap(where, t, tb, "motion-capture times")
        if bq is None:
            raise InputError(f"{where}: missing 'base_quat' ({UNITREE_KEYS['base_quat']})")
        bq = shaped(bq, "base_quat", (tb.size, 4))
        mocap = (tb, shaped(pos, "base_pos", (tb.size, 3)), _unit(where, "'base_quat'", bq, row))
    tau = opt("tau_est")
    _check_map_used(where, imap, {str(i) for i in range(motors)}, target, gains=False)
    return _assemble(
        where,
        target,
        t=t,
        q=per_motor(q, "q", n),
        qd=per_motor(need("dq"), "dq", n),
        effort=None if tau is None else per_motor(tau, "tau_est", n),
        t_cmd=t_cmd,
        cmd=cmd,
        imu=imu,
        mocap=mocap,
    )


# --- ROS 2 bags ---------------------------------------------------------------------------


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
                cols[names] = _columns(f"{where}: topic {topic}, message {i}", list(names), imap,
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
        out[f] = _finite(where, f"topic {topic}, field {f}", rows, _message, target.joint_names)
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
    col = _columns(
        f"{where}: topic {topic}", [str(i) for i in range(motors)], imap, target, motors=True
    )
    seen.update(str(i) for i in range(motors))
    out = {}
    for f in fields:
        rows = np.array([[getattr(x, f) for x in getattr(m, attr)] for _, m in msgs], dtype=float)
        out[f] = _finite(where, f"topic {topic}, {attr}[].{f}", rows[:, col], _message,
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
    if not p.exists():
        raise InputError(f"{p}: no such ROS 2 bag")
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        raise InputError(f"{p}: a ROS 2 bag folder holds metadata.yaml; none here")
    if not p.is_dir() and not p.is_file():
        raise InputError(f"{p}: not a regular file or a folder")
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
    t = _increasing(where, f"topic {topics.joint_states}", _times_s(states, t0_ns))
    imu = None
    first = states[0][1]
    if hasattr(first, "motor_state"):
        rows = _motor_rows(where, topics.joint_states, states, imap, target, "motor_state",
                           ("q", "dq", "tau_est"), seen)  # fmt: skip
        q, qd, effort = rows["q"], rows["dq"], rows["tau_est"]
        if hasattr(first, "imu_state"):
            arr: Callable[[str], np.ndarray] = lambda f: _finite(  # noqa: E731
                where, f"topic {topics.joint_states}, imu_state.{f}",
                np.array([getattr(m.imu_state, f) for _, m in states], dtype=float))  # fmt: skip
            imu = (t, _unit(where, f"topic {topics.joint_states}, imu_state.quaternion",
                            arr("quaternion")), arr("gyroscope"), arr("accelerometer"))  # fmt: skip
    elif hasattr(first, "position") and hasattr(first, "name"):
        rows = _joint_rows(where, topics.joint_states, states, imap, target,
                           ("position", "velocity", "effort"), seen)  # fmt: skip
        if rows["position"] is None or rows["velocity"] is None:
            raise InputError(f"{where}: topic {topics.joint_states}: position and velocity "
                             "are both needed")  # fmt: skip
        q, qd, effort = rows["position"], rows["velocity"], rows["effort"]
    else:
        raise InputError(f"{where}: topic {topics.joint_states} is {types[topics.joint_states]}, "
                         "expected sensor_msgs/msg/JointState or a Unitree LowState")  # fmt: skip
    if msgs.get(topics.imu):
        _expect(where, topics.imu, msgs[topics.imu], types, "sensor_msgs/msg/Imu",
                ("orientation", "orientation_covariance", "angular_velocity",
                 "linear_acceleration"))  # fmt: skip
        ims = _sorted_by_stamp(where, topics.imu, msgs[topics.imu])
        ti = _increasing(where, f"topic {topics.imu}", _times_s(ims, t0_ns))
        _overlap(where, t, ti, f"IMU messages on {topics.imu}")

        def xyz(m: Any, f: str, keys: str) -> list[float]:
            v = getattr(m, f)
            return [float(getattr(v, k)) for k in keys]

        cov = np.array([m.orientation_covariance[0] for _, m in ims])
        if np.any(cov < 0):
            raise InputError(f"{where}: topic {topics.imu}, message {int(np.argmax(cov < 0))}: "
                             "orientation_covariance[0] is -1 (no orientation); the IMU's "
                             "orientation is needed")  # fmt: skip
        quat = _unit(where, f"topic {topics.imu}, orientation",
                     _finite(where, f"topic {topics.imu}, orientation",
                             np.array([xyz(m, "orientation", "wxyz") for _, m in ims])))  # fmt: skip
        gyro = _finite(where, f"topic {topics.imu}, angular_velocity",
                       np.array([xyz(m, "angular_velocity", "xyz") for _, m in ims]))  # fmt: skip
        acc = _finite(where, f"topic {topics.imu}, linear_acceleration",
                      np.array([xyz(m, "linear_acceleration", "xyz") for _, m in ims]))  # fmt: skip
        imu = (ti, quat, gyro, acc)
    elif topics.imu and imu is None and target.base == "floating":
        raise InputError(f"{where}: no messages on {topics.imu} (--imu-topic); a floating-base "
                         "log needs the IMU")  # fmt: skip
    cmds = _sorted_by_stamp(where, topics.commands, msgs[topics.commands])
    t_cmd = _increasing(where, f"topic {topics.commands}", _times_s(cmds, t0_ns))
    _overlap(where, t, t_cmd, f"commands on {topics.commands}")
    c0 = cmds[0][1]
    gains_from_map = False
    if hasattr(c0, "motor_cmd"):
        rows = _motor_rows(where, topics.commands, cmds, imap, target, "motor_cmd",
                           ("q", "dq", "tau", "kp", "kd"), seen)  # fmt: skip
        cmd = {"q": rows["q"], "qd": rows["dq"], "tau": rows["tau"], "kp": rows["kp"],
               "kd": rows["kd"]}  # fmt: skip
    elif hasattr(c0, "position") and hasattr(c0, "name"):
        rows = _joint_rows(where, topics.commands, cmds, imap, target,
                           ("position", "velocity", "effort"), seen)  # fmt: skip
        if rows["position"] is None:
            raise InputError(f"{where}: topic {topics.commands}: position targets are empty")
        zero = np.zeros((t_cmd.size, len(target.joint_names)))
        kp, kd = _gains(where, imap, target, t_cmd.size)
        gains_from_map = True
        cmd = {"q": rows["position"], "kp": kp, "kd": kd,
               "qd": zero if rows["velocity"] is None else rows["velocity"],
               "tau": zero if rows["effort"] is None else rows["effort"]}  # fmt: skip
    else:
        raise InputError(f"{where}: topic {topics.commands} is {types[topics.commands]}, "
                         "expected sensor_msgs/msg/JointState or a Unitree LowCmd")  # fmt: skip
    for k in ("kp", "kd"):
        _gains_check(where, f"topic {topics.commands}, {k}", cmd[k], target.joint_names)
    mocap = None
    if topics.base_pose:
        poses = msgs.get(topics.base_pose)
        if not poses:
            raise InputError(f"{where}: no messages on {topics.base_pose} (--base-pose-topic)")
        _expect(where, topics.base_pose, poses, types, "geometry_msgs/msg/PoseStamped", ("pose",))
        poses = _sorted_by_stamp(where, topics.base_pose, poses)
        tb = _increasing(where, f"topic {topics.base_pose}", _times_s(poses, t0_ns))
        _overlap(where, t, tb, f"poses on {topics.base_pose}")
        pos = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                        for _, m in poses])  # fmt: skip
        bq = np.array([[m.pose.orientation.w, m.pose.orientation.x, m.pose.orientation.y,
                        m.pose.orientation.z] for _, m in poses])  # fmt: skip
        mocap = (tb, _finite(where, f"topic {topics.base_pose}, position", pos),
                 _unit(where, f"topic {topics.base_pose}, orientation", bq))  # fmt: skip
    _check_map_used(where, imap, seen, target, gains=gains_from_map)
    return _assemble(where, target, t=t, q=q, qd=qd, effort=effort, t_cmd=t_cmd, cmd=cmd,
                     imu=imu, mocap=mocap)  # fmt: skip


def _expect(
    where: str, topic: str, msgs: list, types: dict[str, str], kind: str, fields: tuple[str, ...]
) -> None:
    """Refuse a topic whose messages lack the fields of ``kind``."""
    if not all(hasattr(msgs[0][1], f) for f in fields):
        raise InputError(f"{where}: topic {topic} is {types.get(topic)}, expected {kind}")


def import_target(
    robot: RobotConfig, base: str, base_pose: np.ndarray | None, imu_site: str = ""
) -> Target:
    """The joints (model order) and IMU site a log of ``robot`` is imported for.

    Raises:
        InputError: A fixed base without ``base_pose``, or no IMU site on the root body.
    """
    from humimic.real2sim.simulate import imu_site_of
    from humimic.sim.joints import JointMap
    from humimic.sim.models import floating_prediction_spec, prediction_spec

    if base == "fixed":
        if base_pose is None:
            raise InputError("--base fixed needs --base-pose X Y Z QW QX QY QZ (the root body "
                             "in the gantry)")  # fmt: skip
        pose = np.asarray(base_pose, dtype=np.float64)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise InputError("--base-pose: expected 7 finite numbers X Y Z QW QX QY QZ")
        norm = float(np.linalg.norm(pose[3:]))
        if not abs(norm - 1.0) <= QUAT_TOL:
            raise InputError(f"--base-pose: the quaternion QW QX QY QZ has length {norm:.3g}, "
                             "expected unit length")  # fmt: skip
        pose[3:] /= norm
        model = prediction_spec(robot, pose).compile()
        names = tuple(model.joint(j).name for j in range(model.njnt))
        return Target(robot=robot.name, joint_names=names, imu_site="", base=base, base_pose=pose)
    if base_pose is not None:
        raise InputError("--base-pose is for a gantry log (--base fixed); a floating base's "
                         "pose comes from the IMU and motion capture")  # fmt: skip
    model = floating_prediction_spec(robot).compile()
    root = int(model.body(robot.root_body).id)
    return Target(robot=robot.name, joint_names=JointMap.of(model).names,
                  imu_site=imu_site_of(model, root, imu_site), base=base,
                  base_pose=np.zeros(7))  # fmt: skip


def import_log(
    path: str | os.PathLike[str], target: Target, imap: ImportMap, topics: RosTopics
) -> RobotLog:
    """A recorder's log as a robot log, by its kind: a ``.npz`` or ``.csv`` of Unitree
    low-state arrays, or a ROS 2 bag (a folder, or its ``.db3`` / ``.mcap`` file).

    Raises:
        InputError: An unknown kind of file, or a malformed one (naming the file and field).
    """
    p = Path(path)
    if p.suffix in (".npz", ".csv"):
        return import_unitree(p, target, imap)
    if p.is_dir() or p.suffix in (".db3", ".mcap"):
        return import_ros2(p, target, imap, topics)
    raise InputError(f"{p}: expected a .npz or .csv of Unitree low-state arrays, or a ROS 2 bag "
                     "(a folder with metadata.yaml, or its .db3 / .mcap file)")  # fmt: skip
