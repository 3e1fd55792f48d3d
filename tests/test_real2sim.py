"""Real2sim, first slice: logs with undeclared effects, log I/O, the nominal model's residual.

The tests inject an effect at a joint chosen at random (seeded), hand the residual code only
the log, and check that the residual points at that joint. The residual code is never told
the effect.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.errors import InputError
from humimic.real2sim import (
    LogSettings,
    RobotLog,
    kstep_error,
    read_robot_log,
    simulate_log,
    write_robot_log,
)
from humimic.robots import get_robot
from humimic.sim.effects import parse_injection
from humimic.sim.models import fixed_base_spec, prediction_spec

SETTINGS = LogSettings(duration=8.0)


@cache
def _clean() -> RobotLog:
    return simulate_log(get_robot("g1"), [], SETTINGS)


def _nominal_error(log: RobotLog, **kw) -> np.ndarray:
    model = prediction_spec(get_robot("g1"), log.base_pose).compile()
    return kstep_error(model, log, **kw).per_joint


def test_parse_injection() -> None:
    inj = parse_injection("coulomb_friction:left_knee_joint,right_knee_joint=2.5")
    assert inj.effect == "coulomb_friction" and inj.value == 2.5
    assert inj.targets == ("left_knee_joint", "right_knee_joint")
    for bad, msg in [("friction:x=1", "unknown effect"), ("delay:x=abc", "not a number"),
                     ("delay=1", "EFFECT:JOINT"), ("delay:=1", "at least one joint")]:  # fmt: skip
        with pytest.raises(InputError, match=msg):
            parse_injection(bad)


def test_log_round_trip_matches_joints_by_name(tmp_path: Path) -> None:
    log = _clean()
    perm = np.random.default_rng(1).permutation(len(log.joint_names))
    shuffled = replace(
        log,
        joint_names=tuple(log.joint_names[i] for i in perm),
        q=log.q[:, perm], qd=log.qd[:, perm], effort=None if log.effort is None else log.effort[:, perm],
        cmd_q=log.cmd_q[:, perm], cmd_qd=log.cmd_qd[:, perm], cmd_tau=log.cmd_tau[:, perm],
        kp=log.kp[:, perm], kd=log.kd[:, perm],
    )  # fmt: skip
    path = write_robot_log(shuffled, tmp_path / "log.mcap")
    back = read_robot_log(path, log.joint_names)
    for k in ("t", "q", "qd", "effort", "t_cmd", "cmd_q", "kp", "kd"):
        np.testing.assert_allclose(getattr(back, k), getattr(log, k), atol=1e-12, err_msg=k)
    assert back.base == "fixed" and back.robot == "g1"


def test_simulated_log_is_realistic() -> None:
    log = _clean()
    assert log.t.size == 8 * 200 and log.t_cmd.size == 8 * 50
    model = fixed_base_spec(get_robot("g1"), log.base_pose).compile()
    lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
    assert np.all(log.cmd_q >= lo) and np.all(log.cmd_q <= hi)
    still = log.t < SETTINGS.still
    assert np.abs(np.diff(log.cmd_q[log.t_cmd < SETTINGS.still], axis=0)).max() < 1e-12
    assert np.abs(log.qd[still]).mean() < 0.05  # Still period: only noise, settling.
    moving = log.t > SETTINGS.still + 2
    assert np.abs(log.qd[moving]).mean() > 0.1  # Excited.


def test_clean_log_has_small_residual() -> None:
    err = _nominal_error(_clean())
    assert err.max() < 3e-3, err.max()  # Noise only: a few mrad over 0.5 s windows.


@pytest.mark.parametrize("seed", [1])
@pytest.mark.parametrize(
    ("effect", "low", "high"),
    [("coulomb_friction", 2.0, 4.0), ("viscous_damping", 1.0, 3.0)],
)
def test_residual_points_at_the_injected_joint(
    seed: int, effect: str, low: float, high: float
) -> None:
    rng = np.random.default_rng(seed)
    log0 = _clean()
    candidates = [n for n in log0.joint_names if "wrist" not in n]  # Wrists move little.
    joint = str(rng.choice(candidates))
    value = float(rng.uniform(low, high))
    log = simulate_log(get_robot("g1"), [parse_injection(f"{effect}:{joint}={value}")], SETTINGS)
    err = _nominal_error(log)
    clean = _nominal_error(log0)
    j = log.joint_names.index(joint)
    excess = err - clean
    assert np.argmax(excess) == j, (joint, log.joint_names[int(np.argmax(excess))])
    assert err[j] > 2 * clean[j]


def test_held_out_span_uses_the_last_part() -> None:
    log = _clean()
    model = fixed_base_spec(get_robot("g1"), log.base_pose).compile()
    held = kstep_error(model, log, span=(0.7, 1.0))
    assert log.t[held.starts[0]] >= 0.7 * log.duration - 1e-9


def test_no_window_spans_a_gap_in_a_log(tmp_path: Path) -> None:
    """Two recordings logged one after another (1 s apart): each window lies in one of them,
    starting at least SETTLE after the join, and the nominal model predicts the joined log
    as well as each part (a window across the join would compare one recording's prediction
    with the other's states)."""
    from humimic.real2sim.residual import SETTLE, Correction, Predictor
    from humimic.real2sim.robotlog import join_logs

    g1 = get_robot("g1")
    a = simulate_log(g1, [], LogSettings(duration=4.0, seed=1))
    b = simulate_log(g1, [], LogSettings(duration=4.0, seed=2))
    joined = read_robot_log(write_robot_log(join_logs([a, b], pause=1.0), tmp_path / "ab.mcap"),
                            a.joint_names)  # fmt: skip
    (gap,) = joined.gaps()
    assert joined.t[gap + 1] - joined.t[gap] == pytest.approx(1.0, abs=0.01)
    model = prediction_spec(g1, a.base_pose).compile()
    p = Predictor(model, joined, horizon=0.5, stride=0.1)
    start, end = joined.t[p.starts], joined.t[p.starts + p.samples]
    assert np.all(end - start < 0.51)
    later = start > joined.t[gap]
    assert later.any() and (~later).any()
    assert np.all(start[later] >= joined.t[gap + 1] + SETTLE - 1e-9)
    both = p.error(Correction.of(model)).kstep_rmse_rad
    parts = [kstep_error(model, x, stride=0.1).kstep_rmse_rad for x in (a, b)]
    assert both < 1.2 * max(parts)
    # A log whose every window spans a gap is refused, and says so.
    short = join_logs([replace(a, t=a.t[:60], q=a.q[:60], qd=a.qd[:60], effort=None)] * 2)
    with pytest.raises(InputError, match="span a gap"):
        Predictor(model, short, horizon=0.5)


def test_cli_simulate_and_residual(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "log.mcap"
    argv = ["sysid", "simulate", "--duration", "4", "--out", str(out),
            "--inject", "coulomb_friction:left_knee_joint=3"]  # fmt: skip
    assert main(argv) == 0
    report = tmp_path / "r.json"
    assert main(["sysid", "residual", str(out), "--report", str(report)]) == 0
    r = json.loads(report.read_text())
    per_joint = r["error_nominal"]["per_joint"]
    assert max(per_joint, key=per_joint.get) == "left_knee_joint"
    assert main(["sysid", "simulate", "--out", str(tmp_path / "x.mcap"), "--inject", "x"]) == 2
    assert "EFFECT:JOINT" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_cli_diagnose_writes_model_and_report(tmp_path: Path) -> None:
    import mujoco

    log = tmp_path / "log.mcap"
    assert main(["sysid", "simulate", "--duration", "8", "--out", str(log), "--inject",
                 "viscous_damping:right_knee_joint=2.0"]) == 0  # fmt: skip
    out = tmp_path / "diag"
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out)]) == 0
    r = json.loads((out / "report.json").read_text())
    assert set(r) >= {"robot", "log", "error_before", "error_after", "effects", "unexplained",
                      "residual_model"}  # fmt: skip
    claimed = [e for e in r["effects"] if e["confidence"] >= 0.5]
    assert [(e["effect"], e["joints"]) for e in claimed] == [
        ("viscous_damping", ["right_knee_joint"])
    ]
    assert r["error_after"]["kstep_rmse_rad"] < r["error_before"]["kstep_rmse_rad"]
    assert r["residual_model"] is None and r["unexplained"] is False
    # The vocabulary's own effect: once claimed, its joint is back at its noise floor.
    assert claimed[0]["partial"] is False and claimed[0]["stands_out"] < 3.0
    assert "Partial explanations" not in (out / "report.md").read_text()
    model = mujoco.MjModel.from_xml_path(str(out / "model.xml"))
    dof = model.joint("right_knee_joint").dofadr[0]
    assert model.dof_damping[dof] == pytest.approx(claimed[0]["params"]["value"], rel=1e-5)
    assert model.nq == 36  # The full robot, floating base like the nominal.
    md = (out / "report.md").read_text()
    assert md.startswith("# Diagnosis")
    for plot in r["plots"]:
        assert f"]({plot})" in md and (out / plot).stat().st_size > 1000
    assert "signature_viscous_damping_right_knee_joint.png" in r["plots"]


