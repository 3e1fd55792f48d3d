"""Deployment logs: a robot standing on the floor (floating base, IMU, optional mocap).

The logs are simulated by a standing balance controller (an LQR at the command rate) with
MuJoCo's own IMU sensors; the predictions read only the log and rebuild the base's state from
the IMU and the contact (:mod:`humimic.real2sim.floating`), not from the simulator's state.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from functools import cache
from pathlib import Path
from unittest.mock import patch

import mujoco
import numpy as np
import pytest

from humimic.cli.main import main
from humimic.errors import InputError
from humimic.real2sim import LogSettings, RobotLog, read_robot_log, simulate_log, write_robot_log
from humimic.real2sim.correction import Correction
from humimic.real2sim.floating import prediction_step, smooth_track
from humimic.real2sim.residual import Predictor, kstep_error
from humimic.real2sim.result import SysidResult
from humimic.real2sim.simulate import tilt_imu
from humimic.robots import get_robot
from humimic.sim.effects import parse_injection
from humimic.sim.models import floating_prediction_spec
from humimic.sim.physics import load_physics

DURATION = 6.0


@cache
def _model():
    return floating_prediction_spec(get_robot("g1")).compile()


@cache
def _log(mocap: bool = True, inject: str = "", noise: bool = True) -> RobotLog:
    settings = LogSettings(duration=DURATION, base="floating", mocap=mocap, seed=2)
    if not noise:
        settings = replace(settings, q_noise=0.0, qd_noise=0.0, effort_noise=0.0, gyro_noise=0.0,
                           acc_noise=0.0, quat_noise=0.0, mocap_noise=0.0)  # fmt: skip
    injections = [parse_injection(inject)] if inject else []
    return simulate_log(get_robot("g1"), injections, settings)


def test_a_deployment_log_round_trips_with_its_imu_and_mocap(tmp_path: Path) -> None:
    log = _log()
    assert log.base == "floating" and log.imu is not None and log.mocap is not None
    assert log.imu.site == "imu_in_pelvis"
    back = read_robot_log(write_robot_log(log, tmp_path / "d.mcap"), log.joint_names)
    assert back.imu is not None and back.mocap is not None and back.imu.site == "imu_in_pelvis"
    np.testing.assert_allclose(back.imu.t, log.imu.t, atol=1e-9)
    np.testing.assert_allclose(back.imu.quat_w, log.imu.quat_w, atol=1e-12)
    np.testing.assert_allclose(back.imu.gyro_b, log.imu.gyro_b)
    assert back.imu.acc_b is not None and log.imu.acc_b is not None
    np.testing.assert_allclose(back.imu.acc_b, log.imu.acc_b)
    np.testing.assert_allclose(back.mocap.pos_w, log.mocap.pos_w)
    np.testing.assert_allclose(back.q, log.q)
    # Standing still, the accelerometer reads gravity's reaction: +9.81 m/s^2 up.
    assert 9.6 < np.linalg.norm(log.imu.acc_b.mean(axis=0)) < 10.0


def test_the_robot_stands_and_sways_on_its_balance_controller() -> None:
    log = _log()
    assert log.mocap is not None
    z = log.mocap.pos_w[:, 2]
    assert z.max() - z.min() < 0.03  # It stands (the pelvis at ~0.79 m) ...
    moved = np.ptp(log.q, axis=0)
    arms = [i for i, n in enumerate(log.joint_names) if "shoulder" in n or "elbow" in n]
    assert np.all(moved[arms] > 0.05)  # ... and sways its arms (0.05 of their range).


def test_the_base_state_is_rebuilt_from_mocap_and_the_accelerometer() -> None:
    """Noise-free log: the smoothed position and velocity agree with motion capture (the truth
    here) and its derivative; the orientation is the IMU's, its site's rotation undone."""
    log = _log(noise=False)
    assert log.mocap is not None
    p = Predictor(_model(), log, horizon=0.5)
    assert p.base is not None and p.base.world
    assert "motion capture" in p.base.source and "accelerometer" in p.base.source
    truth = log.mocap.pos_w[p.starts]
    assert np.max(np.abs(p.base.qpos[:, :3] - truth)) < 0.001  # [m]
    vel = np.gradient(log.mocap.pos_w, log.mocap.t, axis=0)[p.starts]
    assert np.max(np.abs(p.base.qvel[:, :3] - vel)) < 0.01  # [m/s]
    dots = np.abs(np.sum(p.base.qpos[:, 3:] * log.mocap.quat_w[p.starts], axis=1))
    assert np.all(dots > 1 - 1e-9)


def test_without_mocap_the_contact_and_the_accelerometer_give_height_and_velocity() -> None:
    log = _log(noise=False)
    assert log.mocap is not None
    blind = replace(log, mocap=None)
    p = Predictor(_model(), blind, horizon=0.5)
    assert p.base is not None and not p.base.world and "motion capture" not in p.base.source
    assert np.all(p.base.qpos[:, :2] == 0.0)  # A flat floor does not care.
    truth = log.mocap.pos_w[p.starts]
    assert np.max(np.abs(p.base.qpos[:, 2] - truth[:, 2])) < 0.003  # Contact: within 3 mm.
    vel = np.gradient(log.mocap.pos_w, log.mocap.t, axis=0)[p.starts]
    assert np.max(np.abs(p.base.qvel[:, :3] - vel)) < 0.02  # [m/s]


def _track(rate: float = 50.0, seconds: float = 4.0):
    """A point swaying and walking on: exact position, velocity and acceleration."""
    t = np.arange(0.0, seconds, 1.0 / rate)
    w = 2 * np.pi * np.array([1.5, 0.9, 2.2])
    amp = np.array([0.05, 0.08, 0.02])
    p = amp * np.sin(w * t[:, None]) + np.array([0.4, 0.0, 0.0]) * t[:, None]
    v = amp * w * np.cos(w * t[:, None]) + np.array([0.4, 0.0, 0.0])
    a = -amp * w**2 * np.sin(w * t[:, None])
    return t, p, v, a


def test_the_smoother_reads_velocity_from_noisy_mocap_and_a_biased_accelerometer() -> None:
    rng = np.random.default_rng(3)
    t, p, v, a = _track()
    pos = p + rng.normal(0, 0.001, p.shape)
    acc = a + np.array([0.2, -0.15, 0.1]) + rng.normal(0, 0.05, a.shape)  # Biased, noisy.
    sig = np.full(p.shape, 0.001)
    junk = rng.normal(0, 0.3, v.shape)  # A stance velocity that says little.
    ps, vs = smooth_track(t, acc, pos, sig, junk, 0.3)
    differenced = np.gradient(pos, t, axis=0)
    rms = lambda e: float(np.sqrt(np.mean(e[10:-10] ** 2)))  # noqa: E731
    assert rms(vs - v) < 0.01 and rms(vs - v) < rms(differenced - v) / 3
    assert rms(ps - p) < 0.001
    # Without the accelerometer: about as good as differencing the positions.
    _, v_free = smooth_track(t, None, pos, sig, junk, 0.3)
    assert rms(v_free - v) < 1.5 * rms(differenced - v)


def test_the_smoother_skips_a_slipping_stance_foot() -> None:
    """No position measured: the velocity comes from the accelerometer and the stance foot,
    whose readings sometimes slip 2 m/s away; those are not read."""
    rng = np.random.default_rng(4)
    t, p, v, a = _track()
    stance = v + rng.normal(0, 0.05, v.shape)
    slips = rng.random(len(t)) < 0.2
    stance[slips] += 2.0
    sig = np.full(p.shape, np.inf)
    _, vs = smooth_track(t, a + rng.normal(0, 0.05, a.shape), np.zeros_like(p), sig, stance, 0.3)
    assert float(np.sqrt(np.mean((vs - v) ** 2))) < 0.03


@pytest.mark.parametrize(("rate", "step_ms"),
                         [(50, 5.0), (200, 5.0), (500, 2.0), (1000, 1.0), (125, 4.0), (2000, 1.0)])  # fmt: skip
def test_the_prediction_step_divides_the_state_interval(rate: int, step_ms: float) -> None:
    log = replace(_log(), t=np.arange(40) / rate)
    assert prediction_step(log) == pytest.approx(step_ms * 1e-3)


@pytest.mark.parametrize("mocap", [True, False])
def test_the_nominal_model_predicts_a_clean_deployment_log(mocap: bool) -> None:
    log = _log(mocap=mocap)
    p = Predictor(_model(), log, horizon=0.5)
    assert p.base is not None and ("motion capture" in p.base.source) == mocap
    err = p.error(Correction.of(_model()))
    assert err.kstep_rmse_rad < 0.004  # 1.7-2.1 mrad measured; the sensor noise is 0.2.


def test_a_payload_shows_in_the_prediction_error_of_a_deployment_log() -> None:
    clean = kstep_error(_model(), _log())
    heavy = kstep_error(_model(), _log(inject="payload_mass:torso_link=5.0"))
    names = _log().joint_names
    waist = names.index("waist_pitch_joint")
    assert heavy.kstep_rmse_rad > 3 * clean.kstep_rmse_rad
    assert heavy.per_joint[waist] > 5 * clean.per_joint[waist]


def test_cli_simulates_and_predicts_a_deployment_log(tmp_path: Path, capsys) -> None:
    """A deployment log with its IMU mounted 2 deg / -3 deg off: predicted with the tilt found
    from the soles and removed. A tilt asked of a gantry log exits 2, writing nothing."""
    log = tmp_path / "walk.mcap"
    assert main(["sysid", "simulate", "--base", "floating", "--no-mocap", "--duration", "3",
                 "--imu-tilt", "2", "-3", "--out", str(log)]) == 0  # fmt: skip
    assert main(["sysid", "residual", str(log), "--report", str(tmp_path / "r.json")]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["base"] == "floating"
    assert "motion capture" not in report["base_estimate"]
    found = re.search(r"mount tilt \(([-+0-9., ]+) deg", report["base_estimate"])
    assert found, report["base_estimate"]
    tilt = [float(v) for v in found.group(1).split(",")]
    np.testing.assert_allclose(tilt, [2.0, -3.0], atol=0.1)
    assert report["error_nominal"]["kstep_rmse_rad"] < 0.004
    assert "floating base:" in capsys.readouterr().out
    gantry = tmp_path / "g.mcap"
    assert main(["sysid", "simulate", "--imu-tilt", "2", "0", "--out", str(gantry)]) == 2
    assert not gantry.exists()


def _rewrite(src: Path, dst: Path, topic: str, edit) -> None:
    """Copy a log, passing each message of ``topic`` through ``edit`` (or dropping the topic
    when ``edit`` is None)."""
    from humimic.formats.mcap import McapWriter, read_mcap

    log = read_mcap(src)
    with McapWriter(dst) as w:
        for name, meta in log.metadata.items():
            w.add_metadata(name, meta)
        for t, msgs in log.messages.items():
            for i, (ns, m) in enumerate(msgs):
                if t != topic:
                    w.write(t, ns, m)
                elif edit is not None:
                    w.write(t, ns, edit(i, m))


@pytest.mark.parametrize(
    ("topic", "edit", "expect"),
    [
        ("/imu", None, "needs topic /imu"),
        (
            "/imu",
            lambda i, m: (
                {**m, "orientation": {"w": 0.0, "x": 0.0, "y": 0.0, "z": 0.0}} if i == 5 else m
            ),
            "message 5: field orientation has length 0",
        ),
        (
            "/imu",
            lambda i, m: {k: v for k, v in m.items() if k != "angular_velocity"} if i == 7 else m,
            "message 7: field angular_velocity missing",
        ),
    ],
)
def test_a_broken_deployment_log_exits_2_naming_the_field(
    tmp_path: Path, topic: str, edit, expect: str, capsys
) -> None:
    good = write_robot_log(_log(), tmp_path / "good.mcap")
    bad = tmp_path / "bad.mcap"
    _rewrite(good, bad, topic, edit)
    assert main(["sysid", "residual", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and expect in err


@pytest.mark.slow  # The default run finds an independently built backpack the same way.
def test_a_payload_is_found_blind_in_a_deployment_log(tmp_path: Path) -> None:
    """The diagnosis of a robot on the floor, told nothing but the log: the payload on the
    right body, sized within 30 %, the held-out error at least halved, nothing else claimed."""
    log = tmp_path / "deploy.mcap"
    assert main(["sysid", "simulate", "--base", "floating", "--duration", "8", "--seed", "3",
                 "--inject", "payload_mass:torso_link=4.0", "--out", str(log)]) == 0  # fmt: skip
    _payload_diagnosed(log, tmp_path, 4.0)


def test_a_clean_deployment_log_yields_no_confident_claim(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Nothing claimed, and nothing called unexplained: on the floor each window starts from
    an estimated base state, whose errors move the ankles and the waist several times more
    than the median joint (this log's waist roll and ankle pitches stood out of a noise floor
    taken from the median joint alone); the noise floor follows that. The base is estimated
    once for the whole diagnosis."""
    from humimic.real2sim import residual
    from humimic.real2sim.report import run_diagnosis

    log = simulate_log(get_robot("g1"), [], LogSettings(duration=8.0, base="floating", seed=5))
    calls: list[int] = []
    estimate = residual.estimate_base
    monkeypatch.setattr(
        residual, "estimate_base", lambda *a, **k: calls.append(1) or estimate(*a, **k)
    )
    r = run_diagnosis(write_robot_log(log, tmp_path / "clean.mcap"), tmp_path / "diag").report
    assert len(calls) == 1
    assert [e for e in r["effects"] if e["confidence"] >= 0.5] == []
    assert r["unexplained"] is False and r["unexplained_joints"] == []
    floor = r["noise_floor_rad"]
    median = float(np.median(list(floor.values())))
    assert floor["waist_roll_joint"] > 1.5 * median and floor["left_ankle_pitch_joint"] > median
    noted = next(line for line in (tmp_path / "diag" / "report.md").read_text().splitlines()
                 if line.startswith("Noise floor:"))  # fmt: skip
    assert "waist_roll_joint" in noted


