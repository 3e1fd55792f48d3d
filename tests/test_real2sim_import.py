"""``humimic sysid import``: Unitree low-state arrays (NPZ, CSV) and ROS 2 bags into the MCAP
contract.

The source files are written here, by the tests' own code (numpy, the csv module, rosbags'
writer), from a simulated deployment log; the import must give that log back, and the
predictions must read it as they read the log written directly.
"""

from __future__ import annotations

import csv
import json
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archives import zip_bytes
from humimic.cli.main import main
from humimic.real2sim import LogSettings, RobotLog, imports_unitree, simulate_log
from humimic.real2sim.report import load_robot_log
from humimic.robots import get_robot

rosbags = pytest.importorskip(
    "rosbags", reason="rosbags is a dev dependency (pip install -e '.[dev]')"
)
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.msg import get_types_from_msg  # noqa: E402

UNUSED = 6
"""Unitree's G1 low-level messages carry 35 motor slots; the 29-joint G1 uses the first 29."""


@cache
def _log() -> RobotLog:
    return simulate_log(get_robot("g1"), [],
                        LogSettings(duration=3.0, base="floating", mocap=True, seed=4))  # fmt: skip


def _held(log: RobotLog, a: np.ndarray) -> np.ndarray:
    """Commands held at the state times (a recorder that writes one row per tick)."""
    return a[log.command_index(log.t)]


def _slots(a: np.ndarray) -> np.ndarray:
    """29 joints -> 35 motor slots (the unused ones hold zeros)."""
    return np.concatenate([a, np.zeros((a.shape[0], UNUSED))], axis=1)


def _unitree_arrays(log: RobotLog, t_offset: float = 1000.0) -> dict[str, Any]:
    assert log.imu is not None and log.mocap is not None and log.effort is not None
    return {
        "time": log.t + t_offset, "q": _slots(log.q), "dq": _slots(log.qd),
        "tau_est": _slots(log.effort), "quaternion": log.imu.quat_w,
        "gyroscope": log.imu.gyro_b, "accelerometer": log.imu.acc_b,
        "cmd_time": log.t_cmd + t_offset, "cmd_q": _slots(log.cmd_q),
        "cmd_dq": _slots(log.cmd_qd), "cmd_tau": _slots(log.cmd_tau),
        "cmd_kp": _slots(log.kp), "cmd_kd": _slots(log.kd),
        "base_pos": log.mocap.pos_w, "base_quat": log.mocap.quat_w,
    }  # fmt: skip


def _savez(path: Path, arrays: dict[str, Any]) -> None:
    np.savez(path, **arrays)


def _slot_map(tmp_path: Path, extra: str = "") -> Path:
    m = tmp_path / "g1.yaml"
    m.write_text(f"ignore: [{', '.join(str(29 + i) for i in range(UNUSED))}]\n" + extra)
    return m


def _import(tmp_path: Path, src: Path, *flags: str) -> tuple[int, RobotLog | None]:
    out = tmp_path / "imported.mcap"
    rc = main(["sysid", "import", str(src), "--out", str(out), *flags])
    return rc, (load_robot_log(out)[2] if rc == 0 else None)


def _same(a: RobotLog, b: RobotLog, *, commands_held: bool = False) -> None:
    assert b.joint_names == a.joint_names and b.base == "floating"
    np.testing.assert_allclose(b.t, a.t, atol=1e-8)
    for k in ("q", "qd", "effort"):
        np.testing.assert_allclose(getattr(b, k), getattr(a, k), atol=1e-6, err_msg=k)
    for k in ("cmd_q", "cmd_qd", "cmd_tau", "kp", "kd"):
        want = _held(a, getattr(a, k)) if commands_held else getattr(a, k)
        np.testing.assert_allclose(getattr(b, k), want, atol=1e-6, err_msg=k)
    assert a.imu is not None and b.imu is not None and b.imu.site == a.imu.site
    np.testing.assert_allclose(b.imu.t, a.imu.t, atol=1e-8)
    np.testing.assert_allclose(b.imu.quat_w, a.imu.quat_w, atol=1e-6)
    np.testing.assert_allclose(b.imu.gyro_b, a.imu.gyro_b, atol=1e-6)
    assert b.imu.acc_b is not None and a.imu.acc_b is not None
    np.testing.assert_allclose(b.imu.acc_b, a.imu.acc_b, atol=1e-6)
    assert a.mocap is not None and b.mocap is not None
    np.testing.assert_allclose(b.mocap.pos_w, a.mocap.pos_w, atol=1e-6)
    np.testing.assert_allclose(b.mocap.quat_w, a.mocap.quat_w, atol=1e-6)


