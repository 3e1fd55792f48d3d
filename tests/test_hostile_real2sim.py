"""Hostile input in real2sim: broken robot logs, injections and physics files of the wrong
sign, logs and horizons the residual and the diagnosis cannot use.

Broken logs are made from a clean simulated one by rewriting one message with the plain
``mcap`` package (never through the code under test). Every refusal exits 2 through the CLI,
names the file (topic, message, field) or the flag, and writes nothing.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from humimic.cli.main import main
from humimic.errors import InputError
from humimic.sim.effects import Injection, apply_to_spec, parse_injection
from humimic.sim.physics import load_physics

# An edit gets (topic, index on the topic, log time [ns], message) and returns the new
# (log time, message), or None to drop the message.
Edit = Callable[[str, int, int, dict], tuple[int, dict] | None]


def _keep(topic: str, i: int, t: int, m: dict) -> tuple[int, dict]:
    return t, m


def rewrite(
    src: Path, dst: Path, edit: Edit = _keep, meta: Callable[[dict], dict] | None = None
) -> Path:
    """Copy an MCAP file message by message (in file order), through ``edit`` and ``meta``
    (the ``robot`` metadata record)."""
    with src.open("rb") as f:
        reader = make_reader(f)
        records = list(reader.iter_messages(log_time_order=False))
        metadata = [(r.name, dict(r.metadata)) for r in reader.iter_metadata()]
    counts: dict[str, int] = {}
    with dst.open("wb") as f:
        w = Writer(f)
        w.start(profile="test", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in records:
            assert schema is not None
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    topic=channel.topic,
                    message_encoding=channel.message_encoding,
                    schema_id=schemas[schema.id],
                )
            i = counts.get(channel.topic, 0)
            counts[channel.topic] = i + 1
            out = edit(channel.topic, i, message.log_time, json.loads(message.data))
            if out is None:
                continue
            t, body = out
            w.add_message(channel_id=channels[channel.id], log_time=t, publish_time=t,
                          sequence=message.sequence, data=json.dumps(body).encode())  # fmt: skip
        for name, data in metadata:
            w.add_metadata(name, meta(data) if meta is not None and name == "robot" else data)
        w.finish()
    return dst


@pytest.fixture(scope="module")
def clean_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("logs") / "clean.mcap"
    assert main(["sysid", "simulate", "--duration", "2", "--out", str(path)]) == 0
    return path


def _refused(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> tuple[str, str]:
    """Run ``sysid residual`` and ``sysid diagnose`` on a log; both must exit 2 and write
    nothing. Returns their messages."""
    report = tmp_path / "residual.json"
    out_dir = tmp_path / "diagnosis"
    capsys.readouterr()
    assert main(["sysid", "residual", str(log), "--report", str(report), *extra]) == 2
    residual = capsys.readouterr().err
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out_dir), *extra]) == 2
    diagnose = capsys.readouterr().err
    assert not report.exists()
    assert not out_dir.exists() or not any(out_dir.iterdir())
    for err in (residual, diagnose):
        assert err.startswith("humimic: error: ") and err.count("\n") == 1  # One line.
        assert "Traceback" not in err
    return residual, diagnose


def test_an_unchanged_copy_is_accepted(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The rewriting itself breaks nothing: what the tests below refuse is their one change."""
    copy = rewrite(clean_log, tmp_path / "copy.mcap")
    report = tmp_path / "r.json"
    assert main(["sysid", "residual", str(copy), "--report", str(report)]) == 0
    rmse = json.loads(report.read_text())["error_nominal"]["kstep_rmse_rad"]
    assert 0 < rmse < 2e-3  # Sensor noise: about 0.3 mrad.


# -- 1. Non-finite values and stamps that do not increase ------------------------------------