def _floor_log(seed: int, edit) -> RobotLog:
    """An 8 s floor log of a robot changed by ``edit`` (the test's own spec change)."""
    settings = LogSettings(duration=8.0, base="floating", seed=seed)
    return simulate_log(get_robot("g1"), [], settings, edit=edit)


def _diagnosed_cli(log: RobotLog, tmp_path: Path) -> dict:
    """``humimic sysid diagnose`` on the log (written to a file): its report.json."""
    out = tmp_path / "diag"
    assert main(["sysid", "diagnose", str(write_robot_log(log, tmp_path / "log.mcap")),
                 "--out-dir", str(out)]) == 0  # fmt: skip
    return json.loads((out / "report.json").read_text())


def _cable(spec) -> None:
    """A cable pulling the left knee, made here: MuJoCo's joint spring, cubic, about 0.8 rad
    (no effect of the vocabulary is a position-dependent torque)."""
    knee = spec.joint("left_knee_joint")
    knee.stiffness = np.array([0.0, 0.0, 10.0])
    knee.springref = 0.8


def test_an_effect_outside_the_vocabulary_is_not_passed_off_as_explained(tmp_path: Path) -> None:
    """A spring on the knee is outside the vocabulary: what the diagnosis claims on the knee
    in its place (Coulomb friction on this log) is marked partial, its joints far above their
    noise floor, and the report says so; or nothing is claimed there and the knee is named
    unexplained."""
    r = _diagnosed_cli(_floor_log(6, _cable), tmp_path)
    on_knee = [e for e in r["effects"]
               if e["confidence"] >= 0.5 and "left_knee_joint" in e.get("joints", [])]  # fmt: skip
    if on_knee:
        assert all(e["partial"] and e["stands_out"] > 3.0 for e in on_knee)
        assert "**Partial explanations**" in (tmp_path / "diag" / "report.md").read_text()
    else:
        assert r["unexplained"] and "left_knee_joint" in r["unexplained_joints"]