def test_a_unitree_npz_with_35_motor_slots_imports_and_predicts(tmp_path: Path) -> None:
    src = tmp_path / "lowstate.npz"
    _savez(src, _unitree_arrays(_log()))
    rc, back = _import(tmp_path, src, "--map", str(_slot_map(tmp_path)))
    assert rc == 0 and back is not None
    _same(_log(), back)
    report = tmp_path / "r.json"
    assert (
        main(["sysid", "residual", str(tmp_path / "imported.mcap"), "--report", str(report)]) == 0
    )
    # The nominal model predicts its own clean log: 1.7-2.1 mrad in test_real2sim_floating.
    assert json.loads(report.read_text())["error_nominal"]["kstep_rmse_rad"] < 0.004


def test_a_unitree_csv_with_one_row_per_tick_imports(tmp_path: Path) -> None:
    log = _log()
    arrays = _unitree_arrays(log)
    arrays.pop("cmd_time")
    for k in ("cmd_q", "cmd_dq", "cmd_tau", "cmd_kp", "cmd_kd"):
        arrays[k] = _held(log, arrays[k])
    header: list[str] = []
    cols: list[np.ndarray] = []
    for k, a in reversed(list(arrays.items())):  # Any column order.
        if a.ndim == 1:
            header.append(k)
            cols.append(a)
            continue
        axes = {"quaternion": "wxyz", "base_quat": "wxyz"}.get(k, "xyz" if a.shape[1] == 3 else "")
        for i in range(a.shape[1]):
            header.append(f"{k}_{axes[i] if axes else i}")
            cols.append(a[:, i])
    src = tmp_path / "lowstate.csv"
    with src.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(np.stack(cols, axis=1).tolist())
    rc, back = _import(tmp_path, src, "--map", str(_slot_map(tmp_path)))
    assert rc == 0 and back is not None
    _same(log, back, commands_held=True)


def _stamp(store, ns: int):
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(store, ns: int):
    return store.types["std_msgs/msg/Header"](stamp=_stamp(store, ns), frame_id="")


