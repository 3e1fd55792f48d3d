"""``humimic sysid simulate|residual|diagnose|import``: real2sim on robot logs."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from humimic.configs.choices import RobotName
from humimic.configs.runs import MAX_SEED
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready

MAX_HORIZON_S = 10.0
"""Longest prediction window of ``sysid residual`` and ``diagnose`` [s]."""


def check_horizon(horizon: float) -> None:
    """``--horizon`` in (0, :data:`MAX_HORIZON_S`] s (NaN refused); a window shorter than the
    log's state interval is refused when the log is read."""
    if not 0.0 < horizon <= MAX_HORIZON_S:
        raise InputError(
            f"--horizon {horizon}: expected a positive number of seconds, at most {MAX_HORIZON_S:g}"
        )


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
    imu_tilt: tuple[float, float] = (0.0, 0.0)
    """Floating base: the IMU mounted tilted by ROLL PITCH degrees off its site (what
    `humimic sysid diagnose` should find and remove); at most 30 each."""
    out: Path
    """Output .mcap file."""

    def validate(self) -> None:
        """Check the numbers before anything is simulated; :class:`InputError` names the flag."""
        if not 1.0 <= self.duration <= 3600.0:  # NaN fails too.
            raise InputError(f"--duration {self.duration}: choose 1 to 3600 s")
        if not 0 <= self.seed <= MAX_SEED:
            raise InputError(f"--seed {self.seed}: must be in 0 to {MAX_SEED}")
        if not all(abs(v) <= 30.0 for v in self.imu_tilt):  # NaN fails too.
            raise InputError(f"--imu-tilt {self.imu_tilt}: choose -30 to 30 degrees each")
        if any(v != 0.0 for v in self.imu_tilt) and self.base != "floating":
            raise InputError("--imu-tilt: a gantry log has no IMU; use --base floating")


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

    def validate(self) -> None:
        """Check ``--horizon`` before the log is read; :class:`InputError` names it."""
        check_horizon(self.horizon)


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

    def validate(self) -> None:
        """Check ``--horizon`` before the log is read; :class:`InputError` names it."""
        check_horizon(self.horizon)


@dataclass(frozen=True, kw_only=True)
class SysidImport:
    """Turn another recorder's robot log into humimic's MCAP contract: a Unitree low-state log
    (.npz or .csv; arrays named after unitree_sdk2's LowState/LowCmd fields) or a ROS 2 bag
    (JointState, Imu and a command topic; docs/real2sim.md, "Real logs in")."""

    src: Annotated[Path, tyro.conf.Positional]
    """The recorder's log: .npz, .csv, or a ROS 2 bag (folder, .db3 or .mcap)."""
    robot: RobotName = "g1"
    """Robot name from the registry (`humimic robots list`)."""
    out: Path
    """Output .mcap file."""
    map: Path | None = None
    """YAML: joints (source joint or motor index -> model joint), ignore (source joints not in
    the model), gains (kp/kd per model joint or '*', for commands that carry none)."""
    base: Literal["floating", "fixed"] = "floating"
    """floating: on the floor (needs the IMU); fixed: hanging in a gantry (needs --base-pose)."""
    base_pose: tuple[float, float, float, float, float, float, float] | None = None
    """Fixed base: X Y Z QW QX QY QZ of the root body in the gantry."""
    imu_site: str = ""
    """The model site the IMU sits at (default: the root body's site named *imu*)."""
    states_topic: str = "/joint_states"
    """ROS 2: sensor_msgs/JointState, or a Unitree LowState (motors and IMU)."""
    commands_topic: str = "/joint_commands"
    """ROS 2: sensor_msgs/JointState of targets (gains from --map), or a Unitree LowCmd."""
    imu_topic: str = "/imu"
    """ROS 2: sensor_msgs/Imu (empty: the LowState's IMU, or none for a fixed base)."""
    base_pose_topic: str = ""
    """ROS 2: geometry_msgs/PoseStamped of the root body from motion capture (empty: none)."""


@dataclass(frozen=True, kw_only=True)
class SysidCommand:
    """Real2sim: simulate robot logs with injected effects; measure the simulator's residual."""

    command: tyro.conf.OmitSubcommandPrefixes[
        Annotated[SysidSimulate, tyro.conf.subcommand("simulate")]
        | Annotated[SysidResidual, tyro.conf.subcommand("residual")]
        | Annotated[SysidDiagnose, tyro.conf.subcommand("diagnose")]
        | Annotated[SysidImport, tyro.conf.subcommand("import")]
    ]
    """simulate, residual, diagnose or import."""