@pytest.mark.parametrize(
    "inject", ["delay:left_knee_joint,right_knee_joint=0.03", "backlash:left_knee_joint=0.02"]
)
def test_a_deployment_log_with_a_delay_or_play_is_simulated(inject: str) -> None:
    """The balance controller is designed on the nominal robot, so effects that MuJoCo's
    derivatives do not support (delays) or that add joints (play) still give a log."""
    log = simulate_log(get_robot("g1"), [parse_injection(inject)],
                       LogSettings(duration=3.0, base="floating"))  # fmt: skip
    assert log.mocap is not None and np.ptp(log.mocap.pos_w[:, 2]) < 0.03


def _backpack_body(spec) -> None:
    """A 3 kg box welded 15 cm above the torso's frame, made here (a new body with its own
    inertia), not by the vocabulary's payload (mass added at the body's centre of mass)."""
    box = spec.body("torso_link").add_body(name="backpack_box", pos=[0.0, 0.0, 0.15])
    box.mass = 3.0
    box.ipos[:] = 0.0
    box.inertia[:] = [3.0 / 12 * (0.30**2 + 0.25**2), 3.0 / 12 * (0.12**2 + 0.25**2),
                      3.0 / 12 * (0.12**2 + 0.30**2)]  # fmt: skip
    box.explicitinertial = True


