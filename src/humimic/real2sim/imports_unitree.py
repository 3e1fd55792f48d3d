"""Unitree low-state arrays (NPZ or CSV, the fields of unitree_sdk2's ``LowState_`` and
``LowCmd_``) as a robot log (:mod:`humimic.real2sim.imports`).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from humimic.errors import InputError, first_line
from humimic.npyio import read_npz_members
from humimic.real2sim.imports_common import (
    ImportMap,
    Target,
    assemble_log,
    check_finite,
    check_gains,
    check_increasing,
    check_map_used,
    check_overlap,
    row_label,
    source_columns,
    unit_quaternions,
)
from humimic.real2sim.robotlog import RobotLog

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


@dataclass(frozen=True, kw_only=True)
class _Arrays:
    """A Unitree log's arrays, read through checks that name the file, the key and the row.

    Attributes:
        where: The file, for messages.
        arrays: Key (of :data:`UNITREE_KEYS`) -> array, as read.
        row: A row's name in messages (``row 3``; a CSV's ``line 5``, counting its header).
    """

    where: str
    arrays: dict[str, np.ndarray]
    row: Callable[[int], str]

    def opt(self, key: str) -> np.ndarray | None:
        """The array ``key`` in float64, or ``None`` when the log lacks it; refused unless it
        holds real numbers."""
        if key not in self.arrays:
            return None
        a = np.asarray(self.arrays[key])
        if a.dtype.kind not in "iuf":
            raise InputError(f"{self.where}: {key!r} holds {a.dtype}, expected real numbers")
        return a.astype(np.float64)

    def need(self, key: str) -> np.ndarray:
        """The array ``key`` in float64, refused when the log lacks it."""
        a = self.opt(key)
        if a is None:
            raise InputError(f"{self.where}: missing {key!r} ({UNITREE_KEYS[key]})")
        return a

    def shaped(self, a: np.ndarray, key: str, shape: tuple[int, int]) -> np.ndarray:
        """``a`` (the array ``key``), refused unless of ``shape`` and finite."""
        if a.shape != shape:
            raise InputError(f"{self.where}: {key!r} has shape {a.shape}, expected {shape}")
        return check_finite(self.where, repr(key), a, self.row)


@dataclass(frozen=True, kw_only=True)
class _Motors:
    """A log's motor slots and the slot that fills each model joint.

    Attributes:
        src: The log's arrays. count: Motor slots per row.
        col: The slot of each model joint. Shape: (J,).
        joint_names: The model's joints, in model order.
    """

    src: _Arrays
    count: int
    col: np.ndarray
    joint_names: tuple[str, ...]

    def take(self, a: np.ndarray, key: str, rows: int) -> np.ndarray:
        """The model joints' columns of ``a`` (the array ``key``), refused unless it has
        ``rows`` rows of every slot; only the used slots must be finite (an unused one may
        hold anything)."""
        where = self.src.where
        if a.shape != (rows, self.count):
            raise InputError(f"{where}: {key!r} has shape {a.shape}, expected ({rows}, "
                             f"{self.count})")  # fmt: skip
        return check_finite(where, repr(key), a[:, self.col], self.src.row, self.joint_names)


def _read_arrays(path: str | os.PathLike[str]) -> _Arrays:
    """The arrays of a ``.npz`` or ``.csv`` log, refused when the path is not a file or an
    array's key is not one of :data:`UNITREE_KEYS` (a typo would drop a stream in silence)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected a .npz or .csv file")
    if not p.is_file():
        raise InputError(f"{p}: no such file" if not p.exists() else f"{p}: not a regular file")
    where = str(p)
    row = row_label
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
    return _Arrays(where=where, arrays=arrays, row=row)