def _ros_bag(path: Path, log: RobotLog, *, names_order: np.ndarray, extra_joint: bool) -> None:
    """A ROS 2 bag as a ROS driver records it: JointState (own name order, maybe a hand
    joint the model lacks), Imu (quaternion x y z w), JointState targets, PoseStamped."""
    assert log.imu is not None and log.mocap is not None and log.effort is not None
    acc = log.imu.acc_b
    assert acc is not None
    store = get_typestore(Stores.ROS2_HUMBLE)
    T: Any = store.types
    t0 = 1_700_000_000 * 10**9
    names = [log.joint_names[j] for j in names_order] + (
        ["left_hand_thumb_0_joint"] if extra_joint else []
    )

    def joint_msg(ns: int, *rows: np.ndarray | None):
        vals = [np.empty(0) if r is None else np.concatenate([r[names_order], [0.0] * extra_joint])
                for r in rows]  # fmt: skip
        return T["sensor_msgs/msg/JointState"](header=_header(store, ns), name=names,
                                               position=vals[0], velocity=vals[1], effort=vals[2])  # fmt: skip

    def vec(v):
        return T["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2])

    with Writer(path, version=9) as w:
        c_js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        c_cmd = w.add_connection("/joint_commands", "sensor_msgs/msg/JointState", typestore=store)
        c_imu = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        c_mc = w.add_connection("/mocap", "geometry_msgs/msg/PoseStamped", typestore=store)
        for i, t in enumerate(log.t_cmd):
            ns = t0 + round(t * 1e9)
            msg = joint_msg(ns, log.cmd_q[i], None, log.cmd_tau[i])  # No velocity targets.
            w.write(c_cmd, ns + 50_000, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
        for i, t in enumerate(log.t):
            ns = t0 + round(t * 1e9)
            msg = joint_msg(ns, log.q[i], log.qd[i], log.effort[i])
            w.write(c_js, ns + 100_000, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            qw, qx, qy, qz = log.imu.quat_w[i]
            imu = T["sensor_msgs/msg/Imu"](
                header=_header(store, t0 + round(log.imu.t[i] * 1e9)),
                orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                orientation_covariance=np.zeros(9), angular_velocity=vec(log.imu.gyro_b[i]),
                angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(acc[i]),
                linear_acceleration_covariance=np.zeros(9))  # fmt: skip
            w.write(c_imu, ns + 120_000, store.serialize_cdr(imu, "sensor_msgs/msg/Imu"))
            p, q = log.mocap.pos_w[i], log.mocap.quat_w[i]
            pose = T["geometry_msgs/msg/PoseStamped"](
                header=_header(store, t0 + round(log.mocap.t[i] * 1e9)),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0])))  # fmt: skip
            w.write(c_mc, ns + 150_000, store.serialize_cdr(pose, "geometry_msgs/msg/PoseStamped"))


def _gains_yaml(log: RobotLog) -> str:
    rows = "".join(f"  {n}: {{kp: {float(log.kp[0, j])!r}, kd: {float(log.kd[0, j])!r}}}\n"
                   for j, n in enumerate(log.joint_names))  # fmt: skip
    return "gains:\n" + rows


def test_a_ros2_bag_of_joint_states_imu_and_mocap_imports(tmp_path: Path) -> None:
    log = _log()
    order = np.random.default_rng(0).permutation(len(log.joint_names))
    bag = tmp_path / "bag"
    _ros_bag(bag, log, names_order=order, extra_joint=True)
    mp = tmp_path / "map.yaml"
    mp.write_text("ignore: [left_hand_thumb_0_joint]\n" + _gains_yaml(log))
    rc, back = _import(tmp_path, bag, "--map", str(mp), "--base-pose-topic", "/mocap")
    assert rc == 0 and back is not None
    _same(log, back)
    # Without the hand joint ignored, the import names it.
    mp.write_text(_gains_yaml(log))
    assert _import(tmp_path, bag, "--map", str(mp), "--base-pose-topic", "/mocap")[0] == 2


LOWSTATE = """
MotorState[] motor_state
ImuState imu_state
uint32 tick
"""
MOTORSTATE = "float32 q\nfloat32 dq\nfloat32 tau_est\nint16 temperature\n"
IMUSTATE = "float32[4] quaternion\nfloat32[3] gyroscope\nfloat32[3] accelerometer\n"
LOWCMD = "MotorCmd[] motor_cmd\n"
MOTORCMD = "uint8 mode\nfloat32 q\nfloat32 dq\nfloat32 tau\nfloat32 kp\nfloat32 kd\n"