def test_an_independently_built_backpack_is_found_as_a_payload(tmp_path: Path) -> None:
    """``humimic sysid diagnose`` on a robot on the floor, told nothing but the log. The effect
    is not the vocabulary's (a new body with its own centre of mass and inertia, not mass
    added at the torso's centre of mass): the payload is named on the torso, within 30 %,
    the held-out error at least halved, nothing else claimed."""
    log = simulate_log(get_robot("g1"), [], LogSettings(duration=8.0, base="floating", seed=3),
                       edit=_backpack_body)  # fmt: skip
    _payload_diagnosed(write_robot_log(log, tmp_path / "deploy.mcap"), tmp_path, 3.0)


def _payload_diagnosed(log: Path, tmp_path: Path, mass: float) -> None:
    """``humimic sysid diagnose`` names a payload of ``mass`` on the torso (within 30 %) and
    nothing else, and at least halves the held-out error; no residual network on the floor."""
    out = tmp_path / "diag"
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(out)]) == 0
    r = json.loads((out / "report.json").read_text())
    assert r["base"] == "floating" and "motion capture" in r["base_estimate"]
    assert "backlash" in r["not_searched_effects"]
    claimed = [e for e in r["effects"] if e["confidence"] >= 0.5]
    assert [(e["effect"], e.get("body")) for e in claimed] == [("payload_mass", "torso_link")]
    assert claimed[0]["params"]["value"] == pytest.approx(mass, rel=0.3)
    assert r["error_after"]["kstep_rmse_rad"] <= 0.5 * r["error_before"]["kstep_rmse_rad"]
    assert "Floating base" in (out / "report.md").read_text()
    assert main(["sysid", "diagnose", str(log), "--out-dir", str(tmp_path / "d2"),
                 "--residual-net", "always"]) == 2  # fmt: skip
    assert not (tmp_path / "d2").exists()


