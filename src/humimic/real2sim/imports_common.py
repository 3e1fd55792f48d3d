"""What every recorder's import shares (:mod:`humimic.real2sim.imports`): the import map and
the target robot, the joint mapping, the checks that name a bad value's file, field and row, and
the robot log assembled from model-ordered arrays. The format readers
(:mod:`~humimic.real2sim.imports_unitree`, :mod:`~humimic.real2sim.imports_ros2`) build on them.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from humimic.errors import InputError
from humimic.io import read_yaml
from humimic.real2sim.robotlog import QUAT_TOL, ImuLog, PoseTrack, RobotLog


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


def source_columns(
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


def row_label(i: int) -> str:
    """How messages name row ``i`` of an array (a CSV names its file's line instead)."""
    return f"row {i}"


def check_finite(
    where: str, name: str, a: np.ndarray, row: Callable[[int], str] = row_label,
    columns: tuple[str, ...] = (),
) -> np.ndarray:  # fmt: skip
    """``a``, refused when a value is not finite (naming the row, and the column's joint)."""
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        col = f" ({columns[int(bad[0][1])]})" if columns and a.ndim == 2 else ""
        raise InputError(f"{where}: {name}, {row(int(bad[0][0]))}{col}: a value is not finite")
    return a


def check_increasing(
    where: str, name: str, t: np.ndarray, row: Callable[[int], str] = row_label
) -> np.ndarray:
    """``t``, refused unless a finite, strictly increasing 1-D array of at least 2 times that
    spans at most :data:`MAX_SPAN` seconds (naming the row where it fails)."""
    if t.ndim != 1 or t.size < 2:
        raise InputError(f"{where}: {name} has shape {t.shape}, expected a 1-D array of at "
                         "least 2 times")  # fmt: skip
    check_finite(where, name, t, row)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{where}: {name}, {row(i)}: time {t[i]:.6f} does not increase "
                         f"({row(i - 1)}: {t[i - 1]:.6f})")  # fmt: skip
    if t[-1] - t[0] > MAX_SPAN:
        raise InputError(f"{where}: {name} spans {t[-1] - t[0]:.4g} s; expected seconds (a "
                         "clock in milli- or nanoseconds must be converted)")  # fmt: skip
    return t


def unit_quaternions(
    where: str, name: str, q: np.ndarray, row: Callable[[int], str] = row_label
) -> np.ndarray:
    """``q`` (rows of w x y z) normalized, refused when a row's length is off unit by more
    than :data:`~humimic.real2sim.robotlog.QUAT_TOL` (a recorder's x y z w order, or no
    orientation at all)."""
    n = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(n - 1.0) <= QUAT_TOL))
    if bad.size:
        raise InputError(f"{where}: {name}, {row(int(bad[0]))}: quaternion of length "
                         f"{n[bad[0]]:.3f}, expected unit length (w x y z)")  # fmt: skip
    return q / n[:, None]


def check_gains(
    where: str,
    name: str,
    g: np.ndarray,
    joints: tuple[str, ...],
    row: Callable[[int], str] = row_label,
) -> np.ndarray:
    """``g`` (gains, one column per joint of ``joints``), refused when one is negative."""
    neg = np.argwhere(g < 0)
    if neg.size:
        i, j = (int(x) for x in neg[0])
        raise InputError(f"{where}: {name}, {row(i)}: gain of {joints[j]!r} is {g[i, j]:g}, "
                         "expected >= 0")  # fmt: skip
    return g


def check_overlap(where: str, t: np.ndarray, other: np.ndarray, what: str) -> None:
    """Refuse a stream that does not overlap the joint states in time."""
    if other[0] > t[-1] or other[-1] < t[0]:
        raise InputError(f"{where}: the {what} ({other[0]:.3f}-{other[-1]:.3f} s) do not overlap "
                         f"the joint states ({t[0]:.3f}-{t[-1]:.3f} s): one clock for every "
                         "stream is expected")  # fmt: skip


def check_map_used(
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


def assemble_log(
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