def run_simulate(cmd: SysidSimulate) -> None:
    """Run ``humimic sysid simulate``."""
    from humimic.real2sim import LogSettings, simulate_log, write_robot_log
    from humimic.real2sim.simulate import tilt_imu
    from humimic.robots import get_robot
    from humimic.sim.effects import parse_injection

    robot = get_robot(cmd.robot, "--robot")
    injections = [parse_injection(text) for text in cmd.inject]
    if cmd.out.suffix != ".mcap":
        raise InputError(f"{cmd.out}: the log must be an .mcap file")
    cmd.validate()
    tilted = any(v != 0.0 for v in cmd.imu_tilt)
    check_writable(cmd.out)
    settings = LogSettings(duration=cmd.duration, seed=cmd.seed, base=cmd.base, mocap=cmd.mocap)
    log = simulate_log(robot, injections, settings)
    if tilted:
        log = tilt_imu(log, *cmd.imu_tilt)
    write_robot_log(log, cmd.out)
    print(f"wrote {cmd.out}: {log.q.shape[0]} states, {log.t_cmd.size} commands, "
          f"{len(log.joint_names)} joints")  # fmt: skip


def run_import(cmd: SysidImport) -> None:
    """Run ``humimic sysid import``."""
    import numpy as np

    from humimic.real2sim import write_robot_log
    from humimic.real2sim.imports import (
        ImportMap,
        RosTopics,
        import_log,
        import_target,
        read_import_map,
    )
    from humimic.robots import get_robot

    if cmd.out.suffix != ".mcap":
        raise InputError(f"{cmd.out}: the log must be an .mcap file (--out)")
    inputs = {"the source log": cmd.src} | ({"--map": cmd.map} if cmd.map else {})
    check_not_input(cmd.out, inputs, "--out")
    if cmd.src.is_dir() and cmd.out.resolve().is_relative_to(cmd.src.resolve()):
        raise InputError(f"--out {cmd.out}: inside the bag folder {cmd.src}; choose a path "
                         "outside it")  # fmt: skip
    check_writable(cmd.out)
    robot = get_robot(cmd.robot, "--robot")
    imap = read_import_map(cmd.map) if cmd.map is not None else ImportMap()
    pose = None if cmd.base_pose is None else np.array(cmd.base_pose)
    target = import_target(robot, cmd.base, pose, cmd.imu_site)
    topics = RosTopics(joint_states=cmd.states_topic, commands=cmd.commands_topic,
                       imu=cmd.imu_topic, base_pose=cmd.base_pose_topic)  # fmt: skip
    log = import_log(cmd.src, target, imap, topics)
    write_robot_log(log, cmd.out)
    streams = ["IMU"] if log.imu is not None else []
    if log.imu is not None and log.imu.acc_b is not None:
        streams.append("accelerometer")
    if log.mocap is not None:
        streams.append("motion capture")
    if log.effort is not None:
        streams.append("joint torque")
    rate = (log.t.size - 1) / max(log.duration, 1e-9)
    print(f"wrote {cmd.out}: {log.duration:.1f} s, {log.t.size} states ({rate:.0f} Hz), "
          f"{log.t_cmd.size} commands, {len(log.joint_names)} joints, {log.base} base"
          + (f"; with {', '.join(streams)}" if streams else ""))  # fmt: skip
    if log.gaps().size:
        print(f"note: the state stream breaks {log.gaps().size} time(s) (gaps over 1.5 median "
              "intervals); predictions skip windows across them")  # fmt: skip


def run_residual(cmd: SysidResidual) -> None:
    """Run ``humimic sysid residual``."""
    from humimic.real2sim.correction import Correction
    from humimic.real2sim.report import load_robot_log
    from humimic.real2sim.residual import Predictor

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

    r = run_diagnosis(cmd.log, cmd.out_dir, horizon=cmd.horizon, residual_net=cmd.residual_net)
    print(f"{cmd.log.name}: held-out k-step error {r.before_rad * 1e3:.2f} mrad "
          f"nominal -> {r.after_rad * 1e3:.2f} mrad corrected ({r.seconds:.0f} s)")  # fmt: skip
    for e in r.claims:
        print(f"claimed: {e.effect} on {', '.join(e.targets)} = {e.value:.4g} {e.unit} "
              f"(confidence {e.confidence:.2f})")  # fmt: skip
    for effect, joints in r.not_identifiable:
        print(f"not identifiable from this log: {effect} on {joints} joints")
    if r.unexplained:
        print("unexplained: " + ", ".join(r.unexplained_joints))
    net = r.report.get("residual_model")
    if net is not None:
        print(f"residual actuator network: {net['error_after']['kstep_rmse_rad'] * 1e3:.2f} mrad "
              f"held out -> {net['path']}")  # fmt: skip
    print(f"wrote {cmd.out_dir / 'report.md'}, report.json, model.xml, physics.yaml "
          "(the claims, for --physics)")  # fmt: skip