def _sole_effect_both_ways(
    effect: str, value: float, field: str
) -> tuple[mujoco.MjModel, mujoco.MjModel, Correction]:
    """A sole effect on the left foot written into a spec and set on a compiled model: the
    two give the same ``field`` (a geom array), changed on the left foot's floor colliders
    (all four spheres) only. Returns the nominal model, the written one and the correction."""
    from humimic.real2sim.correction import apply_effect
    from humimic.sim.effects import apply_to_spec

    spec = floating_prediction_spec(get_robot("g1"))
    apply_to_spec(spec, [parse_injection(f"{effect}:left_ankle_roll_link={value}")])
    written = spec.compile()
    model = _model()
    c = Correction.of(model).copy()
    apply_effect(c, effect, model.body("left_ankle_roll_link").id, value)
    np.testing.assert_array_equal(getattr(c.model, field), getattr(written, field))
    changed = np.flatnonzero(getattr(written, field)[:, 0] != getattr(model, field)[:, 0])
    assert {written.body(int(written.geom_bodyid[g])).name for g in changed} == {
        "left_ankle_roll_link"
    }
    assert changed.size == 4
    return model, written, c


def test_contact_softness_means_the_same_on_a_spec_and_on_a_model() -> None:
    """The effect set on a compiled model (what the diagnosis scores) and written into a spec
    (what model.xml and physics files carry) give the same model and the same predictions;
    a body that does not decide its floor contact is refused, naming it."""
    from humimic.sim.effects import apply_to_spec

    model, written, c = _sole_effect_both_ways("contact_softness", 0.08, "geom_solref")
    log = _log()
    a, b = Predictor(model, log, horizon=0.5), Predictor(written, log, horizon=0.5)
    assert a.error(c).kstep_rmse_rad == pytest.approx(
        b.error(Correction.of(written)).kstep_rmse_rad
    )
    assert a.error(c).kstep_rmse_rad != pytest.approx(a.error(Correction.of(model)).kstep_rmse_rad)
    with pytest.raises(InputError, match="'pelvis'"):
        apply_to_spec(floating_prediction_spec(get_robot("g1")),
                      [parse_injection("contact_softness:pelvis=0.08")])  # fmt: skip


