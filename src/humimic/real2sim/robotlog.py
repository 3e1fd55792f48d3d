"""Robot logs: joint states and drive commands over time, read from and written to MCAP.

The schema is fixed by issue 4 (see docs/viewer.md for the topics): a metadata record
``robot`` (``name``, ``base`` = ``fixed`` or ``floating``, ``base_pose`` for a fixed base),
``/joint_states`` (position, velocity, optional effort) and ``/joint_commands`` (position,
velocity, effort, kp, kd), each stamped; MCAP log time is the time base. Joints are matched to
the model by name.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from humimic.mcap_io import McapFormatError, McapWriter, read_mcap, stamp


@dataclass(frozen=True, kw_only=True)
class RobotLog:
    """A robot log in the model's joint order. Times in seconds from the first message.

    Attributes:
        robot: Registry name. base: ``fixed`` or ``floating``.
        base_pose: For a fixed base: x y z qw qx qy qz of the root body. Shape: (7,).
        joint_names: Shape: (J,).
        t: State times. Shape: (N,). q, qd: Shape: (N, J). effort: Shape: (N, J) or None.
        t_cmd: Command times. Shape: (M,). Commands (M, J): cmd_q, cmd_qd, cmd_tau, kp, kd.
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

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def command_index(self, times: np.ndarray) -> np.ndarray:
        """Index of the command in force at each time (the drive holds the last one)."""
        return np.clip(np.searchsorted(self.t_cmd, times, side="right") - 1, 0, len(self.t_cmd) - 1)


def write_robot_log(log: RobotLog, path: str | os.PathLike[str]) -> Path:
    """Write a robot log as MCAP (atomically)."""
    names = list(log.joint_names)
    t0 = min(log.t[0], log.t_cmd[0])
    with McapWriter(path) as w:
        w.add_metadata(
            "robot",
            {
                "name": log.robot,
                "base": log.base,
                "base_pose": " ".join(repr(float(x)) for x in log.base_pose),
            },
        )
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


def _matrix(
    log_path: Path, topic: str, msgs: list, field: str, names: tuple[str, ...]
) -> np.ndarray:
    out = np.zeros((len(msgs), len(names)))
    first = msgs[0][1]["name"]
    missing = [n for n in names if n not in first]
    if missing:
        raise McapFormatError(f"{log_path}: topic {topic}: field name lacks the joints {missing}")
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
    return out


def read_robot_log(path: str | os.PathLike[str], joint_names: tuple[str, ...]) -> RobotLog:
    """Read a robot log, in the order of ``joint_names`` (the model's).

    Raises:
        InputError / McapFormatError: Missing file, topics, metadata or joints, naming them.
    """
    log = read_mcap(path, topics=["/joint_states", "/joint_commands"],
                    require=["/joint_states", "/joint_commands"])  # fmt: skip
    meta = log.meta("robot")
    base = meta.get("base", "")
    if base not in ("fixed", "floating"):
        raise McapFormatError(
            f"{log.path}: metadata robot.base is {base!r}, expected fixed or floating"
        )
    try:
        base_pose = np.array([float(x) for x in meta.get("base_pose", "0 0 0 1 0 0 0").split()])
    except ValueError:
        raise McapFormatError(f"{log.path}: metadata robot.base_pose is not 7 numbers") from None
    if base_pose.shape != (7,):
        raise McapFormatError(f"{log.path}: metadata robot.base_pose must hold 7 numbers")
    states = log.topic("/joint_states")
    cmds = log.topic("/joint_commands")
    t_all0 = min(states[0][0], cmds[0][0])
    t = (np.array([ts for ts, _ in states], dtype=np.float64) - t_all0) * 1e-9
    t_cmd = (np.array([ts for ts, _ in cmds], dtype=np.float64) - t_all0) * 1e-9
    has_effort = all("effort" in m for _, m in states)
    zero = np.zeros((len(cmds), len(joint_names)))

    def cmd(field: str) -> np.ndarray:
        return (
            _matrix(log.path, "/joint_commands", cmds, field, joint_names)
            if all(field in m for _, m in cmds)
            else zero.copy()
        )

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
        kp=_matrix(log.path, "/joint_commands", cmds, "kp", joint_names),
        kd=_matrix(log.path, "/joint_commands", cmds, "kd", joint_names),
    )
