"""Real2sim diagnosis: logs with undeclared effects, diagnosed blind.

Every test simulates a log with an effect (or two) at a joint and a size drawn at random per
seed, hands the diagnosis only the log, and checks what it names, how large, and the held-out
error. The diagnosis is never told the effect; effects outside the vocabulary are injected by
editing the simulated robot, which the diagnosis never sees.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache
from pathlib import Path

import mujoco
import numpy as np
import pytest

from humimic.cli.main import main
from humimic.real2sim import LogSettings, RobotLog, simulate_log
from humimic.real2sim.correction import apply_effect
from humimic.real2sim.diagnose import FIT_END, Diagnosis, Finding, diagnose_log
from humimic.real2sim.fitting import backlash_models
from humimic.real2sim.residual import Correction, Predictor, kstep_error
from humimic.robots import get_robot
from humimic.sim.effects import apply_to_spec, parse_injection
from humimic.sim.models import prediction_spec

DURATION = 12.0


def _model(log: RobotLog) -> mujoco.MjModel:
    return prediction_spec(get_robot("g1"), log.base_pose).compile()


def _diagnose(log: RobotLog) -> Diagnosis:
    """The diagnosis, told nothing but the log (and the robot's models)."""
    return diagnose_log(
        _model(log), log, backlash_model=backlash_models(get_robot("g1"), log.base_pose)
    )


@cache
def _clean(seed: int) -> RobotLog:
    return simulate_log(get_robot("g1"), [], LogSettings(duration=DURATION, seed=seed))


def _typical_peak_torque(log: RobotLog, joint: str) -> float:
    """95th percentile of the commanded PD torque at a joint while the robot moves."""
    j = log.joint_names.index(joint)
    c = log.command_index(log.t)
    tau = log.kp[c, j] * (log.cmd_q[c, j] - log.q[:, j]) - log.kd[c, j] * log.qd[:, j]
    return float(np.percentile(np.abs(tau[log.t > 4.0]), 95))


EXACT = [
    ("coulomb_friction", "left_knee_joint", 2.0),
    ("viscous_damping", "right_hip_pitch_joint", 1.5),
    ("armature", "left_elbow_joint", 0.05),
    ("gain_mismatch", "right_knee_joint", 0.7),
    ("delay", "left_hip_pitch_joint", 0.0205),  # MuJoCo rounds whole-step delays either way.
    ("lag", "left_knee_joint", 0.03),
    ("torque_limit", "left_knee_joint", 1.0),
    ("encoder_offset", "left_knee_joint", 0.05),
    ("payload_mass", "left_wrist_yaw_link", 1.0),
]


@pytest.mark.parametrize(("effect", "target", "value"), EXACT)
def test_predictions_express_every_effect_exactly(effect: str, target: str, value: float) -> None:
    """Noise-free logs: the prediction with the effect set on the correction, and the model
    written with the effect (model.xml), both reproduce the log to rounding."""
    settings = LogSettings(duration=3.0, q_noise=0.0, qd_noise=0.0, effort_noise=0.0)
    inj = parse_injection(f"{effect}:{target}={value}")
    log = simulate_log(get_robot("g1"), [inj], settings)
    model = _model(log)
    nominal = kstep_error(model, log).kstep_rmse_rad
    c = Correction.of(model).copy()
    index = model.body(target).id if effect == "payload_mass" else model.joint(target).id
    apply_effect(c, effect, index, value)
    assert kstep_error(c, log).kstep_rmse_rad < 1e-9 < nominal
    spec = prediction_spec(get_robot("g1"), log.base_pose)
    apply_to_spec(spec, [inj])
    written = spec.compile()
    if effect == "gain_mismatch":  # Predictions take the gains from the log's commands; the
        # written model carries the nominal gains times the ratio.
        a = written.actuator(target).id
        assert written.actuator_gainprm[a, 0] == pytest.approx(value * model.actuator_gainprm[a, 0])
        assert written.actuator_biasprm[a, 2] == pytest.approx(value * model.actuator_biasprm[a, 2])
    else:
        assert kstep_error(written, log).kstep_rmse_rad < 1e-9


def test_every_effect_acts_on_a_spec_and_on_a_compiled_model() -> None:
    """The vocabulary, the spec's delta items and the compiled model's appliers name the same
    effects; each effect is a parameter change or a structural item, never both."""
    from humimic.real2sim.correction import ON_MODEL
    from humimic.sim.delta import STRUCTURAL, Change, Structural
    from humimic.sim.effects import EFFECTS

    assert set(ON_MODEL) == set(EFFECTS)
    for name, e in EFFECTS.items():
        (item,) = e.items(("x",), 1.0)
        assert isinstance(item, Structural) == (name in STRUCTURAL)
        assert isinstance(item, Change) == (e.change is not None)


def test_play_joints_in_different_places_predict_alone_and_batched_alike() -> None:
    """Backlash candidates on different joints have the same sizes but different trees: a
    batch of them must predict each exactly as it does alone (the state layout and MuJoCo's
    data are per tree)."""
    log = simulate_log(get_robot("g1"), [], LogSettings(duration=3.0, seed=1))
    build = backlash_models(get_robot("g1"), log.base_pose)
    cs = []
    for joint in ("left_knee_joint", "waist_pitch_joint", "right_elbow_joint"):
        c = Correction.of(build((joint,)))
        apply_effect(c, "backlash", log.joint_names.index(joint), 0.04)
        cs.append(c)
    alone = [Predictor(_model(log), log).run([c])[0] for c in cs]
    batched = Predictor(_model(log), log).run(cs)
    for a, b in zip(alone, batched, strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)
    assert np.all(np.isfinite(batched)) and np.abs(batched).max() < 0.5


def _draw(effect: str, rng: np.random.Generator) -> tuple[str, float]:
    legs = ["left_knee_joint", "right_knee_joint", "left_hip_pitch_joint", "right_hip_pitch_joint"]
    if effect == "coulomb_friction":
        return str(rng.choice(legs)), float(rng.uniform(1.5, 3.0))
    if effect == "viscous_damping":
        return str(rng.choice(legs)), float(rng.uniform(1.0, 2.5))
    if effect == "armature":  # Arm joints: a leg's heavy links hide a small armature.
        return str(rng.choice(["left_elbow_joint", "right_shoulder_pitch_joint"])), float(
            rng.uniform(0.03, 0.08)
        )
    if effect == "gain_mismatch":
        return str(rng.choice([*legs, "left_elbow_joint"])), float(
            rng.choice([rng.uniform(0.6, 0.8), rng.uniform(1.3, 1.6)])
        )
    if effect == "delay":
        return str(rng.choice(legs)), float(rng.uniform(0.012, 0.035))
    if effect == "lag":
        return str(rng.choice(legs)), float(rng.uniform(0.015, 0.04))
    if effect == "encoder_offset":  # Joints whose gravity load reveals an offset.
        return str(rng.choice(["left_knee_joint", "right_hip_roll_joint"])), float(
            rng.choice([-1, 1]) * rng.uniform(0.03, 0.08)
        )
    if effect == "payload_mass":
        return str(rng.choice(["left_wrist_yaw_link", "right_ankle_roll_link"])), float(
            rng.uniform(0.5, 2.0)
        )
    if effect == "backlash":
        return str(rng.choice(["left_knee_joint", "right_elbow_joint"])), float(
            rng.uniform(0.02, 0.06)
        )
    raise AssertionError(effect)


def _held(log: RobotLog, c: Correction | mujoco.MjModel):
    return kstep_error(c, log, span=(FIT_END, 1.0))


# Four effects are diagnosed blind by other tests of the default run too, so their cases here
# run with the slow tests (`-m slow`), which keeps the default run under its 10 minutes:
# Coulomb friction and viscous damping (together on one joint: two effects at once; damping
# alone: test_real2sim.py's CLI diagnosis), delay (with a payload: two effects at once; shared
# by the whole bus: the latency test) and a payload (with a delay; on a wrist, checked by the
# torque regressor: test_real2sim.py).
_ALSO_ELSEWHERE = pytest.mark.slow


@pytest.mark.parametrize("seed", [0])
@pytest.mark.parametrize(
    "effect",
    [
        pytest.param("coulomb_friction", marks=_ALSO_ELSEWHERE),
        pytest.param("viscous_damping", marks=_ALSO_ELSEWHERE),
        "armature",
        "gain_mismatch",
        pytest.param("delay", marks=_ALSO_ELSEWHERE),
        "lag",
        "encoder_offset",
        pytest.param("payload_mass", marks=_ALSO_ELSEWHERE),
        "torque_limit",
        "backlash",
    ],
)
def test_diagnosis_names_and_sizes_an_undeclared_effect(effect: str, seed: int) -> None:
    rng = np.random.default_rng([seed, sum(map(ord, effect))])
    if effect == "torque_limit":  # A limit the excitation reaches often enough to show.
        target = str(rng.choice(["left_knee_joint", "left_hip_pitch_joint", "right_elbow_joint"]))
        value = float(rng.uniform(0.6, 0.8)) * _typical_peak_torque(_clean(seed), target)
    else:
        target, value = _draw(effect, rng)
    log = simulate_log(
        get_robot("g1"), [parse_injection(f"{effect}:{target}={value}")],
        LogSettings(duration=DURATION, seed=seed),
    )  # fmt: skip
    model = _model(log)
    d = _diagnose(log)
    assert [(f.effect, f.target) for f in d.claimed] == [(effect, target)], d.findings[:4]
    assert d.claimed[0].value == pytest.approx(value, rel=0.3)
    before, after = _held(log, model), _held(log, d.correction or model)
    joints = [log.joint_names.index(n) for n in d.claimed[0].joints]
    # On the held-out 30%: the effect's joints' error at least halved, the whole robot's lower.
    assert np.sum(after.per_joint[joints] ** 2) <= 0.25 * np.sum(before.per_joint[joints] ** 2)
    assert after.kstep_rmse_rad < before.kstep_rmse_rad


def test_diagnosis_claims_nothing_on_a_clean_log() -> None:
    log = _clean(11)
    d = _diagnose(log)
    assert d.claimed == []


@pytest.mark.parametrize(
    "pair",
    [
        ("coulomb_friction:left_knee_joint=2.0", "viscous_damping:left_knee_joint=1.5"),
        ("delay:right_knee_joint=0.02", "payload_mass:left_wrist_yaw_link=0.8"),
    ],
)
def test_diagnosis_finds_two_effects_at_once(pair: tuple[str, str]) -> None:
    injections = [parse_injection(p) for p in pair]
    log = simulate_log(get_robot("g1"), injections, LogSettings(duration=DURATION, seed=5))
    model = _model(log)
    d = _diagnose(log)
    found = {(f.effect, f.target): f.value for f in d.claimed}
    assert set(found) == {(i.effect, i.targets[0]) for i in injections}, d.findings[:5]
    for inj in injections:
        assert found[(inj.effect, inj.targets[0])] == pytest.approx(inj.value, rel=0.3)
    before, after = _held(log, model), _held(log, d.correction or model)
    assert after.kstep_rmse_rad < 0.5 * before.kstep_rmse_rad


def test_a_latency_of_the_whole_bus_is_one_shared_delay() -> None:
    """Every command acts 25 ms after the log says it was sent. The latency is made by moving
    the log's command stamps (not by the vocabulary's delay): the diagnosis claims one delay
    shared by all joints, not a delay joint by joint."""
    clean = _clean(3)
    latency = 0.025
    log = replace(clean, t_cmd=clean.t_cmd - latency)
    model = _model(log)
    d = _diagnose(log)
    assert [(f.effect, f.target) for f in d.claimed] == [("delay", "all_joints")], d.findings[:4]
    (f,) = d.claimed
    assert f.value == pytest.approx(latency, rel=0.1)
    assert f.acts_on == log.joint_names
    before, after = _held(log, model), _held(log, d.correction or model)
    assert after.kstep_rmse_rad < 0.25 * before.kstep_rmse_rad


def test_a_group_finding_acts_on_its_joints_in_the_report_and_the_physics() -> None:
    from humimic.real2sim.report import _effect_entry
    from humimic.real2sim.result import SysidResult

    legs = ("left_knee_joint", "right_knee_joint")
    f = Finding(effect="delay", target="limbs_of_left_hip_pitch_joint+right_hip_pitch_joint",
                joints=legs, value=0.03, confidence=0.9, error_reduction=0.8, targets=legs)  # fmt: skip
    entry = _effect_entry(f)
    assert entry["joints"] == list(legs) and entry["group"] == f.target
    err = {"kstep_rmse_rad": 0.01}
    report = {"effects": [entry], "error_before": err, "error_after": err}
    physics = SysidResult.of(report).physics(name="x", robot="g1")
    assert [(i.effect, i.targets, i.value) for i in physics.effects] == [("delay", legs, 0.03)]
    one = _effect_entry(replace(f, target="left_knee_joint", joints=legs[:1], targets=()))
    assert one["joints"] == ["left_knee_joint"] and "group" not in one


def test_an_effect_refitted_to_nothing_has_no_size() -> None:
    """The final refit can move an effect back to "no effect" when the others explain its
    joints (a 0.0 ms delay on all joints was claimed on the backpack's log): such a value is
    no finding."""
    from humimic.real2sim.candidates import Candidate, is_sized

    delay = Candidate(effect="delay", index=0, joints=np.arange(3), lo=0.0, hi=0.05, none=0.0,
                  probe=0.01, group=(0, 1, 2), label="all_joints")  # fmt: skip
    assert not is_sized(delay, 0.0) and not is_sized(delay, 0.0004) and is_sized(delay, 0.003)
    limit = Candidate(effect="torque_limit", index=0, joints=np.arange(1), lo=1.0, hi=20.0,
                  none=20.0, probe=16.0)  # fmt: skip
    assert not is_sized(limit, 19.9) and is_sized(limit, 15.0)


def test_an_offset_the_log_cannot_reveal_is_declared_not_guessed() -> None:
    """A wrist yaw encoder offset: the drive tracks the encoder, and the hand's gravity load
    does not depend on the yaw angle, so the log cannot show it."""
    log = simulate_log(get_robot("g1"), [parse_injection("encoder_offset:left_wrist_yaw_joint=0.05")],
                       LogSettings(duration=DURATION, seed=2))  # fmt: skip
    d = _diagnose(log)
    assert d.claimed == []
    (statement,) = [s for s in d.not_identifiable if s.effect == "encoder_offset"]
    assert "left_wrist_yaw_joint" in statement.joints
    assert "knee" not in " ".join(statement.joints)  # Loaded joints can be identified.


def _cable_spring(spec: mujoco.MjSpec) -> None:
    """Outside the vocabulary: a cable pulling the left knee, a cubic spring about 0.8 rad."""
    j = spec.joint("left_knee_joint")
    j.stiffness = np.array([0.0, 0.0, 300.0])
    j.springref = 0.8


def test_an_effect_outside_the_vocabulary_is_unexplained_and_learned(tmp_path: Path) -> None:
    from humimic.real2sim import write_robot_log
    from humimic.real2sim.actuator_net import ResidualActuatorNet

    log = simulate_log(get_robot("g1"), [], LogSettings(duration=16.0, seed=4), edit=_cable_spring)
    path = write_robot_log(log, tmp_path / "cable.mcap")
    out = tmp_path / "diag"
    assert main(["sysid", "diagnose", str(path), "--out-dir", str(out)]) == 0
    r = json.loads((out / "report.json").read_text())
    before = r["error_before"]["kstep_rmse_rad"]
    after = r["error_after"]["kstep_rmse_rad"]
    # Either no vocabulary effect is claimed and the log is unexplained, or what is claimed
    # removes most of the error.
    assert r["unexplained"] or after < 0.5 * before
    assert "left_knee_joint" in r["unexplained_joints"]
    net = r["residual_model"]
    assert net is not None and Path(net["path"]).exists() and net["improves"]
    assert (
        net["error_after"]["per_joint"]["left_knee_joint"]
        < 0.5 * (r["error_after"]["per_joint"]["left_knee_joint"])
    )
    # The saved network loads and predicts the same held-out error.
    model = _model(log)
    loaded = ResidualActuatorNet.load(net["path"])
    held = Predictor(model, log, span=(FIT_END, 1.0))
    c = Correction.of(model)
    for e in r["effects"]:
        if e["confidence"] >= 0.5:
            idx = model.body(e["body"]).id if "body" in e else model.joint(e["joints"][0]).id
            apply_effect(c, e["effect"], idx, e["params"]["value"])
    again = held.report(held.run_with_torque(c, loaded.torque, loaded.config.history))
    assert again.kstep_rmse_rad == pytest.approx(net["error_after"]["kstep_rmse_rad"], rel=1e-6)
    assert (out / "residual_per_joint.png").stat().st_size > 1000