def _soft_soles(spec) -> None:
    """Softer soles (or a soft mat under them), made here: the G1's foot spheres' contact
    time constant 0.1 s, five times MuJoCo's 0.02."""
    for foot in ("left_ankle_roll_link", "right_ankle_roll_link"):
        for g in spec.body(foot).geoms:
            if g.type == mujoco.mjtGeom.mjGEOM_SPHERE:
                g.solref = np.array([0.1, 1.0])


def test_soft_soles_are_found_blind_in_a_deployment_log(tmp_path: Path) -> None:
    """Both feet on a softer contact: the diagnosis claims one contact time constant for
    every sole within 30 % and nothing else, the held-out error at least halves, and the
    physics file it writes carries the effect on both feet."""
    r = _diagnosed_cli(_floor_log(6, _soft_soles), tmp_path)
    claimed = [e for e in r["effects"] if e["confidence"] >= 0.5]
    assert [(e["effect"], e.get("group")) for e in claimed] == [("contact_softness", "all_soles")]
    assert sorted(claimed[0]["bodies"]) == ["left_ankle_roll_link", "right_ankle_roll_link"]
    assert claimed[0]["params"]["value"] == pytest.approx(0.1, rel=0.3)
    assert r["error_after"]["kstep_rmse_rad"] <= 0.5 * r["error_before"]["kstep_rmse_rad"]
    assert r["unexplained"] is False
    physics = load_physics(tmp_path / "diag" / "physics.yaml")
    assert [(e.effect, sorted(e.targets)) for e in physics.effects] == [
        ("contact_softness", ["left_ankle_roll_link", "right_ankle_roll_link"])
    ]


def _slippery_soles(spec) -> None:
    """A slippery floor (wet tiles, ice), made here: the G1's foot spheres, whose friction
    decides their contact with the floor, slide at 0.07 instead of 0.6."""
    for foot in ("left_ankle_roll_link", "right_ankle_roll_link"):
        for g in spec.body(foot).geoms:
            if g.type == mujoco.mjtGeom.mjGEOM_SPHERE:
                g.friction = np.array([0.07, *np.asarray(g.friction)[1:]])


def test_a_slippery_floor_is_found_blind_in_a_deployment_log(tmp_path: Path) -> None:
    """Feet that slide as the robot sways: the diagnosis claims one sliding friction for
    every sole within 30 % and nothing else, the held-out error halves, and the physics file
    it writes carries the friction on both feet; the same effect written into a spec and set
    on a compiled model give the same model."""
    r = _diagnosed_cli(_floor_log(6, _slippery_soles), tmp_path)
    claimed = [e for e in r["effects"] if e["confidence"] >= 0.5]
    assert [(e["effect"], e.get("group")) for e in claimed] == [("contact_friction", "all_soles")]
    assert claimed[0]["params"]["value"] == pytest.approx(0.07, rel=0.3)
    assert r["error_after"]["kstep_rmse_rad"] <= 0.5 * r["error_before"]["kstep_rmse_rad"]
    physics = SysidResult.of(r).physics(name="slippery", robot="g1")
    assert [(e.effect, sorted(e.targets)) for e in physics.effects] == [
        ("contact_friction", ["left_ankle_roll_link", "right_ankle_roll_link"])
    ]
    _sole_effect_both_ways("contact_friction", 0.2, "geom_friction")


