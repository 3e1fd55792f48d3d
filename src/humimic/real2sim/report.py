"""``humimic sysid diagnose``: diagnose a log file, write the corrected model and the report.

``DIR/model.xml`` (the full robot, floating base like the nominal, with the claimed effects),
``DIR/report.json`` (the issue's format, plus what was searched and what cannot be decided),
``DIR/report.md`` with plots (``DIR/*.png``), and ``DIR/residual_net.pt`` when a large share of
the error is left unexplained.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready
from humimic.real2sim.correction import Correction
from humimic.real2sim.diagnose import (
    CLAIM,
    FIT_END,
    NOT_SEARCHED,
    PARTIAL,
    SEARCHED,
    Diagnosis,
    Finding,
    diagnose_log,
)
from humimic.real2sim.fitting import backlash_models, fit_predictors, noise_floor
from humimic.real2sim.floating import prediction_step
from humimic.real2sim.report_plots import write_plots
from humimic.real2sim.residual import KStepError, Predictor
from humimic.real2sim.result import SYSID_SCHEMA, SysidResult
from humimic.real2sim.robotlog import RobotLog, parse_base_pose, read_robot_log
from humimic.robots.registry import RobotConfig
from humimic.sim.effects import EFFECTS, Injection, apply_to_spec
from humimic.sim.joints import JointMap
from humimic.sim.models import prediction_spec
from humimic.sim.physics import write_physics

UNEXPLAINED = 0.5
"""Share of the held-out error above the noise floor that, when left, makes a log unexplained."""


def load_fixed_base_log(path: Path) -> tuple[RobotConfig, mujoco.MjModel, RobotLog]:
    """Robot, compiled fixed-base prediction model and log of a robot log file.

    Raises:
        InputError: The file is not a fixed-base robot log of a registered robot (see
            :func:`~humimic.real2sim.robotlog.read_robot_log` for what a log must hold),
            naming the file.
    """
    from humimic.formats.mcap import read_mcap
    from humimic.robots import get_robot

    meta = read_mcap(path, topics=[]).meta("robot")
    robot = get_robot(meta.get("name", ""), f"{path}: metadata robot.name")
    if meta.get("base") != "fixed":
        raise InputError(
            f"{path}: metadata robot.base is {meta.get('base')!r}, expected fixed (a robot "
            "hanging in a gantry)" + ("" if meta.get("base") == "floating" else
                                      " or floating (on the floor)")
        )  # fmt: skip
    base_pose = parse_base_pose(meta, Path(path))
    model = prediction_spec(robot, base_pose).compile()
    names = tuple(model.joint(j).name for j in range(model.njnt))
    return robot, model, read_robot_log(path, names)


def load_robot_log(path: Path) -> tuple[RobotConfig, mujoco.MjModel, RobotLog]:
    """Robot, compiled prediction model and log of a robot log file, fixed base (a gantry) or
    floating (a robot on the floor, with ``/imu``).

    Raises:
        InputError: The file is not a robot log of a registered robot, or a floating-base
            log without ``/imu``, naming the file.
    """
    from humimic.formats.mcap import read_mcap
    from humimic.robots import get_robot
    from humimic.sim.models import floating_prediction_spec

    meta = read_mcap(path, topics=[]).meta("robot")
    if meta.get("base") != "floating":
        return load_fixed_base_log(path)
    robot = get_robot(meta.get("name", ""), f"{path}: metadata robot.name")
    model = floating_prediction_spec(robot).compile()
    log = read_robot_log(path, JointMap.of(model).names)
    if log.imu is None:
        raise InputError(
            f"{path}: a floating-base log needs topic /imu (the base's orientation and angular "
            'velocity) and metadata robot.imu_site for predictions (docs/real2sim.md, "Logs")'
        )
    model.opt.timestep = prediction_step(log)
    return robot, model, log


def _effect_entry(f: Finding) -> dict:
    where: dict[str, Any] = {"joints": list(f.acts_on)}
    if f.on_body:
        where = {"bodies": list(f.acts_on)} if f.targets else {"body": f.target}
    if f.targets:
        where["group"] = f.target
    return {
        "effect": f.effect,
        **where,
        "params": {"value": f.value, "unit": EFFECTS[f.effect].unit},
        "confidence": f.confidence,
        "error_reduction": f.error_reduction,
        "scored_on": list(f.joints),
        "stands_out": f.stands_out,
        "partial": f.partial,
    }


def payload_regression(robot: RobotConfig, log: RobotLog, body: str) -> dict:
    """A payload on ``body`` sized by linear least squares on Pinocchio's torque regressor over
    the fit part of the log (:func:`humimic.real2sim.pinocchio.identify_payload`): a second method,
    with no search and no simulation, beside the diagnosis's k-step fit. The torques are the
    logged efforts, or the drives' PD law from the held commands when the log has none.

    Returns:
        ``mass`` and ``mass_std`` [kg], ``rows`` used and ``seconds``; or ``error``, why the
        log cannot size it (no sample moves the joints that carry the body).
    """
    from humimic.real2sim.pinocchio import PinocchioRobot, accelerations, identify_payload
    from humimic.robots import nominal_model

    t0 = time.perf_counter()
    pr = PinocchioRobot.from_mujoco(nominal_model(robot), base_pose=log.base_pose)
    qdd, valid = accelerations(log.t, log.qd, log.t_cmd)
    fit = valid & (log.t < log.t[0] + FIT_END * (log.t[-1] - log.t[0]))
    if log.effort is not None:
        tau, source = log.effort, "logged effort"
    else:
        i = log.command_index(log.t)
        tau = log.kp[i] * (log.cmd_q[i] - log.q) + log.kd[i] * (log.cmd_qd[i] - log.qd)
        tau, source = tau + log.cmd_tau[i], "PD law of the commands"
    try:
        f = identify_payload(pr, log.q, log.qd, qdd, tau, body, samples=fit)
    except InputError as e:
        return {"method": "torque regressor (Pinocchio)", "error": str(e)}
    return {"method": "torque regressor (Pinocchio), instrumental variables", "torques": source,
            "mass": f.mass, "mass_std": f.mass_std, "rows": f.rows,
            "seconds": time.perf_counter() - t0}  # fmt: skip


def _unexplained(
    before: KStepError, after: KStepError, noise: np.ndarray
) -> tuple[float, np.ndarray]:
    """Share of the error above the noise floor (twice each joint's ``noise``, see
    :func:`~humimic.real2sim.fitting.noise_floor`) left after the correction, and the joints
    that still stand out."""
    floor = 2.0 * noise

    def excess(e: np.ndarray) -> float:
        return float(np.sum(np.maximum(e**2 - floor**2, 0.0)))

    share = excess(after.per_joint) / excess(before.per_joint) if excess(before.per_joint) else 0.0
    standout = (after.per_joint > 1.5 * floor) & (after.per_joint > 0.5 * before.per_joint)
    return share, standout


def run_diagnosis(
    log_path: Path,
    out_dir: Path,
    *,
    horizon: float = 0.5,
    residual_net: Literal["auto", "always", "never"] = "auto",
) -> SysidResult:
    """Diagnose ``log_path``; write model, report and plots into ``out_dir``. Returns what
    was found (``report.json``'s content, typed).

    Raises:
        InputError: A log the diagnosis cannot use, a bad ``horizon`` or an output that
            cannot be written, before anything is written (``out_dir`` is not even created).
    """
    t0 = time.perf_counter()
    if residual_net not in ("auto", "always", "never"):
        raise InputError(f"--residual-net {residual_net!r}: choose auto, always or never")
    robot, model, log = load_robot_log(log_path)
    floating = log.base == "floating"
    if floating and residual_net == "always":
        raise InputError(
            f"--residual-net always: {log_path} is a floating-base log, and the residual "
            "actuator network is trained on inverse dynamics, which on the floor needs the "
            "contact forces the log lacks (gantry logs only so far)"
        )
    # Every check on the log and the horizon comes before the output folder is made.
    held = Predictor(model, log, horizon=horizon, span=(FIT_END, 1.0))
    fit_predictors(model, log, horizon, held.track)
    out = out_dir
    _check_out_dir(out, log_path)
    nominal = Correction.of(model)
    unsearched = ("backlash",) if floating else ("contact_softness", "contact_friction")
    before = held.error(nominal)
    # Backlash needs a second hinge per joint in the prediction model; on the floor that
    # model is not built yet, so backlash is searched on gantry logs only.
    plays = None if floating else backlash_models(robot, log.base_pose)
    diagnosis = diagnose_log(
        nominal, log, horizon=horizon, backlash_model=plays, base_track=held.track
    )
    corrected = diagnosis.correction or nominal
    after = held.error(corrected)
    # The second estimate of each claimed payload, before anything is written.
    effects = _effect_entries(robot, log, diagnosis)
    names = log.joint_names
    noise = noise_floor(held, nominal, before.residual)
    share, standout = _unexplained(before, after, noise)
    # Unexplained: much of the excess error is left, and some joint still stands out (a clean
    # log's small excess over the median joint is noise, not something missing).
    unexplained = share > UNEXPLAINED and bool(standout.any())

    net_entry, net_error = None, None
    if not floating and (residual_net == "always" or (residual_net == "auto" and unexplained)):
        net_entry, net_error = _fit_residual_net(corrected, log, held, after, out)
    _export_model(robot, diagnosis, out / "model.xml")
    plots = write_plots(out, log, nominal, corrected, diagnosis, before, after, net_error, held)
    report = {
        "schema": SYSID_SCHEMA,
        "robot": robot.name,
        "log": str(log_path),
        "error_before": before.as_report(names),
        "error_after": after.as_report(names),
        "effects": effects,
        "unexplained": unexplained,
        "unexplained_share": share,
        "unexplained_joints": [n for n, s in zip(names, standout, strict=True) if s],
        "noise_floor_rad": dict(zip(names, noise.tolist(), strict=True)),
        "residual_model": net_entry,
        "not_identifiable": [
            {"effect": s.effect, "joints": list(s.joints), "reason": s.reason}
            for s in diagnosis.not_identifiable
        ],
        "base": log.base,
        "base_estimate": held.base.source if held.base is not None else None,
        # Backlash's play joint is not built into the floor model; a gantry has no floor.
        "searched_effects": [e for e in SEARCHED if e not in unsearched],
        "not_searched_effects": [*NOT_SEARCHED, *unsearched],
        "plots": [p.name for p in plots],
        "seconds": time.perf_counter() - t0,
    }
    return _write_report(out, log_path, robot, report, diagnosis, plots)


def _write_report(
    out: Path, log_path: Path, robot: RobotConfig, report: dict, diagnosis: Diagnosis,
    plots: list[Path],
) -> SysidResult:  # fmt: skip
    """report.json, report.md and physics.yaml (the claims, for ``--physics``)."""
    atomic_write_text(out / "report.json", json.dumps(json_ready(report), indent=2) + "\n")
    atomic_write_text(out / "report.md", _markdown(log_path, robot, report, diagnosis, plots))
    result = SysidResult.of(json_ready(report), str(out / "report.json"))
    write_physics(result.physics(name="sysid", robot=robot.name), out / "physics.yaml")
    return result


OUTPUTS = ("model.xml", "report.json", "report.md", "physics.yaml", "residual_net.pt")
"""What a diagnosis writes into its folder (with its plots)."""


def _check_out_dir(out: Path, log_path: Path) -> None:
    """Refuse an output folder that holds other files and no earlier diagnosis, or outputs
    that would overwrite the log or cannot be written.

    Raises:
        InputError: Naming the folder or the output.
    """
    if out.is_dir() and any(out.iterdir()) and not (out / "report.json").is_file():
        raise InputError(
            f"--out-dir {out}: holds other files and no earlier diagnosis (no report.json); "
            "choose a new or empty folder"
        )
    for name in OUTPUTS:
        check_not_input(out / name, {"the log": log_path}, "--out-dir")
    for name in OUTPUTS:
        check_writable(out / name)


def _effect_entries(robot: RobotConfig, log: RobotLog, diagnosis: Diagnosis) -> list[dict]:
    """The report's entry of each finding, a claimed payload's with its second estimate by
    the torque regressor (:func:`payload_regression`; gantry logs only)."""
    floating = log.base == "floating"
    effects = [_effect_entry(f) for f in diagnosis.findings]
    for f, entry in zip(diagnosis.findings, effects, strict=True):
        if f.effect == "payload_mass" and f.confidence >= CLAIM and not floating:
            entry["regression"] = payload_regression(robot, log, f.target)
    return effects


def _fit_residual_net(
    corrected: Correction, log: RobotLog, held: Predictor, after: KStepError, out: Path
) -> tuple[dict, KStepError]:
    """Train the residual actuator network on the fit part of the log, save it into ``out``
    and score it on the held-out windows of ``held``.

    Returns:
        The report's ``residual_model`` entry and the held-out error with the network.
    """
    from humimic.real2sim.actuator_net import fit_residual_net

    net, info = fit_residual_net(corrected, log, (0.0, FIT_END))
    net_error = held.report(held.run_with_torque(corrected, net.torque, net.config.history))
    net.save(out / "residual_net.pt")
    net_entry = {
        "path": str(out / "residual_net.pt"),
        "error_after": net_error.as_report(log.joint_names),
        "improves": bool(net_error.kstep_rmse_rad < after.kstep_rmse_rad),
        "training": info,
        "inputs": f"per joint: the last {net.config.history} position errors, velocities "
        "and positions at the state rate",
    }
    return net_entry, net_error


def _export_model(robot: RobotConfig, diagnosis: Diagnosis, path: Path) -> None:
    """Write the full robot (floating base, like the nominal) with the claimed effects."""
    from humimic.robots import export_nominal

    injections = [
        Injection(effect=f.effect, targets=f.acts_on, value=f.value) for f in diagnosis.claimed
    ]
    export_nominal(robot, path, edit=lambda spec: apply_to_spec(spec, injections))


def _markdown(
    log_path: Path, robot: RobotConfig, report: dict, diagnosis: Diagnosis, plots: list[Path]
) -> str:
    before, after = report["error_before"], report["error_after"]
    lines = [
        f"# Diagnosis of {log_path.name} ({robot.name})",
        "",
        f"Held-out k-step error ({before['horizon_s']} s windows, last 30% of the log): "
        f"{before['kstep_rmse_rad'] * 1e3:.2f} mrad with the nominal model, "
        f"{after['kstep_rmse_rad'] * 1e3:.2f} mrad with the effects below.",
        "",
    ]
    if report["base"] == "floating":
        lines += _floating_lines(report)
    lines += _claimed_lines(diagnosis)
    lines += _unexplained_lines(report)
    for s in diagnosis.not_identifiable:
        lines += [f"Not identifiable from this log: **{s.effect}** on "
                  f"{len(s.joints)} joints ({', '.join(s.joints)}): {s.reason}", ""]  # fmt: skip
    lines += [f"![{p.stem}]({p.name})" for p in plots]
    lines += [
        "",
        "| effect | on | value | confidence | error removed (fit data) |",
        "|---|---|---|---|---|",
        *[
            f"| {f.effect} | {f.target} | {f.value:.4g} | {f.confidence:.2f} | "
            f"{100 * f.error_reduction:.0f}% |"
            for f in diagnosis.findings[:16]
        ],
        "",
        f"Searched: {', '.join(report['searched_effects'])}. "
        f"Not searched: {', '.join(report['not_searched_effects'])}. "
        f"Claimed: confidence >= {CLAIM}.",
        "",
        *[
            f"Claimed payload on {e['body']}: the torque regressor (no search, "
            f"{e['regression']['torques']}) gives {e['regression']['mass']:.4g} +- "
            f"{e['regression']['mass_std']:.2g} kg.\n"
            for e in report["effects"]
            if "mass" in e.get("regression", {})
        ],
        "Per-joint held-out error (mrad), before -> after:",
        "",
        *[
            f"- {n}: {b * 1e3:.2f} -> {after['per_joint'][n] * 1e3:.2f}"
            for n, b in before["per_joint"].items()
        ],
    ]
    return "\n".join(lines) + "\n"


def _floating_lines(report: dict) -> list[str]:
    """The report's paragraph on a floating base: where each window starts from, what is not
    done on the floor yet, and the joints whose noise floor the base estimate raises."""
    lines = [
        f"Floating base (a robot on the floor): each window starts from {report['base_estimate']}. "
        "Not on the floor yet: backlash, the signature plots and the residual network "
        "(they need the contact forces or a play joint in the floor model).",
        "",
    ]
    floor = report["noise_floor_rad"]
    least = min(floor.values())  # The median joint's error (noise_floor).
    high = sorted((n for n in floor if floor[n] > 1.5 * least), key=lambda n: -floor[n])
    if high:
        lines += [
            "Noise floor: errors of the base estimate move some joints' predictions more "
            f"than others, so their floors are above the least one ({1e3 * least:.2f} "
            "mrad, the median joint's error): "
            + ", ".join(f"{n} {1e3 * floor[n]:.2f}" for n in high[:6])
            + " mrad. A joint is unexplained only above three times its own floor.",
            "",
        ]
    return lines


def _claimed_lines(diagnosis: Diagnosis) -> list[str]:
    """The report's claimed effects, and a warning on those that explain only part of their
    joints' error."""
    lines: list[str] = []
    claimed = diagnosis.claimed
    if claimed:
        lines += ["Claimed (confidence >= 0.5):", ""]
        lines += [
            f"- **{f.effect}** on {f.target}: {f.value:.4g} {EFFECTS[f.effect].unit} "
            f"(confidence {f.confidence:.2f}; removes {100 * f.error_reduction:.0f}% of the "
            "error of " + ", ".join(f.joints) + " on unseen fit data)"
            for f in claimed
        ]
    else:
        lines.append("No effect claimed.")
    lines.append("")
    partial = [f for f in claimed if f.partial]
    if partial:
        lines += [
            "**Partial explanations**: with every claimed effect in the model, their joints "
            f"keep more than {PARTIAL:g} times their noise floor. Such an effect is right but "
            "incomplete (another acts on the same joints, or its model differs from the "
            "robot's, e.g. kp weaker but kd not), or it stands in for an effect outside the "
            "searched vocabulary; its confidence cannot tell which. Check these before "
            "relying on their values.",
            "",
            *[
                f"- {f.effect} on {f.target} ({f.value:.4g} {EFFECTS[f.effect].unit}, "
                f"confidence {f.confidence:.2f}): its joints keep {f.stands_out:.1f} times "
                "their noise floor"
                for f in partial
                if f.stands_out is not None
            ],
            "",
        ]
    return lines


def _unexplained_lines(report: dict) -> list[str]:
    """The report's word on the error left unexplained, and on the residual network."""
    lines: list[str] = []
    if report["unexplained"]:
        lines += [
            f"**Unexplained**: {100 * report['unexplained_share']:.0f}% of the error above the "
            "noise floor is left (joints: " + ", ".join(report["unexplained_joints"]) + "). "
            "No effect of the searched vocabulary accounts for it.",
            "",
        ]
    elif report["unexplained_joints"]:
        lines += [
            f"{100 * report['unexplained_share']:.0f}% of the error above the noise floor is "
            "left; joints still above it: " + ", ".join(report["unexplained_joints"]) + ".",
            "",
        ]
    net = report["residual_model"]
    if net is not None:
        verdict = (
            "it improves the prediction"
            if net["improves"]
            else "it does NOT improve the prediction: do not use it"
        )
        lines += [
            f"Residual actuator network ({Path(net['path']).name}): held-out error "
            f"{net['error_after']['kstep_rmse_rad'] * 1e3:.2f} mrad with it, {verdict} "
            f"(trained on {net['training']['samples']} samples of the fit part).",
            "",
        ]
    return lines