@pytest.mark.parametrize(
    ("topic", "field", "value"),
    [
        ("/joint_states", "position", math.nan),
        ("/joint_states", "velocity", math.inf),
        ("/joint_states", "effort", -math.inf),
        ("/joint_commands", "position", math.nan),
        ("/joint_commands", "velocity", math.nan),
        ("/joint_commands", "effort", math.inf),
        ("/joint_commands", "kp", math.nan),
        ("/joint_commands", "kd", math.nan),
    ],
)
def test_a_non_finite_value_is_refused(
    clean_log: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    topic: str,
    field: str,
    value: float,
) -> None:
    def edit(tp: str, i: int, t: int, m: dict) -> tuple[int, dict]:
        if tp == topic and i == 7:
            m[field][3] = value
        return t, m

    log = rewrite(clean_log, tmp_path / "nonfinite.mcap", edit)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: topic {topic}, message 7: field {field} of 'left_knee_joint'" in err
        assert "expected a finite number" in err


def _shift(topic: str, shifts: dict[int, tuple[int, int]]) -> Edit:
    """Move messages' log times and header stamps: index -> (log time, stamp) shifts [ns]."""

    def edit(tp: str, i: int, t: int, m: dict) -> tuple[int, dict]:
        if tp == topic and i in shifts:
            dt_log, dt_header = shifts[i]
            st = m["header"]["stamp"]
            ns = st["sec"] * 10**9 + st["nanosec"] + dt_header
            m["header"]["stamp"] = {"sec": ns // 10**9, "nanosec": ns % 10**9}
            t += dt_log
        return t, m

    return edit


@pytest.mark.parametrize(
    ("case", "topic", "expect"),
    [
        # Message 21 logged at message 20's time.
        ("equal log time", "/joint_states", "message 21: log time"),
        ("equal log time", "/joint_commands", "message 21: log time"),
        # Message 20 logged after 21 (the reader sorts by log time: the stamps then go back).
        ("swapped log times", "/joint_states", "message 21: field header.stamp"),
        # The header stamp of message 21 equals message 20's.
        ("equal stamp", "/joint_commands", "message 21: field header.stamp"),
    ],
)
def test_stamps_that_do_not_increase_are_refused(
    clean_log: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    topic: str,
    expect: str,
) -> None:
    period = {"/joint_states": 5_000_000, "/joint_commands": 20_000_000}[topic]
    shifts = {
        "equal log time": {21: (-period, 0)},
        "swapped log times": {20: (period, 0), 21: (-period, 0)},
        "equal stamp": {21: (0, -period)},
    }[case]
    edit = _shift(topic, shifts)
    log = rewrite(clean_log, tmp_path / "stamps.mcap", edit)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: topic {topic}, {expect}" in err and "strictly increasing" in err


def test_a_negative_gain_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def edit(tp: str, i: int, t: int, m: dict) -> tuple[int, dict]:
        if tp == "/joint_commands":
            m["kd"][3] = -m["kd"][3]  # Every message: constant gains, but negative.
        return t, m

    log = rewrite(clean_log, tmp_path / "gain.mcap", edit)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: topic /joint_commands, message 0: field kd of 'left_knee_joint'" in err
        assert "expected a gain >= 0" in err


@pytest.mark.parametrize(
    "pose", ["0 0 1 nan 0 0 0", "0 0 1 0 0 0 0", "0 0 1 1 0 0", "0 0 inf 1 0 0 0"]
)
def test_a_bad_base_pose_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], pose: str
) -> None:
    log = rewrite(clean_log, tmp_path / "pose.mcap", meta=lambda d: {**d, "base_pose": pose})
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: metadata robot.base_pose" in err


