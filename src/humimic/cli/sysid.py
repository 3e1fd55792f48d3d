"""``humimic sysid simulate|residual|diagnose``: real2sim on robot logs."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from humimic.configs.choices import RobotName
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready


@dataclass(frozen=True, kw_only=True)
class SysidSimulate:
    """Write a realistic robot log (MCAP) from the nominal model plus injected effects: hanging
    in a gantry (fixed base), or standing on the floor and swaying under a balance controller
    (floating base: a deployment log with an IMU and, optionally, motion capture)."""

    robot: RobotName = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    inject: tyro.conf.UseAppendAction[tuple[str, ...]] = ()
    """An effect as EFFECT:JOINT[,JOINT...]=VALUE, e.g. coulomb_friction:left_knee_joint=2.0;
    repeat the flag for more."""
    duration: float = 40.0
    """Seconds."""
    seed: int = 0
    """Seed of the excitation signal and the sensor noise."""
    base: Literal["fixed", "floating"] = "fixed"
    """fixed: a gantry; floating: on the floor (IMU on /imu)."""
    mocap: bool = True
    """Floating base: log the root body's pose from motion capture (/base_pose)."""
    out: Path
    """Output .mcap file."""


@dataclass(frozen=True, kw_only=True)
class SysidResidual:
    """The nominal model's k-step open-loop prediction error on a robot log, per joint (fixed
    base, or floating: predicted with the floor from the IMU's base state)."""

    log: Annotated[Path, tyro.conf.Positional]
    """Robot log (.mcap): /joint_states, /joint_commands, metadata 'robot'."""
    horizon: float = 0.5
    """Prediction window [s]."""
    report: Path | None = None
    """Write the numbers as JSON here."""


@dataclass(frozen=True, kw_only=True)
class SysidDiagnose:
    """Find the joint-level effects the nominal model lacks in a robot log, size them, write
    the corrected model and a report (fit on the first 70%, scored on the last 30%)."""

    log: Annotated[Path, tyro.conf.Positional]
    """Robot log (.mcap)."""
    out_dir: Path
    """Folder for model.xml, report.json, report.md (with plots), residual_net.pt."""
    horizon: float = 0.5
    """Prediction window [s]."""
    residual_net: Literal["auto", "always", "never"] = "auto"
    """Fit a residual actuator network: when the effects leave the log unexplained (auto)."""


@dataclass(frozen=True, kw_only=True)
class SysidCommand:
    """Real2sim: simulate robot logs with injected effects; measure the simulator's residual."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[SysidSimulate, tyro.conf.subcommand("simulate")]
        | Annotated[SysidResidual, tyro.conf.subcommand("residual")]
        | Annotated[SysidDiagnose, tyro.conf.subcommand("diagnose")]
    ]
    """simulate, residual or diagnose."""


def run_simulate(cmd: SysidSimulate) -> None:
    """Run ``humimic sysid simulate``."""
    from humimic.real2sim import LogSettings, simulate_log, write_robot_log
    from humimic.robots import get_robot
    from humimic.sim.effects import parse_injection

    robot = get_robot(cmd.robot, "--robot")
    injections = [parse_injection(text) for text in cmd.inject]
    if cmd.out.suffix != ".mcap":
        raise InputError(f"{cmd.out}: the log must be an .mcap file")
    if not 1.0 <= cmd.duration <= 3600.0:
        raise InputError(f"--duration {cmd.duration}: choose 1 to 3600 s")
    check_writable(cmd.out)
    settings = LogSettings(duration=cmd.duration, seed=cmd.seed, base=cmd.base, mocap=cmd.mocap)
    log = simulate_log(robot, injections, settings)
    write_robot_log(log, cmd.out)
    print(f"wrote {cmd.out}: {log.q.shape[0]} states, {log.t_cmd.size} commands, "
          f"{len(log.joint_names)} joints")  # fmt: skip


def run_residual(cmd: SysidResidual) -> None:
    """Run ``humimic sysid residual``."""
    from humimic.real2sim.report import load_robot_log
    from humimic.real2sim.residual import Predictor
    from humimic.sim.effects import Correction

    if cmd.report is not None:
        check_not_input(cmd.report, {"the log": cmd.log}, "--report")
        check_writable(cmd.report)
    robot, model, log = load_robot_log(cmd.log)
    names = log.joint_names
    predictor = Predictor(model, log, horizon=cmd.horizon)
    err = predictor.error(Correction.of(model))
    result = {"robot": robot.name, "log": str(cmd.log), "base": log.base,
              "error_nominal": err.as_report(names)}  # fmt: skip
    if predictor.base is not None:
        result["base_estimate"] = predictor.base.source
        print(f"floating base: {predictor.base.source}")
    worst = sorted(result["error_nominal"]["per_joint"].items(), key=lambda kv: -kv[1])[:5]
    print(f"{cmd.log.name}: nominal k-step RMSE {err.kstep_rmse_rad * 1e3:.2f} mrad over "
          f"{err.horizon_s} s windows; worst joints: "
          + ", ".join(f"{n} {v * 1e3:.2f}" for n, v in worst))  # fmt: skip
    if cmd.report is not None:
        atomic_write_text(cmd.report, json.dumps(json_ready(result), indent=2) + "\n")


def run_diagnose(cmd: SysidDiagnose) -> None:
    """Run ``humimic sysid diagnose``."""
    from humimic.real2sim.report import run_diagnosis

    report = run_diagnosis(cmd.log, cmd.out_dir, horizon=cmd.horizon, residual_net=cmd.residual_net)
    before, after = report["error_before"], report["error_after"]
    print(f"{cmd.log.name}: held-out k-step error {before['kstep_rmse_rad'] * 1e3:.2f} mrad "
          f"nominal -> {after['kstep_rmse_rad'] * 1e3:.2f} mrad corrected "
          f"({report['seconds']:.0f} s)")  # fmt: skip
    for e in report["effects"]:
        if e["confidence"] >= 0.5:
            where = e.get("body") or ", ".join(e["joints"])
            print(f"claimed: {e['effect']} on {where} = {e['params']['value']:.4g} "
                  f"{e['params']['unit']} (confidence {e['confidence']:.2f})")  # fmt: skip
    for s in report["not_identifiable"]:
        print(f"not identifiable from this log: {s['effect']} on {len(s['joints'])} joints")
    if report["unexplained"]:
        print("unexplained: " + ", ".join(report["unexplained_joints"]))
    if report["residual_model"] is not None:
        net = report["residual_model"]
        print(f"residual actuator network: {net['error_after']['kstep_rmse_rad'] * 1e3:.2f} mrad "
              f"held out -> {net['path']}")  # fmt: skip
    print(f"wrote {cmd.out_dir / 'report.md'}, report.json, model.xml")