def test_cli_diagnose_bad_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 30)
    assert main(["sysid", "diagnose", str(bad), "--out-dir", str(tmp_path / "d")]) == 2
    assert "bad.mcap" in capsys.readouterr().err
    assert not (tmp_path / "d" / "report.json").exists()


def test_cli_diagnose_checks_a_claimed_payload_with_the_torque_regressor(tmp_path: Path) -> None:
    """A claimed payload comes with a second, search-free estimate (Pinocchio's regressor);
    both find the hidden mass, and the report says so."""
    log = tmp_path / "log.mcap"
    assert main(["sysid", "simulate", "--duration", "12", "--seed", "3", "--out", str(log),
                 "--inject", "payload_mass:right_wrist_yaw_link=0.8"]) == 0  # fmt: skip
    out = tmp_path / "diag"
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out)]) == 0
    r = json.loads((out / "report.json").read_text())
    claimed = [e for e in r["effects"] if e["confidence"] >= 0.5]
    assert [(e["effect"], e.get("body")) for e in claimed] == [
        ("payload_mass", "right_wrist_yaw_link")
    ]
    reg = claimed[0]["regression"]
    assert reg["torques"] == "logged effort" and reg["rows"] > 1000
    assert reg["mass"] == pytest.approx(0.8, abs=max(0.05, 3 * reg["mass_std"]))
    assert reg["mass"] == pytest.approx(claimed[0]["params"]["value"], abs=0.08)
    unclaimed = [e for e in r["effects"] if e["confidence"] < 0.5]
    assert all("regression" not in e for e in unclaimed)
    assert "torque regressor" in (out / "report.md").read_text()