def test_an_imu_heading_off_motion_capture_is_turned_onto_it() -> None:
    """A real IMU's heading is arbitrary (gravity fixes its tilt only): the IMU's world is
    turned 1.2 rad about the vertical against motion capture's, by scipy here. The estimate
    finds the offset and predicts as well as with the aligned log; reading the IMU's heading
    as motion capture's would not."""
    from scipy.spatial.transform import Rotation

    log = _log()
    assert log.imu is not None
    turn = Rotation.from_euler("z", 1.2)
    xyzw = (turn * Rotation.from_quat(log.imu.quat_w[:, [1, 2, 3, 0]])).as_quat()
    turned = replace(log, imu=replace(log.imu, quat_w=xyzw[:, [3, 0, 1, 2]]))
    model = _model()
    base = Predictor(model, log, horizon=0.5)
    p = Predictor(model, turned, horizon=0.5)
    assert p.base is not None and "heading turned -68.8 deg" in p.base.source
    aligned = base.error(Correction.of(model)).kstep_rmse_rad
    assert p.error(Correction.of(model)).kstep_rmse_rad == pytest.approx(aligned, rel=0.05)
    # Without motion capture there is nothing to align to: the heading is the IMU's.
    nomocap = Predictor(model, replace(turned, mocap=None), horizon=0.5)
    assert nomocap.base is not None and "heading" not in nomocap.base.source


def test_a_gyro_bias_is_found_and_removed() -> None:
    """A real gyro reads a constant bias on top of its noise: here (30, -20, 10) mrad/s added
    to the log's gyro. Against motion capture's orientation, or without it against the IMU's
    own orientation, the bias is found within 5 % per axis, named, and removed: the
    predictions are the clean log's (within 5 %), not the biased ones' (a third worse or
    more). A clean log reports no bias."""
    log = _log()
    assert log.imu is not None
    bias = np.array([0.03, -0.02, 0.01])
    model = _model()
    for mocap in (True, False):
        clean = log if mocap else replace(log, mocap=None)
        assert clean.imu is not None
        biased = replace(clean, imu=replace(clean.imu, gyro_b=clean.imu.gyro_b + bias))
        p0, p = Predictor(model, clean, horizon=0.5), Predictor(model, biased, horizon=0.5)
        assert p0.base is not None and "bias" not in p0.base.source
        assert p.base is not None
        found = re.search(r"gyro's bias \(([-+0-9., ]+) mrad/s", p.base.source)
        assert found, p.base.source
        values = np.array([float(v) for v in found.group(1).split(",")]) * 1e-3
        np.testing.assert_allclose(values, bias, rtol=0.05)
        assert ("motion capture's" in p.base.source) == mocap
        before = p0.error(Correction.of(model)).kstep_rmse_rad
        assert p.error(Correction.of(model)).kstep_rmse_rad == pytest.approx(before, rel=0.05)
    with pytest.MonkeyPatch.context() as mp:  # Not removed: the predictions suffer.
        from humimic.real2sim import floating

        mp.setattr(floating, "GYRO_BIAS_NOTE", 1.0)
        raw = Predictor(model, replace(log, imu=replace(log.imu, gyro_b=log.imu.gyro_b + bias)),
                        horizon=0.5).error(Correction.of(model)).kstep_rmse_rad  # fmt: skip
    assert raw > 1.3 * Predictor(model, log, horizon=0.5).error(Correction.of(model)).kstep_rmse_rad


def test_an_imu_mount_tilt_is_found_and_removed() -> None:
    """An IMU mounted 2 deg in roll and -3 deg in pitch off its site (the pelvis's axes): the
    base would lean that much and every prediction with it. Against motion capture, or
    without it against the stance soles (a sole on the floor lies flat), the tilt is found
    within 0.1 deg, named and removed: the predictions are the clean log's within 10 %, where
    the tilted ones are more than twice as far off. A clean log reports no tilt."""
    from humimic.real2sim import floating

    model = _model()
    for mocap in (True, False):
        clean = _log() if mocap else replace(_log(), mocap=None)
        tilted = tilt_imu(clean, 2.0, -3.0)
        p0, p = Predictor(model, clean, horizon=0.5), Predictor(model, tilted, horizon=0.5)
        assert p0.base is not None and "tilt" not in p0.base.source
        assert p.base is not None
        found = re.search(r"mount tilt \(([-+0-9., ]+) deg", p.base.source)
        assert found, p.base.source
        np.testing.assert_allclose([float(v) for v in found.group(1).split(",")], [2.0, -3.0],
                                   atol=0.1)  # fmt: skip
        assert ("motion capture's" in p.base.source) == mocap
        before = p0.error(Correction.of(model)).kstep_rmse_rad
        assert p.error(Correction.of(model)).kstep_rmse_rad == pytest.approx(before, rel=0.1)
        with patch.object(floating, "MOUNT_TILT_NOTE", 1.0):  # Left in: predictions suffer.
            raw = Predictor(model, tilted, horizon=0.5).error(Correction.of(model))
        assert raw.kstep_rmse_rad > 2 * before


