"""The floor-log checks of issue 26's twelfth session, as one rerunnable script.

1. ``floor``: a clean 40 s deployment log (seed 11, the ``sysid_independent`` logs): each
   joint's nominal held-out error, how far its prediction moves when every window's base
   state is off along one axis (``noise_floor``'s probes), the fitted per-joint floor, and
   what the report calls unexplained.
2. ``short``: 8 s deployment logs: clean (seed 5) and a cubic spring on the left knee made
   here with MuJoCo's joint stiffness (seeds 3, 4, 6): claims, their ``stands_out``, and the
   joints called unexplained.
3. ``gyro``: the 6 s standing log of the floor tests (seed 2) with (30, -20, 10) mrad/s added
   to its gyro, with and without motion capture: the bias found, and the k-step error of the
   clean log, of the biased log as read before (bias not removed) and as read now; and a
   gyro turning at 0.3 rad/s with a 10 mrad/s bias against a reference with a 2 s gap.
4. ``tilt`` (thirteenth session): 6 s standing logs (seeds 2, 3, 7) and a 40 s one (seed 11)
   read by an IMU mounted with a roll and pitch (scipy turns its frame, gyro and
   accelerometer), with and without motion capture: the tilt found (and whether the base
   estimate names it), and the k-step error of the clean log, of the tilted log with the
   tilt left in and with it removed.
5. ``soft`` (thirteenth session): deployment logs whose foot spheres' contact time constant
   is set here in the spec (not through the vocabulary), on both feet or one, softer and
   harder than MuJoCo's 0.02 s: what the diagnosis claims, the held-out error before and
   after, and the diagnosis's time.
6. ``solimp`` (fourteenth session): a softness the vocabulary does not express: the foot
   spheres' contact impedance (MuJoCo's solimp: dmin, dmax, width; set here in the spec,
   their time constant left at 0.02 s), on both feet or one. The vocabulary's softness
   edits the time constant only: what the diagnosis claims for a softness of another form.
7. ``slip`` (fourteenth session): a slippery floor: the foot spheres' sliding friction set
   here in the spec (0.6 in the model), on both feet or one, 8-40 s, and clean logs: what
   the diagnosis claims (``contact_friction``), the held-out error before and after.
8. ``slip_truth`` (fourteenth session): on slippery logs (one noise-free), the held-out error
   of joint positions and of drive torques with the nominal model and with the true friction:
   why ``contact_friction`` is scored on positions only.

Prints one JSON object per part. Usage: .venv/bin/python benchmarks/sysid_floor_checks.py
[--only floor|short|gyro|tilt|soft|solimp|slip|slip_truth]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path
from unittest.mock import patch

import numpy as np

from humimic.real2sim import LogSettings, floating, simulate_log, write_robot_log
from humimic.real2sim.correction import Correction
from humimic.real2sim.fitting import BASE_PROBES, FIT_END, noise_floor
from humimic.real2sim.floating import gyro_bias, prediction_step
from humimic.real2sim.report import load_robot_log, run_diagnosis
from humimic.real2sim.residual import Predictor
from humimic.real2sim.simulate import tilt_imu
from humimic.robots import get_robot
from humimic.sim.models import floating_prediction_spec

TOP = 6


def _cable(spec) -> None:
    knee = spec.joint("left_knee_joint")
    knee.stiffness = np.array([0.0, 0.0, 10.0])
    knee.springref = 0.8


def _top(names: tuple[str, ...], v: np.ndarray, scale: float = 1e3) -> dict[str, float]:
    order = np.argsort(-v)[:TOP]
    return {names[j]: round(float(v[j]) * scale, 3) for j in order}


def floor_part(tmp: Path) -> dict:
    log = simulate_log(get_robot("g1"), [], LogSettings(duration=40.0, base="floating", seed=11))
    path = write_robot_log(log, tmp / "clean.mcap")
    _, model, log = load_robot_log(path)
    held = Predictor(model, log, horizon=0.5, span=(0.7, 1.0))
    c = Correction.of(model)
    res0 = held.run([c])[0]
    names = log.joint_names
    error = np.sqrt(np.mean(res0**2, axis=(0, 1)))
    base = held.base
    assert base is not None
    moved: dict[str, dict[str, float]] = {}
    axes = {"linear velocity": [(1, 0, "x"), (1, 1, "y"), (1, 2, "z")],
            "angular velocity": [(1, 3, "x"), (1, 4, "y"), (1, 5, "z")],
            "height": [(0, 2, "z")]}  # fmt: skip
    for name, sigma in BASE_PROBES:
        for which, i, axis in axes[name]:
            qpos, qvel = base.qpos.copy(), base.qvel.copy()
            (qpos, qvel)[which][:, i] += sigma
            d = np.sqrt(np.mean((held.with_base(qpos, qvel).run([c])[0] - res0) ** 2, axis=(0, 1)))
            moved[f"{name} {axis} +{sigma:g}"] = {
                **_top(names, d),
                "median": 1e3 * float(np.median(d)),
            }
    floor = noise_floor(held, c, res0)
    r = run_diagnosis(path, tmp / "diag").report
    return {"part": "floor", "log": "clean, 40 s, seed 11", "unit": "mrad",
            "nominal_error": {**_top(names, error), "median": 1e3 * float(np.median(error))},
            "moved_by_base_probe": moved,
            "floor": _top(names, floor), "error_over_floor": _top(names, error / floor, 1.0),
            "unexplained": r["unexplained"], "unexplained_joints": r["unexplained_joints"],
            "claimed": [e["effect"] for e in r["effects"] if e["confidence"] >= 0.5]}  # fmt: skip


def short_part(tmp: Path) -> dict:
    rows = []
    for name, edit, seed in (("clean", None, 5), ("knee spring", _cable, 3),
                             ("knee spring", _cable, 4), ("knee spring", _cable, 6)):  # fmt: skip
        log = simulate_log(get_robot("g1"), [], LogSettings(duration=8.0, base="floating", seed=seed),
                           edit=edit)  # fmt: skip
        r = run_diagnosis(write_robot_log(log, tmp / f"s{seed}.mcap"), tmp / f"d{seed}").report
        rows.append({"log": name, "seed": seed,
                     "claimed": [{"effect": e["effect"], "on": e.get("body") or e.get("group")
                                  or e["joints"][0], "value": round(e["params"]["value"], 3),
                                  "confidence": round(e["confidence"], 2),
                                  "stands_out": e["stands_out"], "partial": e["partial"]}
                                 for e in r["effects"] if e["confidence"] >= 0.5],
                     "unexplained": r["unexplained"], "unexplained_joints": r["unexplained_joints"],
                     "heldout_mrad": [1e3 * r["error_before"]["kstep_rmse_rad"],
                                      1e3 * r["error_after"]["kstep_rmse_rad"]]})  # fmt: skip
    return {"part": "short", "logs": rows}


def gyro_part() -> dict:
    log = simulate_log(get_robot("g1"), [], LogSettings(duration=6.0, base="floating", seed=2))
    model = floating_prediction_spec(get_robot("g1")).compile()
    model.opt.timestep = prediction_step(log)
    bias = np.array([0.03, -0.02, 0.01])
    rows = []
    for mocap in (True, False):
        clean = log if mocap else replace(log, mocap=None)
        assert clean.imu is not None
        biased = replace(clean, imu=replace(clean.imu, gyro_b=clean.imu.gyro_b + bias))

        def err(lg, model=model) -> float:
            return (
                1e3 * Predictor(model, lg, horizon=0.5).error(Correction.of(model)).kstep_rmse_rad
            )

        found = Predictor(model, biased, horizon=0.5).base
        assert found is not None
        with patch.object(floating, "GYRO_BIAS_NOTE", np.inf):  # As read before: left in.
            kept = err(biased)
        rows.append({"mocap": mocap, "added_mrad_s": (1e3 * bias).tolist(),
                     "base_estimate": found.source.split("; ", 1)[-1],
                     "kstep_mrad": {"clean": err(clean), "biased, not removed": kept,
                                    "biased, removed": err(biased)}})  # fmt: skip
    t = np.arange(0.0, 6.0, 0.005)
    turned = 0.3 * t + np.where(t > 4.0, 1.0, 0.0)
    track = np.stack([np.cos(turned / 2), 0 * t, 0 * t, np.sin(turned / 2)], axis=1)
    seen = (t < 2.0) | (t > 4.0)
    b, _ = gyro_bias(t[seen], track[seen], t, np.tile([0.01, 0.0, 0.3], (t.size, 1)))
    return {
        "part": "gyro",
        "standing": rows,
        "turning_0.3_rad_s_gap_2_s": {
            "added_mrad_s": [10.0, 0.0, 0.0],
            "found_mrad_s": (1e3 * b).round(3).tolist(),
        },
    }


def tilt_part() -> dict:
    model = floating_prediction_spec(get_robot("g1")).compile()
    found: list = []
    estimate = floating._segment_mean

    def spy(t, x):
        out = estimate(t, x)
        found.append(out)
        return out

    rows = []
    floating._segment_mean = spy
    try:
        for seed, duration in ((2, 6.0), (3, 6.0), (7, 6.0), (11, 40.0)):
            settings = LogSettings(duration=duration, base="floating", seed=seed)
            log = simulate_log(get_robot("g1"), [], settings)
            model.opt.timestep = prediction_step(log)

            def err(lg, model=model) -> float:
                p = Predictor(model, lg, horizon=0.5, span=(0.7, 1.0))
                return 1e3 * p.error(Correction.of(model)).kstep_rmse_rad

            for mocap in (True, False):
                clean = log if mocap else replace(log, mocap=None)
                for degrees in ((0.0, 0.0), (0.4, 0.3), (2.0, -3.0), (12.0, 5.0)):
                    tilted = tilt_imu(clean, *degrees)
                    found.clear()
                    base = Predictor(model, tilted, horizon=0.5).base
                    assert base is not None
                    e, se = found[0]
                    with patch.object(floating, "MOUNT_TILT_NOTE", np.inf):  # Left in.
                        kept = err(tilted)
                    rows.append({"seed": seed, "seconds": duration, "mocap": mocap,
                                 "tilt_deg": list(degrees),
                                 "found_deg": np.degrees(e[:2]).round(3).tolist(),
                                 "se_deg": np.degrees(se[:2]).round(4).tolist(),
                                 "removed": "mount tilt" in base.source,
                                 "kstep_mrad": {"clean": round(err(clean), 3),
                                                "tilt left in": round(kept, 3),
                                                "as read now": round(err(tilted), 3)}})  # fmt: skip
    finally:
        floating._segment_mean = estimate
    return {"part": "tilt", "held_out_kstep": "last 30 % of each log", "rows": rows}


SOFT_CASES = (  # (time constant [s], feet, seed, seconds); the first is the default test's.
    (0.1, ("left_ankle_roll_link", "right_ankle_roll_link"), 6, 8.0),
    (0.06, ("left_ankle_roll_link", "right_ankle_roll_link"), 3, 8.0),
    (0.15, ("left_ankle_roll_link", "right_ankle_roll_link"), 4, 8.0),
    (0.1, ("left_ankle_roll_link",), 5, 8.0),
    (0.01, ("left_ankle_roll_link", "right_ankle_roll_link"), 7, 8.0),
    (0.08, ("left_ankle_roll_link", "right_ankle_roll_link"), 11, 40.0),
)


BOTH = ("left_ankle_roll_link", "right_ankle_roll_link")
SOLIMP_CASES = (  # (solimp dmin, dmax, width [m]; feet, seed, seconds); MuJoCo's: 0.9, 0.95, 0.001.
    ((0.5, 0.7, 0.005), BOTH, 6, 8.0),
    ((0.7, 0.8, 0.01), BOTH, 4, 8.0),
    ((0.3, 0.5, 0.005), BOTH, 3, 8.0),
    ((0.5, 0.7, 0.005), ("left_ankle_roll_link",), 5, 8.0),
    ((0.5, 0.7, 0.005), BOTH, 11, 40.0),
)


SLIP_CASES = (  # (sliding friction, feet, seed, seconds); 0.6: the model's own, a clean log.
    (0.07, BOTH, 6, 8.0),  # The default test's.
    (0.07, BOTH, 3, 8.0),
    (0.08, BOTH, 5, 8.0),
    (0.06, BOTH, 4, 8.0),
    (0.07, ("left_ankle_roll_link",), 2, 8.0),
    (0.1, BOTH, 6, 8.0),
    (0.1, BOTH, 9, 8.0),
    (0.1, BOTH, 8, 12.0),
    (0.1, BOTH, 4, 16.0),
    (0.1, BOTH, 11, 40.0),
    (0.15, BOTH, 7, 16.0),
    (0.2, BOTH, 3, 8.0),
    (0.6, BOTH, 5, 8.0),
    (0.6, BOTH, 11, 40.0),
)


def _sphere_edit(feet: tuple[str, ...], solref=None, solimp=None, friction=None):
    """A spec edit that sets the foot spheres' contact parameters (this script's own code)."""
    import mujoco

    def edit(spec) -> None:
        for foot in feet:
            for g in spec.body(foot).geoms:
                if g.type == mujoco.mjtGeom.mjGEOM_SPHERE:
                    if solref is not None:
                        g.solref = np.array(solref, dtype=np.float64)
                    if solimp is not None:
                        g.solimp = np.array([*solimp, 0.5, 2.0], dtype=np.float64)
                    if friction is not None:
                        g.friction = np.array([friction, *np.asarray(g.friction)[1:]])

    return edit


def _clean_kstep(settings: LogSettings, tmp: Path) -> float:
    """The nominal model's held-out k-step error [rad] on the same log without the change
    (what a perfect correction would come down to)."""
    path = write_robot_log(simulate_log(get_robot("g1"), [], settings), tmp / "clean.mcap")
    _, model, log = load_robot_log(path)
    held = Predictor(model, log, horizon=0.5, span=(FIT_END, 1.0))
    return held.error(Correction.of(model)).kstep_rmse_rad


def _contact_rows(tmp: Path, cases, label: str, edit_of) -> list[dict]:
    rows = []
    for what, feet, seed, duration in cases:
        settings = LogSettings(duration=duration, base="floating", seed=seed)
        log = simulate_log(get_robot("g1"), [], settings, edit=edit_of(what, feet))
        clean = _clean_kstep(settings, tmp)
        name = f"{label}_{'_'.join(map(str, np.atleast_1d(what)))}_{len(feet)}_{seed}"
        r = run_diagnosis(write_robot_log(log, tmp / f"{name}.mcap"), tmp / name).report
        rows.append({label: what, "feet": list(feet), "seed": seed, "seconds": duration,
                     "claimed": [(e["effect"], e.get("group") or e.get("body")
                                  or e.get("joints"), round(e["params"]["value"], 4),
                                  round(e["confidence"], 2), e["partial"])
                                 for e in r["effects"] if e["confidence"] >= 0.5],
                     "kstep_mrad": [round(1e3 * r["error_before"]["kstep_rmse_rad"], 3),
                                    round(1e3 * r["error_after"]["kstep_rmse_rad"], 3)],
                     "clean_log_kstep_mrad": round(1e3 * clean, 3),
                     "unexplained": r["unexplained_joints"],
                     "diagnosis_s": round(r["seconds"], 1)})  # fmt: skip
    return rows


def soft_part(tmp: Path) -> dict:
    rows = _contact_rows(tmp, SOFT_CASES, "time_constant_s",
                      lambda tc, feet: _sphere_edit(feet, solref=(tc, 1.0)))  # fmt: skip
    return {"part": "soft", "rows": rows}


def solimp_part(tmp: Path) -> dict:
    rows = _contact_rows(tmp, SOLIMP_CASES, "solimp",
                      lambda imp, feet: _sphere_edit(feet, solimp=imp))  # fmt: skip
    return {"part": "solimp", "rows": rows}


def slip_part(tmp: Path) -> dict:
    rows = _contact_rows(tmp, SLIP_CASES, "friction",
                      lambda mu, feet: _sphere_edit(feet, friction=mu))  # fmt: skip
    return {"part": "slip", "rows": rows}


SLIP_TRUTH_CASES = (  # (friction, seed, seconds, noise-free)
    (0.1, 6, 8.0, True),
    (0.1, 11, 40.0, False),
    (0.08, 5, 8.0, False),
)


def slip_truth_part(tmp: Path) -> dict:
    """What the true friction does to the predictions: the held-out error of joint positions
    and of drive torques with the nominal model and with the log's own friction set on both
    soles (the vocabulary's effect at the true value), per log."""
    from humimic.real2sim.correction import apply_effect

    rows = []
    for mu, seed, duration, noise_free in SLIP_TRUTH_CASES:
        settings = LogSettings(duration=duration, base="floating", seed=seed)
        if noise_free:
            settings = replace(settings, q_noise=0.0, qd_noise=0.0, effort_noise=0.0,
                               gyro_noise=0.0, acc_noise=0.0, quat_noise=0.0, mocap_noise=0.0)  # fmt: skip
        log = simulate_log(get_robot("g1"), [], settings, edit=_sphere_edit(BOTH, friction=mu))
        _, model, log = load_robot_log(write_robot_log(log, tmp / "truth.mcap"))
        held = Predictor(model, log, horizon=0.5, span=(FIT_END, 1.0))
        nominal = Correction.of(model)
        true = nominal.copy()
        for foot in BOTH:
            apply_effect(true, "contact_friction", model.body(foot).id, mu)
        res = held.run([nominal, true], effort=True)  # (2, W, S, J, 2)
        rms = np.sqrt(np.mean(res**2, axis=(1, 2, 3)))
        rows.append({"friction": mu, "seed": seed, "seconds": duration, "noise_free": noise_free,
                     "position_mrad": [round(1e3 * float(rms[0, 0]), 3),
                                       round(1e3 * float(rms[1, 0]), 3)],
                     "torque_nm": [round(float(rms[0, 1]), 4), round(float(rms[1, 1]), 4)]})  # fmt: skip
    return {"part": "slip_truth", "nominal_then_true": True, "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--only",
        choices=["floor", "short", "gyro", "tilt", "soft", "solimp", "slip", "slip_truth"],
        default=None,
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = Path(scratch)
        if args.only in (None, "floor"):
            print(json.dumps(floor_part(tmp)), flush=True)
        if args.only in (None, "short"):
            print(json.dumps(short_part(tmp)), flush=True)
        if args.only in (None, "gyro"):
            print(json.dumps(gyro_part()), flush=True)
        if args.only in (None, "tilt"):
            print(json.dumps(tilt_part()), flush=True)
        if args.only in (None, "soft"):
            print(json.dumps(soft_part(tmp)), flush=True)
        if args.only in (None, "solimp"):
            print(json.dumps(solimp_part(tmp)), flush=True)
        if args.only in (None, "slip"):
            print(json.dumps(slip_part(tmp)), flush=True)
        if args.only in (None, "slip_truth"):
            print(json.dumps(slip_truth_part(tmp)), flush=True)


if __name__ == "__main__":
    main()