def test_a_ros2_bag_of_unitree_lowstate_and_lowcmd_imports(tmp_path: Path) -> None:
    """Unitree's own messages (motors by slot, the IMU inside the low state), stamped by the
    bag's receive time; the bag carries the message definitions."""
    log = _log()
    assert log.imu is not None and log.effort is not None
    store = get_typestore(Stores.EMPTY)
    types = {}
    for name, text in (("MotorState", MOTORSTATE), ("ImuState", IMUSTATE),
                       ("LowState", LOWSTATE), ("MotorCmd", MOTORCMD), ("LowCmd", LOWCMD)):  # fmt: skip
        types |= get_types_from_msg(text, f"unitree_hg/msg/{name}")
    store.register(types)
    T: Any = store.types
    t0 = 1_700_000_000 * 10**9
    bag = tmp_path / "unitree_bag"
    with Writer(bag, version=9) as w:
        c_s = w.add_connection("/lowstate", "unitree_hg/msg/LowState", typestore=store)
        c_c = w.add_connection("/lowcmd", "unitree_hg/msg/LowCmd", typestore=store)
        for i, t in enumerate(log.t_cmd):
            motors = [T["unitree_hg/msg/MotorCmd"](mode=1, q=log.cmd_q[i, j], dq=log.cmd_qd[i, j],
                                                   tau=log.cmd_tau[i, j], kp=log.kp[i, j],
                                                   kd=log.kd[i, j]) for j in range(29)]  # fmt: skip
            motors += [T["unitree_hg/msg/MotorCmd"](mode=0, q=0, dq=0, tau=0, kp=0, kd=0)] * UNUSED
            msg = T["unitree_hg/msg/LowCmd"](motor_cmd=motors)
            w.write(c_c, t0 + round(t * 1e9), store.serialize_cdr(msg, "unitree_hg/msg/LowCmd"))
        for i, t in enumerate(log.t):
            motors = [T["unitree_hg/msg/MotorState"](q=log.q[i, j], dq=log.qd[i, j],
                                                     tau_est=log.effort[i, j], temperature=30)
                      for j in range(29)]  # fmt: skip
            motors += [T["unitree_hg/msg/MotorState"](q=0, dq=0, tau_est=0, temperature=0)] * UNUSED
            imu = T["unitree_hg/msg/ImuState"](
                quaternion=log.imu.quat_w[i].astype(np.float32),
                gyroscope=log.imu.gyro_b[i].astype(np.float32),
                accelerometer=np.asarray(log.imu.acc_b)[i].astype(np.float32))  # fmt: skip
            msg = T["unitree_hg/msg/LowState"](motor_state=motors, imu_state=imu, tick=i)
            w.write(c_s, t0 + round(t * 1e9), store.serialize_cdr(msg, "unitree_hg/msg/LowState"))
    rc, back = _import(tmp_path, bag, "--map", str(_slot_map(tmp_path)), "--states-topic",
                       "/lowstate", "--commands-topic", "/lowcmd", "--imu-topic", "")  # fmt: skip
    assert rc == 0 and back is not None
    assert back.imu is not None and back.imu.acc_b is not None and back.mocap is None
    np.testing.assert_allclose(back.t, log.t, atol=1e-8)
    np.testing.assert_allclose(back.t_cmd, log.t_cmd, atol=1e-8)
    for k in ("q", "qd", "effort", "cmd_q", "kp", "kd"):  # float32 on the wire.
        np.testing.assert_allclose(getattr(back, k), getattr(log, k), atol=2e-5 * max(
            1.0, float(np.abs(getattr(log, k)).max())), err_msg=k)  # fmt: skip
    np.testing.assert_allclose(back.imu.quat_w, log.imu.quat_w, atol=1e-6)


def test_a_gantry_log_imports_with_its_base_pose(tmp_path: Path) -> None:
    arrays = _unitree_arrays(_log())
    for k in ("quaternion", "gyroscope", "accelerometer", "base_pos", "base_quat"):
        arrays.pop(k)
    src = tmp_path / "gantry.npz"
    _savez(src, arrays)
    mp = str(_slot_map(tmp_path))
    out = tmp_path / "imported.mcap"
    pose = ["0", "0", "1.2", "1", "0", "0", "0"]
    assert main(["sysid", "import", str(src), "--out", str(out), "--map", mp, "--base", "fixed",
                 "--base-pose", *pose]) == 0  # fmt: skip
    _, model, back = load_robot_log(out)
    assert back.base == "fixed" and back.imu is None and model.nq == len(back.joint_names)
    np.testing.assert_allclose(back.base_pose, [0, 0, 1.2, 1, 0, 0, 0])
    # Without an IMU, a floating base is refused.
    assert main(["sysid", "import", str(src), "--out", str(out), "--map", mp]) == 2