def test_a_gyro_bias_is_measured_while_turning_and_across_a_reference_gap() -> None:
    """A gyro turning at 0.3 rad/s about its z with a 10 mrad/s bias about its x (the bias
    sweeps round in the world), against a reference that loses 2 s in the middle and comes
    back with its frame 1 rad off (markers re-acquired): the bias in the gyro's own axes,
    the stretches across the gap left out."""
    from humimic.real2sim.floating import gyro_bias

    t = np.arange(0.0, 6.0, 0.005)
    turned = 0.3 * t + np.where(t > 4.0, 1.0, 0.0)  # Unseen between 2 and 4 s, then off.
    ref = np.stack([np.cos(turned / 2), 0 * t, 0 * t, np.sin(turned / 2)], axis=1)
    gyro = np.tile([0.01, 0.0, 0.3], (t.size, 1))
    seen = (t < 2.0) | (t > 4.0)
    bias, se = gyro_bias(t[seen], ref[seen], t, gyro)
    np.testing.assert_allclose(bias, [0.01, 0.0, 0.0], atol=2e-4)
    assert np.all(se < 1e-4)


def test_a_drifting_imu_heading_is_followed() -> None:
    """A real IMU's heading also drifts (no magnetometer, or one the motors disturb): here it
    drifts 0.5 rad over the log on top of a 1.2 rad turn, by scipy. The base's orientation is
    that of the aligned log all along, and so are the predictions; one turn for the whole log
    leaves the ends a quarter of the drift off (this standing robot barely moves, so its
    predictions hardly suffer; a walking one's velocity would turn with the heading)."""
    from scipy.spatial.transform import Rotation

    from humimic.real2sim import floating

    log = _log()
    assert log.imu is not None
    yaw = 1.2 + 0.5 * (log.imu.t - log.imu.t[0]) / (log.imu.t[-1] - log.imu.t[0])
    turn = Rotation.from_euler("z", yaw[:, None])
    xyzw = (turn * Rotation.from_quat(log.imu.quat_w[:, [1, 2, 3, 0]])).as_quat()
    drifting = replace(log, imu=replace(log.imu, quat_w=xyzw[:, [3, 0, 1, 2]]))
    model = _model()
    aligned = Predictor(model, log, horizon=0.5).error(Correction.of(model)).kstep_rmse_rad
    p = Predictor(model, drifting, horizon=0.5)
    assert p.base is not None
    found = re.search(r"following its drift \(([0-9.]+) deg", p.base.source)
    # 28.6 deg, less what the mean over 1 s trims at the two ends of the 6 s log.
    assert found and 28.0 < float(found.group(1)) < 29.2  # 0.5 rad: 28.6 deg.
    assert p.error(Correction.of(model)).kstep_rmse_rad == pytest.approx(aligned, rel=0.05)

    ref = Predictor(model, log, horizon=0.5).base
    assert ref is not None

    def off(b) -> float:  # Largest angle between two base orientations at the windows' starts.
        assert b is not None
        dot = np.abs(np.sum(b.qpos[:, 3:] * ref.qpos[:, 3:], axis=1))
        return float(np.max(2 * np.arccos(np.clip(dot, 0.0, 1.0))))

    assert off(p.base) < 0.01
    # One turn for the whole log: the ends are a quarter of the drift off.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(floating, "heading_offset", _one_turn(floating.heading_offset))
        assert off(Predictor(model, drifting, horizon=0.5).base) > 0.2


def _one_turn(heading_offset):
    """``heading_offset`` flattened to its mean: one turn for the whole log."""

    def once(*args):
        h = heading_offset(*args)
        return np.full_like(h, np.mean(h))

    return once