def test_a_floating_base_log_keeps_its_placeholder_pose(tmp_path: Path) -> None:
    """Only a fixed base needs a real pose; a floating-base log (e.g. the loop's deployment)
    writes zeros there, and a finite log of that kind reads back."""
    import numpy as np

    from humimic.real2sim import RobotLog, read_robot_log, write_robot_log

    t = np.arange(4) * 0.02
    q = np.linspace(0.0, 0.3, 8).reshape(4, 2)
    zeros = np.zeros_like(q)
    gains = np.full_like(q, 40.0)
    log = RobotLog(robot="g1", base="floating", base_pose=np.zeros(7), joint_names=("a", "b"),
                   t=t, q=q, qd=zeros, effort=None, t_cmd=t, cmd_q=q, cmd_qd=zeros,
                   cmd_tau=zeros, kp=gains, kd=gains)  # fmt: skip
    back = read_robot_log(write_robot_log(log, tmp_path / "f.mcap"), ("a", "b"))
    np.testing.assert_allclose(back.q, q)
    assert back.source == str(tmp_path / "f.mcap")


# -- 2. Injections and physics files of the wrong sign ----------------------------------------


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        ("coulomb_friction:left_knee_joint=-2", ">= 0 N m"),
        ("viscous_damping:left_knee_joint=-0.5", ">= 0 N m s/rad"),
        ("armature:left_knee_joint=-0.01", ">= 0 kg m^2"),
        ("delay:left_knee_joint=-0.01", ">= 0 s"),
        ("delay:left_knee_joint=1e6", "at most 1 s"),
        ("lag:left_knee_joint=-0.02", ">= 0 s"),
        ("torque_limit:left_knee_joint=-5", "> 0 N m"),
        ("torque_limit:left_knee_joint=0", "> 0 N m"),
        ("gain_mismatch:left_knee_joint=0", "> 0 ratio"),
        ("gain_mismatch:left_knee_joint=-0.7", "positive feedback"),
        ("payload_mass:torso_link=-3", ">= 0 kg"),
        ("backlash:left_knee_joint=0", "> 0 rad"),
        ("backlash:left_knee_joint=-0.01", "> 0 rad"),
        ("coulomb_friction:left_knee_joint=nan", "finite"),
        ("encoder_offset:left_knee_joint=inf", "finite"),
    ],
)
def test_an_injection_of_the_wrong_sign_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, expect: str
) -> None:
    out = tmp_path / "log.mcap"
    assert main(["sysid", "simulate", "--duration", "2", "--out", str(out), "--inject",
                 "armature:right_knee_joint=0.01", "--inject", text]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert f"--inject {text!r}:" in err and expect in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "text", ["coulomb_friction:left_knee=2", "encoder_offset:knee=0.1", "payload_mass:torso=1"]
)
def test_an_injection_on_a_joint_the_robot_lacks_names_the_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str
) -> None:
    out = tmp_path / "log.mcap"
    assert main(["sysid", "simulate", "--duration", "2", "--out", str(out), "--inject", text]) == 2
    err = capsys.readouterr().err
    assert f"--inject {text!r}: no " in err and "in the robot" in err
    assert not out.exists()


def test_signed_and_zero_values_are_accepted() -> None:
    """An encoder reads high or low: its offset is signed. Zero adds nothing and is valid for
    amounts (friction, payload, delay...)."""
    assert parse_injection("encoder_offset:left_knee_joint=-0.05").value == -0.05
    for text in ("coulomb_friction:a=0", "payload_mass:b=0", "delay:a=0", "lag:a=0",
                 "gain_mismatch:a=2.5", "delay:a=1"):  # fmt: skip
        parse_injection(text)


def test_apply_to_spec_refuses_an_injection_made_in_code() -> None:
    import mujoco

    spec = mujoco.MjSpec.from_string(
        '<mujoco><worldbody><body name="b"><joint name="j"/><geom size="0.1"/></body>'
        '</worldbody><actuator><position joint="j" kp="10"/></actuator></mujoco>'
    )
    with pytest.raises(InputError, match=r"^armature on j: armature must be >= 0"):
        apply_to_spec(spec, [Injection(effect="armature", targets=("j",), value=-1.0)])
    assert spec.joint("j").armature == 0.0