def _broken(tmp_path: Path, edit) -> Path:
    arrays = _unitree_arrays(_log())
    edit(arrays)
    src = tmp_path / "broken.npz"
    _savez(src, arrays)
    return src


def _set(key: str, row: int, col: int, value: float):
    def edit(a: dict[str, np.ndarray]) -> None:
        a[key] = a[key].copy()
        a[key][row, col] = value

    return edit


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda a: a.pop("cmd_kp"), ["'cmd_kp'", "missing"]),
        (_set("q", 5, 3, np.nan), ["'q'", "row 5", "not finite"]),
        (_set("cmd_kd", 7, 2, -1.0), ["'cmd_kd'", "row 7", "left_hip_yaw_joint"]),
        (_set("quaternion", 9, 0, 3.0), ["'quaternion'", "row 9", "unit length"]),
        (lambda a: a.__setitem__("time", a["time"][::-1].copy()), ["'time'", "does not increase"]),
        (lambda a: a.__setitem__("dq", a["dq"][:, :20]), ["'dq'", "shape"]),
        (lambda a: a.__setitem__("temperature", a["q"]), ["unknown array", "'temperature'"]),
        (lambda a: a.__setitem__("gyroscope", a["gyroscope"][:-1]), ["'gyroscope'", "shape"]),
        (lambda a: a.__setitem__("q", a["q"] + 1j), ["'q'", "complex", "real numbers"]),
        (lambda a: a.__setitem__("time", a["time"] * 1e9), ["'time'", "spans", "seconds"]),
        (lambda a: a.pop("base_pos"), ["needs 'base_pos'"]),
        (lambda a: a.__setitem__("cmd_time", a["cmd_time"] + 1e3), ["do not overlap"]),
        (_set("q", 4, 3, np.inf), ["'q'", "row 4", "(left_knee_joint)", "not finite"]),
    ],
)
def test_a_broken_unitree_log_exits_2_naming_the_field(tmp_path: Path, capsys, edit, words) -> None:
    src = _broken(tmp_path, edit)
    assert _import(tmp_path, src, "--map", str(_slot_map(tmp_path)))[0] == 2
    err = capsys.readouterr().err
    assert str(src) in err and all(w in err for w in words), err
    assert not (tmp_path / "imported.mcap").exists()


def test_a_nan_in_an_ignored_motor_slot_is_not_read(tmp_path: Path) -> None:
    src = _broken(tmp_path, _set("cmd_kd", 2, 30, np.nan))
    assert _import(tmp_path, src, "--map", str(_slot_map(tmp_path)))[0] == 0


