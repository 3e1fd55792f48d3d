"""Simulated deployment logs: the robot stands on the floor and sways about its standing pose
under PD targets, balanced by an LQR designed on the nominal robot, its IMU read by MuJoCo's own
sensors and, optionally, its root body's pose by motion capture
(:func:`~humimic.real2sim.simulate.simulate_log` with ``base="floating"``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.robotlog import ImuLog, PoseTrack, RobotLog
from humimic.real2sim.simulate import (
    LogSettings,
    assemble_robot_log,
    encoder_offsets,
    hold_pose,
    imu_site_of,
    multisines,
    sensed_values,
)
from humimic.robots.model import nominal_spec
from humimic.robots.registry import RobotConfig
from humimic.sim import rollout
from humimic.sim.effects import Injection, apply_to_spec
from humimic.sim.joints import JointMap
from humimic.sim.lqr import LqrWeights, control_step_jacobians, riccati
from humimic.sim.models import PHYSICS_DT, floating_prediction_spec
from humimic.transforms import quat_mul


def simulate_floating(
    robot: RobotConfig,
    injections: list[Injection],
    settings: LogSettings,
    edit: Callable[[mujoco.MjSpec], None] | None,
) -> RobotLog:
    """A deployment log: the robot stands on the floor and sways under PD targets."""
    rng = np.random.default_rng(settings.seed)
    probe, model, site = _floor_model(robot, injections, settings, edit)
    root = int(probe.body(robot.root_body).id)
    jm = JointMap.of(model)
    names = jm.names
    if model.nu != len(names):
        raise InputError(f"{robot.name}: expected one actuator per joint")
    offset = encoder_offsets(injections, names)
    nominal_robot, drives = nominal_spec(robot)
    nominal = nominal_robot.compile()
    kp = np.array([drives[n].kp for n in names])
    kd = np.array([drives[n].kd for n in names])
    stand = _standing_pose(nominal, names)
    legs = _leg_joints(robot, probe, model, root, names)
    ranges = np.array([nominal.jnt_range[nominal.joint(n).id] for n in names])
    t_cmd, cmd_q = _sway(ranges[:, 0], ranges[:, 1], stand, legs, settings, rng)
    cmd_every = round(1.0 / (settings.command_rate * PHYSICS_DT))
    data, balanced = _landed(robot, model, jm, cmd_q[0] - offset, cmd_every)
    rec = _record_standing(model, data, jm, root, balanced, t_cmd, cmd_q, offset, settings)
    imu, mocap = _floor_sensors(site, rec, settings, rng)
    sensed = sensed_values(rec.q + offset, rec.qd, rec.effort, settings, rng)
    return assemble_robot_log(robot, "floating", np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), names,
                      rec.t, sensed, t_cmd, rec.sent, kp, kd, imu, mocap)  # fmt: skip


def _floor_model(
    robot: RobotConfig,
    injections: list[Injection],
    settings: LogSettings,
    edit: Callable[[mujoco.MjSpec], None] | None,
) -> tuple[mujoco.MjModel, mujoco.MjModel, str]:
    """The robot on the floor with the effects (encoder offsets aside: they act on what the
    drives and the log read) and MuJoCo's own IMU sensors at its IMU's site (the IMU as a
    robot's driver reports it: orientation, gyro, accelerometer, in that order).

    Returns:
        The model without the sensors (its bodies and sites are the simulated robot's), the
        model with them, and the IMU's site.
    """
    spec = floating_prediction_spec(robot, filters=False)
    apply_to_spec(spec, [inj for inj in injections if inj.effect != "encoder_offset"])
    if edit is not None:
        edit(spec)
    probe = spec.compile()
    root = int(probe.body(robot.root_body).id)
    site = imu_site_of(probe, root, settings.imu_site)
    site_obj = mujoco.mjtObj.mjOBJ_SITE
    spec.add_sensor(type=mujoco.mjtSensor.mjSENS_FRAMEQUAT, objtype=site_obj, objname=site)
    spec.add_sensor(type=mujoco.mjtSensor.mjSENS_GYRO, objtype=site_obj, objname=site)
    spec.add_sensor(type=mujoco.mjtSensor.mjSENS_ACCELEROMETER, objtype=site_obj, objname=site)
    return probe, spec.compile(), site


def _standing_pose(nominal: mujoco.MjModel, names: tuple[str, ...]) -> np.ndarray:
    """The standing pose of joints ``names``: the robot's first keyframe (its joints by
    name), else zero."""
    stand = np.zeros(len(names))
    if nominal.nkey:
        for i, n in enumerate(names):
            j = nominal.joint(n)
            stand[i] = nominal.key_qpos[0, nominal.jnt_qposadr[j.id]]
    return stand


def _leg_joints(
    robot: RobotConfig,
    probe: mujoco.MjModel,
    model: mujoco.MjModel,
    root: int,
    names: tuple[str, ...],
) -> np.ndarray:
    """Which of the joints ``names`` lie between the root body and a foot (their sway is
    kept small so that the feet stay planted). Shape: (J,), bool."""
    feet = [probe.body(b).id for b in robot.feet.values()]
    legs = np.zeros(len(names), dtype=bool)
    for f in feet:
        b = f
        while b != root and b != 0:
            j0, nj = model.body_jntadr[b], model.body_jntnum[b]
            for j in range(j0, j0 + nj):
                if model.joint(j).name in names:
                    legs[names.index(model.joint(j).name)] = True
            b = model.body_parentid[b]
    return legs


def _landed(
    robot: RobotConfig, model: mujoco.MjModel, jm: JointMap, target: np.ndarray, cmd_every: int
) -> tuple[mujoco.MjData, _Balance]:
    """The robot dropped from 2 mm above the floor in the pose ``target`` (per joint, the
    drives holding it) and landed on joint PD alone (it tips over later), with its balance
    controller designed about the landed pose."""
    act = jm.act_log
    data = mujoco.MjData(model)
    fj = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
    qa = int(model.jnt_qposadr[fj])
    data.qpos[jm.qadr] = target
    data.qpos[qa : qa + 7] = 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
    mujoco.mj_kinematics(model, data)
    lowest = min(float(data.geom_xpos[g, 2] - model.geom_rbound[g])
                 for g in range(model.ngeom) if model.geom_bodyid[g] != 0)  # fmt: skip
    data.qpos[qa + 2] = -lowest + 0.002  # Dropped from 2 mm above the floor.
    hold_pose(model, data, target[act])
    data.ctrl[:] = target[act]
    rollout.step(model, data, round(0.3 / PHYSICS_DT))  # Land (PD alone tips over later).
    return data, _Balance(robot, model, data, jm, target, cmd_every)


def _sway(
    lo: np.ndarray,
    hi: np.ndarray,
    stand: np.ndarray,
    legs: np.ndarray,
    settings: LogSettings,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """PD targets about the standing pose inside the joint ranges ``lo``-``hi``: slow
    multi-sines, small on the legs (the feet stay planted), larger on the arms and the waist.
    Returns command times (M,) and targets (M, J)."""
    centre = np.clip(stand, lo, hi)
    room = np.minimum(centre - lo, hi - centre)
    amp = np.where(legs, settings.sway_legs, settings.sway * (hi - lo))
    amp = np.minimum(amp, 0.8 * room)
    t = np.arange(0.0, settings.duration, 1.0 / settings.command_rate)
    ramp, sines = multisines(rng, t, centre.size, 1.0, settings.still)
    return t, np.clip(centre + ramp[:, None] * amp * sines, lo, hi)


def _standing_gain(
    model: mujoco.MjModel, qpos: np.ndarray, ctrl: np.ndarray, decimation: int
) -> np.ndarray:
    """The steady-state LQR gain of the robot standing at ``qpos`` (commands held for
    ``decimation`` physics steps). Shape: (nu, 2 nv)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    A, B = control_step_jacobians(model, data, ctrl, decimation, 1e-6)
    H = 400  # Control steps of the backward pass: enough for the gain to settle.
    w = LqrWeights()
    nx = A.shape[0]
    lxx = np.broadcast_to(np.diag(w.state_diagonal(model.nv)), (H + 1, nx, nx)).copy()
    luu = np.broadcast_to(w.control * np.eye(model.nu), (H, model.nu, model.nu)).copy()
    out = riccati(np.zeros((H + 1, nx)), lxx, np.zeros((H, model.nu)), luu,
                  np.broadcast_to(A, (H, nx, nx)), np.broadcast_to(B, (H, *B.shape)), 0.0)  # fmt: skip
    if out is None:
        raise InputError("the standing robot's linearization is not finite")
    return out[1][0]


class _Balance:
    """A balance controller (a robot on the floor needs one: joint PD alone tips over): the
    LQR of the standing robot, its reference the commanded joint pose with the base as it
    stands now (upright).

    The controller is designed on the nominal robot (its designer does not know the effects;
    MuJoCo's derivatives do not support actuator delays either) and reads the robot's base
    and its link-side joints.

    Args:
        robot: The robot.
        model, data: The simulated robot, standing.
        jm: Its joints.
        target: The joint pose it stands in (per joint).
        cmd_every: Physics steps a command is held.
    """

    def __init__(
        self,
        robot: RobotConfig,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        jm: JointMap,
        target: np.ndarray,
        cmd_every: int,
    ) -> None:
        design = floating_prediction_spec(robot, filters=False).compile()
        jd = JointMap.of(design)
        fd = int(np.flatnonzero(design.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
        fj = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
        self.qd0, self.dd0 = int(design.jnt_qposadr[fd]), int(design.jnt_dofadr[fd])
        self.qa, self.da = int(model.jnt_qposadr[fj]), int(model.jnt_dofadr[fj])
        qa, qd0 = self.qa, self.qd0
        self.ref_q = design.qpos0.copy()
        self.ref_q[qd0 : qd0 + 7] = data.qpos[qa : qa + 7]
        self.ref_q[jd.qadr] = jm.link(data.qpos, jm.play_q, jm.qadr)
        row = np.argsort(jd.act_log)  # Design actuator of each joint.
        gain = _standing_gain(design, self.ref_q, target[jd.act_log], cmd_every)
        self.gain = gain[row[jm.act_log]]
        self.now_q, self.dq = design.qpos0.copy(), np.zeros(2 * design.nv)
        self.design, self.jd, self.data, self.jm = design, jd, data, jm

    def __call__(self, target: np.ndarray) -> np.ndarray:
        """PD targets (per actuator) for joint targets ``target`` (per joint), balanced."""
        design, jd, jm, data = self.design, self.jd, self.jm, self.data
        qa, da, qd0, dd0, now_q, dq = self.qa, self.da, self.qd0, self.dd0, self.now_q, self.dq
        ref = self.ref_q.copy()
        ref[jd.qadr] = target
        now_q[qd0 : qd0 + 7] = data.qpos[qa : qa + 7]
        now_q[jd.qadr] = jm.link(data.qpos, jm.play_q, jm.qadr)
        mujoco.mj_differentiatePos(design, dq[: design.nv], 1.0, ref, now_q)
        dq[design.nv + dd0 : design.nv + dd0 + 6] = data.qvel[da : da + 6]
        dq[design.nv + jd.dadr] = jm.link(data.qvel, jm.play_d, jm.dadr)
        return target[jm.act_log] + self.gain @ dq


@dataclass(frozen=True, kw_only=True)
class _Standing:
    """What a standing robot's log records, before sensor noise and encoder offsets.

    Attributes:
        t: State times [s]. Shape: (N,).
        q, qd, effort: Link-side joint positions, velocities, drive torques. Shape: (N, J).
        sent: The commands as sent (the balanced ones). Shape: (M, J).
        quat, gyro, acc: The IMU sensors' readings. Shape: (N, 4), (N, 3), (N, 3).
        pos, pose_q: The root body's position and orientation (world). Shape: (N, 3), (N, 4).
    """

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    effort: np.ndarray
    sent: np.ndarray
    quat: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    pos: np.ndarray
    pose_q: np.ndarray


def _record_standing(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    jm: JointMap,
    root: int,
    balanced: _Balance,
    t_cmd: np.ndarray,
    cmd_q: np.ndarray,
    offset: np.ndarray,
    settings: LogSettings,
) -> _Standing:
    """Let the landed robot come to rest on its first command, then run it through the
    commands ``cmd_q`` (at ``t_cmd``), balanced, and record what its log would.

    Raises:
        InputError: The robot fell (its root below 0.6 of its standing height).
    """
    act = jm.act_log
    cmd_every = round(1.0 / (settings.command_rate * PHYSICS_DT))
    settle = round(1.5 / PHYSICS_DT)  # Land and come to rest before the log starts.
    for step in range(settle):
        if step % cmd_every == 0:
            data.ctrl[:] = balanced(cmd_q[0] - offset)
        rollout.step(model, data)
    height0 = float(data.xpos[root, 2])
    n_steps = round(settings.duration / PHYSICS_DT)
    state_every = round(1.0 / (settings.state_rate * PHYSICS_DT))
    n_states = n_steps // state_every
    q = np.zeros((n_states, len(jm.names)))
    qd, effort = np.zeros_like(q), np.zeros_like(q)
    sent = np.zeros_like(cmd_q)  # The commands as sent: the balanced ones.
    quat, pose_q = np.zeros((n_states, 4)), np.zeros((n_states, 4))
    gyro, acc, pos = np.zeros((n_states, 3)), np.zeros((n_states, 3)), np.zeros((n_states, 3))
    for step in range(n_steps):
        if step % cmd_every == 0 and step // cmd_every < len(t_cmd):
            k = step // cmd_every
            data.ctrl[:] = balanced(cmd_q[k] - offset)
            sent[k, act] = data.ctrl + offset[act]
        if step % state_every == 0 and step // state_every < n_states:
            mujoco.mj_forward(model, data)
            i = step // state_every
            if data.xpos[root, 2] < 0.6 * height0:
                raise InputError(
                    f"the robot fell {step * PHYSICS_DT:.2f} s into the log while standing "
                    "with these effects; choose smaller effects or a shorter log"
                )
            q[i] = jm.link(data.qpos, jm.play_q, jm.qadr)
            qd[i] = jm.link(data.qvel, jm.play_d, jm.dadr)
            effort[i, act] = data.actuator_force
            quat[i], gyro[i], acc[i] = (
                data.sensordata[:4],
                data.sensordata[4:7],
                data.sensordata[7:10],
            )
            pos[i], pose_q[i] = data.xpos[root], data.xquat[root]
        rollout.step(model, data)
    t = np.arange(n_states) * state_every * PHYSICS_DT
    return _Standing(t=t, q=q, qd=qd, effort=effort, sent=sent, quat=quat, gyro=gyro, acc=acc,
                     pos=pos, pose_q=pose_q)  # fmt: skip


def _noisy_quats(qs: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Quaternions turned by small random rotations (sensor noise), w kept >= 0."""
    dq = np.concatenate([np.ones((len(qs), 1)), rng.normal(0.0, sigma / 2.0, (len(qs), 3))],
                        axis=1)  # fmt: skip
    out = quat_mul(qs, dq / np.linalg.norm(dq, axis=1, keepdims=True))
    return out * np.where(out[:, :1] < 0, -1.0, 1.0)


def _floor_sensors(
    site: str, rec: _Standing, settings: LogSettings, rng: np.random.Generator
) -> tuple[ImuLog, PoseTrack | None]:
    """The IMU (at ``site``) and, if ``settings`` log it, motion capture as the log records
    them: the recorded readings plus sensor noise (drawn in this order: orientation, gyro,
    accelerometer, mocap position, mocap orientation)."""
    t = rec.t
    imu = ImuLog(site=site, t=t, quat_w=_noisy_quats(rec.quat, settings.quat_noise, rng),
                 gyro_b=rec.gyro + rng.normal(0, settings.gyro_noise, rec.gyro.shape),
                 acc_b=rec.acc + rng.normal(0, settings.acc_noise, rec.acc.shape))  # fmt: skip
    mocap = None
    if settings.mocap:
        mocap = PoseTrack(t=t, pos_w=rec.pos + rng.normal(0, settings.mocap_noise, rec.pos.shape),
                          quat_w=_noisy_quats(rec.pose_q, settings.quat_noise, rng))  # fmt: skip
    return imu, mocap