@pytest.mark.parametrize(
    ("text", "field", "expect"),
    [
        ("floor_friction: -1\n", "floor_friction", "must be >= 0"),
        ("floor_friction: .nan\n", "floor_friction", "expected a finite number"),
        ("armature_scale: -1\n", "armature_scale", "must be positive"),
        ("mass_scale: {torso_link: .inf}\n", "mass_scale.torso_link", "finite number"),
        ("com_offset: {torso_link: [0, .nan, 0]}\n", "com_offset.torso_link", "finite number"),
        ("effects:\n  - armature:left_knee_joint=-0.1\n", "effects[0]", "armature must be >= 0"),
        ("effects:\n  - delay:left_knee_joint=0.01\n  - payload_mass:torso_link=-4\n",
         "effects[1]", "payload_mass must be >= 0"),
        ("effects:\n  - coulomb_friction:left_knee_joint=nan\n", "effects[0]", "finite"),
        ("robot: [g1]\n", "robot", "expected a robot name"),
    ],
)  # fmt: skip
def test_a_physics_file_of_the_wrong_sign_is_refused(
    tmp_path: Path, text: str, field: str, expect: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        load_physics(path)
    assert str(e.value).startswith(f"{path}: {field}") and expect in str(e.value)
    assert path.read_text() == text


def test_a_physics_file_names_itself_when_a_joint_is_missing(tmp_path: Path) -> None:
    from dataclasses import replace

    from humimic.robots import get_robot
    from humimic.robots.model import nominal_spec

    path = tmp_path / "typo.yaml"
    path.write_text("effects:\n  - coulomb_friction:left_knee=2\nkp_scale: {no_joint: 1.1}\n")
    physics = load_physics(path)
    spec, _ = nominal_spec(get_robot("g1"))
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: kp_scale: no actuated"):
        physics.edit(spec)
    where = re.escape(f"{path}: effects[0] 'coulomb_friction:left_knee=2'")
    with pytest.raises(InputError, match=rf"^{where}: no joint 'left_knee' in the robot"):
        replace(physics, kp_scale={}).edit(spec)


def test_train_refuses_a_physics_file_of_the_wrong_sign(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    physics = tmp_path / "worn.yaml"
    physics.write_text("effects:\n  - gain_mismatch:left_knee_joint=-0.7\n")
    motion = tmp_path / "motion.npz"
    motion.write_bytes(b"not read: the physics file is refused first")
    run = tmp_path / "run"
    argv = ["train", "--motion", str(motion), "--out", str(run), "--physics", str(physics)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{physics}: effects[0] 'gain_mismatch:left_knee_joint=-0.7'" in err
    assert "gain_mismatch must be > 0" in err
    assert not run.exists()


def test_diagnose_refuses_an_out_dir_of_other_files(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--out-dir a folder of the user's files: the diagnosis wrote its model, report and plots
    beside them. A folder that holds an earlier diagnosis (report.json) is written again."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine\n")
    assert main(["sysid", "diagnose", str(clean_log), "--out-dir", str(mine)]) == 2
    err = capsys.readouterr().err
    assert f"--out-dir {mine}: holds other files" in err and err.count("\n") == 1, err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


# -- 3. Logs and horizons the residual and the diagnosis cannot use -------------------------


@pytest.mark.parametrize(
    ("horizon", "why"),
    [("0", "expected a positive number of seconds"),
     ("-0.5", "expected a positive number of seconds"),
     ("11", "expected a positive number of seconds, at most 10"),
     ("nan", "must be a finite number"), ("inf", "must be a finite number")],
)  # fmt: skip
def test_a_bad_horizon_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], horizon: str, why: str
) -> None:
    for err in _refused(clean_log, tmp_path, capsys, "--horizon", horizon):
        assert f"--horizon {float(horizon)}: {why}" in err


def test_a_horizon_below_the_state_interval_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for err in _refused(clean_log, tmp_path, capsys, "--horizon", "0.001"):
        assert "--horizon 0.001: shorter than the state interval of" in err
        assert str(clean_log) in err


def test_a_horizon_longer_than_the_log_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    residual, diagnose = _refused(clean_log, tmp_path, capsys, "--horizon", "3")
    assert f"{clean_log}: too short for --horizon 3 s windows: the log (2 s)" in residual
    assert f"{clean_log}: too short for --horizon 3 s windows" in diagnose


def test_diagnose_refuses_a_log_too_short_for_its_fit_and_held_out_parts(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """1 s at 0.5 s windows: the residual has windows, the diagnosis's held-out 30% has none."""

    def first_second(tp: str, i: int, t: int, m: dict) -> tuple[int, dict] | None:
        return (t, m) if t < 1_000_000_000 else None

    log = rewrite(clean_log, tmp_path / "short.mcap", first_second)
    out_dir = tmp_path / "d"
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out_dir)]) == 2
    err = capsys.readouterr().err
    assert f"{log}: too short for --horizon 0.5 s windows: its 70%-100% span" in err
    assert not out_dir.exists()
    assert main(["sysid", "residual", str(log)]) == 0  # The whole log holds windows.