def test_a_corrupt_npz_exits_2(tmp_path: Path, capsys) -> None:
    src = _broken(tmp_path, lambda a: None)
    data = src.read_bytes()
    src.write_bytes(data[: len(data) // 2])
    assert _import(tmp_path, src)[0] == 2
    assert "not a readable .npz archive" in capsys.readouterr().err
    src.write_text("time,q_0\n")
    assert _import(tmp_path, src)[0] == 2
    assert "not a zip archive" in capsys.readouterr().err


def test_an_npz_whose_header_claims_a_huge_array_exits_2_before_allocating(
    tmp_path: Path, capsys
) -> None:
    """A header that claims shape (1e10, 36) of float64 (2.9 TB): numpy allocated it and
    died with a MemoryError traceback."""
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (10000000000, 36), }"
    header += " " * (117 - len(header)) + "\n"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + b"\0" * 64
    src = tmp_path / "huge.npz"
    src.write_bytes(zip_bytes({"q.npy": npy}))
    assert _import(tmp_path, src)[0] == 2
    err = capsys.readouterr().err
    assert str(src) in err and "'q'" in err and "limit" in err, err
    assert not (tmp_path / "imported.mcap").exists()


def test_an_npz_bomb_is_refused_from_its_directory_before_it_is_unpacked(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """A deflated member that unpacks to more than the cap (here lowered to 1 MiB, so that
    the test stays small; the shipped cap is 4 GiB) is refused from the sizes the zip
    directory declares: ``np.load`` unpacked all of it first (6 GB for a 5.76 GB member)."""
    monkeypatch.setattr(imports_unitree, "MAX_LOG_ARRAY_BYTES", 1 << 20)
    src = tmp_path / "bomb.npz"
    np.savez_compressed(src, q=np.zeros((2 << 20) // 8))
    assert src.stat().st_size < 64 << 10
    assert _import(tmp_path, src)[0] == 2
    err = capsys.readouterr().err
    assert str(src) in err and "declares" in err and "1 MiB limit" in err, err
    assert not (tmp_path / "imported.mcap").exists()


def test_unmapped_motor_slots_and_bad_maps_exit_2(tmp_path: Path, capsys) -> None:
    src = _broken(tmp_path, lambda a: None)
    assert _import(tmp_path, src)[0] == 2
    assert "motor 29 has no joint" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("joint: {}\n")
    assert _import(tmp_path, src, "--map", str(bad))[0] == 2
    assert "unknown key 'joint'" in capsys.readouterr().err
    # Two motors filling one joint.
    dup = _slot_map(tmp_path, "joints: {'1': left_hip_pitch_joint}\n")
    assert _import(tmp_path, src, "--map", str(dup))[0] == 2
    assert "filled by both motor 0 and motor 1" in capsys.readouterr().err
    # Map entries that name nothing are refused, not ignored: a typo would pass in silence.
    for extra, words in (("joints: {'77': left_knee_joint}\n", "names '77'"),
                         ("gains: {'*': {kp: 1, kd: 1}}\n", "carry their own kp and kd"),
                         ("gains: [1, 2]\n", "gains must map")):  # fmt: skip
        assert _import(tmp_path, src, "--map", str(_slot_map(tmp_path, extra)))[0] == 2
        assert words in capsys.readouterr().err
    # The output never overwrites the input (a ROS 2 bag stored as one .mcap file).
    bag = tmp_path / "bag.mcap"
    bag.write_bytes(b"not touched")
    assert main(["sysid", "import", str(bag), "--out", str(bag)]) == 2
    assert "would overwrite" in capsys.readouterr().err and bag.read_bytes() == b"not touched"


def test_a_ros2_bag_without_its_command_topic_or_gains_exits_2(tmp_path: Path, capsys) -> None:
    log = _log()
    bag = tmp_path / "bag"
    _ros_bag(bag, log, names_order=np.arange(len(log.joint_names)), extra_joint=False)
    mp = tmp_path / "map.yaml"
    mp.write_text(_gains_yaml(log))
    # A topic of another type where the IMU or the poses should be; an output in the bag.
    assert _import(tmp_path, bag, "--map", str(mp), "--imu-topic", "/joint_commands")[0] == 2
    assert "topic /joint_commands is sensor_msgs/msg/JointState, expected sensor_msgs/msg/Imu" in (
        capsys.readouterr().err
    )
    assert _import(tmp_path, bag, "--map", str(mp), "--base-pose-topic", "/imu")[0] == 2
    assert "expected geometry_msgs/msg/PoseStamped" in capsys.readouterr().err
    inside = bag / "out.mcap"
    assert main(["sysid", "import", str(bag), "--out", str(inside), "--map", str(mp)]) == 2
    assert "inside the bag folder" in capsys.readouterr().err and not inside.exists()
    assert _import(tmp_path, bag, "--commands-topic", "/cmd")[0] == 2
    err = capsys.readouterr().err
    assert "no messages on /cmd (--commands-topic)" in err and "/joint_commands" in err
    assert _import(tmp_path, bag)[0] == 2
    assert "carries no gains" in capsys.readouterr().err
    assert _import(tmp_path, tmp_path / "nothing.txt")[0] == 2
    assert "expected a .npz or .csv" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("time,q_0\n0,1\n0.1,x\n", [":3:", "column 'q_0'", "'x' is not a number"]),
        ("time,q_0,q_2\n0,1,1\n0.1,1,1\n", ["q_*", "without gaps", "found 0, 2"]),
        ("time,q_0\n0,1\n0.1\n", [":3:", "1 fields, the header has 2"]),
        ("time,quaternion_w,quaternion_x\n0,1,0\n0.1,1,0\n", ["quaternion_w/x/y/z expected"]),
        ("time,speed_0\n0,1\n0.1,1\n", ["column 'speed_0'"]),
        ("time,q_00\n0,1\n0.1,1\n", ["column 'q_00'"]),
        ("time_0,q_0\n0,1\n0.1,1\n", ["column 'time_0'"]),
        ("time,q_0,q_0\n0,1,1\n0.1,1,1\n", ["column 'q_0' appears more than once"]),
        ("time;q_0\n0;1\n0.1;1\n", ["separated by commas"]),
        ("time,q_0\n0,1\n\nnan,1\n0.2,1\n", ["'time', line 4", "not finite"]),
    ],
)
def test_a_broken_csv_exits_2_naming_the_line_or_column(
    tmp_path: Path, capsys, text: str, words: list[str]
) -> None:
    src = tmp_path / "broken.csv"
    src.write_text(text)
    assert _import(tmp_path, src)[0] == 2
    err = capsys.readouterr().err
    assert str(src) in err and all(w in err for w in words), err


def test_a_csv_from_a_spreadsheet_imports(tmp_path: Path) -> None:
    """A byte-order mark and blank lines (as spreadsheets write them) are read past."""
    log = _log()
    arrays = _unitree_arrays(log)
    n = 20
    header = ["time"] + [f"{k}_{i}" for k in ("q", "dq", "cmd_q", "cmd_kp", "cmd_kd")
                         for i in range(35)]  # fmt: skip
    rows = [[arrays["time"][r]] + [arrays[k][r if k in ("q", "dq") else log.command_index(log.t)[r], i]
                                   for k in ("q", "dq", "cmd_q", "cmd_kp", "cmd_kd")
                                   for i in range(35)] for r in range(n)]  # fmt: skip
    src = tmp_path / "sheet.csv"
    text = (
        ",".join(header) + "\r\n" + "\r\n".join(",".join(repr(float(v)) for v in r) for r in rows)
    )
    src.write_text("\ufeff" + text + "\r\n\r\n", encoding="utf-8")
    rc, back = _import(tmp_path, src, "--map", str(_slot_map(tmp_path)), "--base", "fixed",
                       "--base-pose", "0", "0", "1", "1", "0", "0", "0")  # fmt: skip
    assert rc == 0 and back is not None
    np.testing.assert_allclose(back.q, log.q[:n], atol=1e-9)


def test_a_bad_base_pose_exits_2(tmp_path: Path, capsys) -> None:
    src = _broken(tmp_path, lambda a: None)
    mp = str(_slot_map(tmp_path))
    assert _import(tmp_path, src, "--map", mp, "--base", "fixed", "--base-pose",
                   "0", "0", "1", "0", "0", "0", "0")[0] == 2  # fmt: skip
    assert "length 0" in capsys.readouterr().err
    assert (
        _import(tmp_path, src, "--map", mp, "--base-pose", "0", "0", "1", "1", "0", "0", "0")[0]
        == 2
    )
    assert "--base-pose is for a gantry log" in capsys.readouterr().err