def _commands(
    src: _Arrays, t: np.ndarray, motors: _Motors
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The command times (the state times without ``cmd_time``) and the model-ordered
    commands: targets and gains required, velocity targets and feedforward torques zero when
    absent."""
    where, row = src.where, src.row
    tc = src.opt("cmd_time")
    t_cmd = t if tc is None else check_increasing(where, "'cmd_time'", tc, row)
    check_overlap(where, t, t_cmd, "command times")
    m = t_cmd.size
    cmd = {k: motors.take(src.need(f"cmd_{k}"), f"cmd_{k}", m) for k in ("q", "kp", "kd")}
    zero = np.zeros((1, motors.count))
    for k, key in (("qd", "cmd_dq"), ("tau", "cmd_tau")):
        a = src.opt(key)
        cmd[k] = motors.take(np.repeat(zero, m, axis=0) if a is None else a, key, m)
    for k in ("kp", "kd"):
        check_gains(where, f"'cmd_{k}'", cmd[k], motors.joint_names, row)
    return t_cmd, cmd


def _imu(
    src: _Arrays, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None:
    """The IMU at the state times (times, quaternion, gyroscope, accelerometer or ``None``),
    or ``None`` without one; orientation and angular velocity come together."""
    where, n = src.where, t.size
    quat, gyro, acc = src.opt("quaternion"), src.opt("gyroscope"), src.opt("accelerometer")
    if (quat is None) != (gyro is None) or (acc is not None and quat is None):
        raise InputError(f"{where}: the IMU needs both 'quaternion' and 'gyroscope' (and "
                         "'accelerometer' comes with them)")  # fmt: skip
    if quat is None or gyro is None:
        return None
    return (t, unit_quaternions(where, "'quaternion'", src.shaped(quat, "quaternion", (n, 4)),
                                src.row),
            src.shaped(gyro, "gyroscope", (n, 3)),
            None if acc is None else src.shaped(acc, "accelerometer", (n, 3)))  # fmt: skip


def _mocap(src: _Arrays, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Motion capture's root pose (times, position, quaternion), or ``None`` without it; its
    times are the state times unless ``base_time`` gives them."""
    where, row = src.where, src.row
    pos, bq, tb = src.opt("base_pos"), src.opt("base_quat"), src.opt("base_time")
    if pos is None and (bq is not None or tb is not None):
        raise InputError(f"{where}: motion capture needs 'base_pos' with 'base_quat' (and "
                         "'base_time' comes with them)")  # fmt: skip
    if pos is None:
        return None
    tb = t if tb is None else check_increasing(where, "'base_time'", tb, row)
    check_overlap(where, t, tb, "motion-capture times")
    if bq is None:
        raise InputError(f"{where}: missing 'base_quat' ({UNITREE_KEYS['base_quat']})")
    bq = src.shaped(bq, "base_quat", (tb.size, 4))
    return (tb, src.shaped(pos, "base_pos", (tb.size, 3)),
            unit_quaternions(where, "'base_quat'", bq, row))  # fmt: skip


def import_unitree(path: str | os.PathLike[str], target: Target, imap: ImportMap) -> RobotLog:
    """A Unitree low-state log (NPZ arrays or a CSV, keys :data:`UNITREE_KEYS`) as a robot
    log. Motor ``i`` is the model's ``i``-th joint unless the map says otherwise.

    Raises:
        InputError: A missing or malformed array, naming the file and the key.
    """
    src = _read_arrays(path)
    where = src.where
    t = check_increasing(where, "'time'", src.need("time"), src.row)
    n = t.size
    q = src.need("q")
    if q.ndim != 2 or q.shape[0] != n or q.shape[1] == 0:
        raise InputError(f"{where}: 'q' has shape {q.shape}, expected ({n}, motors)")
    slots = [str(i) for i in range(q.shape[1])]
    col = source_columns(where, slots, imap, target, motors=True)
    motors = _Motors(src=src, count=q.shape[1], col=col, joint_names=target.joint_names)
    t_cmd, cmd = _commands(src, t, motors)
    imu = _imu(src, t)
    mocap = _mocap(src, t)
    tau = src.opt("tau_est")
    check_map_used(where, imap, set(slots), target, gains=False)
    return assemble_log(
        where,
        target,
        t=t,
        q=motors.take(q, "q", n),
        qd=motors.take(src.need("dq"), "dq", n),
        effort=None if tau is None else motors.take(tau, "tau_est", n),
        t_cmd=t_cmd,
        cmd=cmd,
        imu=imu,
        mocap=mocap,
    )