def test_diagnose_refuses_too_few_samples_for_the_fit(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """40 states (0.2 s) hold 5 ms windows, but the fit part holds only 28 samples."""

    def first_states(tp: str, i: int, t: int, m: dict) -> tuple[int, dict] | None:
        return (t, m) if t < 200_000_000 else None

    log = rewrite(clean_log, tmp_path / "tiny.mcap", first_states)
    out_dir = tmp_path / "d"
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out_dir), "--horizon",
                 "0.005"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert f"{log}: 28 state samples in the fit part" in err and "at least 50" in err
    assert not out_dir.exists()


def test_a_single_state_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def one_state(tp: str, i: int, t: int, m: dict) -> tuple[int, dict] | None:
        return None if tp == "/joint_states" and i > 0 else (t, m)

    log = rewrite(clean_log, tmp_path / "one.mcap", one_state)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: 1 message on /joint_states; predictions need at least 2" in err


def test_a_log_of_another_robot_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = rewrite(clean_log, tmp_path / "t1.mcap", meta=lambda d: {**d, "name": "t1"})
    for err in _refused(other, tmp_path, capsys):
        assert f"{other}: topic /joint_commands: field name lacks" in err
        assert "a log of another robot" in err
    unknown = rewrite(clean_log, tmp_path / "h9.mcap", meta=lambda d: {**d, "name": "h9"})
    for err in _refused(unknown, tmp_path, capsys):
        assert f"{unknown}: metadata robot.name: unknown robot 'h9'" in err


def test_a_log_missing_a_joint_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def drop_knee(tp: str, i: int, t: int, m: dict) -> tuple[int, dict]:
        k = m["name"].index("left_knee_joint")
        for v in m.values():
            if isinstance(v, list):
                del v[k]
        return t, m

    log = rewrite(clean_log, tmp_path / "no_knee.mcap", drop_knee)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: topic /joint_" in err and "lacks 1 of the robot's joints" in err
        assert "left_knee_joint" in err


def test_a_log_that_retunes_its_drives_is_refused(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def retune(tp: str, i: int, t: int, m: dict) -> tuple[int, dict]:
        if tp == "/joint_commands" and i >= 50:
            m["kp"][3] *= 2.0
        return t, m

    log = rewrite(clean_log, tmp_path / "retuned.mcap", retune)
    for err in _refused(log, tmp_path, capsys):
        assert f"{log}: the log changes kp of 'left_knee_joint'" in err


def test_diagnose_refuses_to_overwrite_its_log(
    clean_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "d"
    out_dir.mkdir()
    log = out_dir / "report.json"  # A log file under the name of an output.
    log.write_bytes(clean_log.read_bytes())
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out_dir)]) == 2
    assert "--out-dir" in capsys.readouterr().err
    assert log.read_bytes() == clean_log.read_bytes() and sorted(out_dir.iterdir()) == [log]
