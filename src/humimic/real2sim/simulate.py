"""Realistic robot logs from the nominal model plus injected effects (test data for real2sim).

A fixed-base robot (hanging in a gantry) follows multi-sine PD targets inside its joint limits,
with a still period, commands at 50 Hz, states at 200 Hz, sensor noise. A floating-base robot
stands on the floor and sways about its standing pose (a deployment log: IMU and, optionally,
motion capture). The effects are added to the model the log is simulated with; the log itself
records only what a robot would: joint states, the commands sent, and on the floor the IMU
and the mocap pose. Nothing in the log names the effects.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.robotlog import ImuLog, PoseTrack, RobotLog
from humimic.robots.collision import tree_path
from humimic.robots.model import nominal_spec
from humimic.robots.registry import RobotConfig
from humimic.sim import rollout
from humimic.sim.effects import Injection, apply_to_spec, value_problem
from humimic.sim.joints import JointMap
from humimic.sim.models import PHYSICS_DT, fixed_base_spec


@dataclass(frozen=True, kw_only=True)
class LogSettings:
    """How a simulated log is recorded.

    Attributes:
        duration: Seconds. state_rate, command_rate: Hz.
        still: Seconds of still commands at the start.
        amplitude: Excitation amplitude as a fraction of each joint's range.
        q_noise, qd_noise, effort_noise: Sensor noise (standard deviations).
        base_height: Height of the fixed base (the pelvis hangs free of the floor) [m].
        base: ``fixed`` (a gantry) or ``floating`` (standing on the floor, swaying).
        mocap: Log the root body's pose from motion capture (floating base).
        imu_site: The IMU's site (floating base; default: the root body's site named
            ``*imu*``).
        sway: On the floor, the excitation amplitude of the arms and the waist as a fraction
            of each joint's range (the robot falls at about twice it).
        sway_legs: On the floor, the leg joints' amplitude [rad] (the feet stay planted).
        gyro_noise, acc_noise, quat_noise, mocap_noise: IMU and mocap noise (standard
            deviations: rad/s, m/s^2, rad, m).
    """

    duration: float = 40.0
    state_rate: float = 200.0
    command_rate: float = 50.0
    still: float = 2.0
    amplitude: float = 0.15
    q_noise: float = 2e-4
    qd_noise: float = 0.01
    effort_noise: float = 0.05
    base_height: float = 1.0
    seed: int = 0
    base: str = "fixed"
    mocap: bool = True
    imu_site: str = ""
    sway: float = 0.05
    sway_legs: float = 0.04
    gyro_noise: float = 0.005
    acc_noise: float = 0.05
    quat_noise: float = 0.002
    mocap_noise: float = 0.001


def _tree_distance(model: mujoco.MjModel, a: int, b: int) -> int:
    """Edges between two bodies in the kinematic tree."""
    return len(tree_path(model, a, b))


def multisines(
    rng: np.random.Generator, t: np.ndarray, joints: int, f_max: float, still: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each joint's sum of three sines at times ``t`` (frequencies drawn in 0.1 to ``f_max``
    Hz, random phases, convex weights: the sum stays within +-1), and a ramp from 0 to 1 over
    the 2 s after ``still`` seconds that starts the motion from rest.

    Returns:
        The ramp (M,) and the sums (M, joints).
    """
    freqs = rng.uniform(0.1, f_max, size=(joints, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(joints, 3))
    weights = rng.dirichlet(np.ones(3), size=joints)
    ramp = np.clip((t - still) / 2.0, 0.0, 1.0)
    sines = np.einsum(
        "jk,tjk->tj", weights, np.sin(2 * np.pi * freqs[None] * t[:, None, None] + phases[None])
    )
    return ramp, sines


def excitation(
    model: mujoco.MjModel, settings: LogSettings, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-sine PD targets inside the joint limits, with a still start and no self-contact.

    The amplitudes shrink until no pose along the commanded path brings two geoms within
    2 cm of each other (a hanging robot must not hit itself: contacts would dominate the log).

    Returns:
        Command times (M,) and targets (M, J).
    """
    lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
    centre = np.clip(0.0, lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo))
    amp = settings.amplitude * (hi - lo)
    amp = np.minimum(amp, np.minimum(centre - lo, hi - centre) * 0.8)
    t = np.arange(0.0, settings.duration, 1.0 / settings.command_rate)
    J = model.njnt
    ramp, sines = multisines(rng, t, J, 1.2, settings.still)
    # |sines| <= 1 (convex weights), and the ramp starts the motion from the centre.
    data = mujoco.MjData(model)
    saved = model.geom_margin.copy(), model.opt.disableflags
    model.geom_margin[:] = 0.01  # Pairs closer than 2 cm count as touching.
    model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)

    def touching(poses: np.ndarray) -> np.ndarray:
        """Joints that moved a geom into contact, over a path of poses."""
        hit = np.zeros(J, dtype=bool)
        for q in poses:
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_collision(model, data)
            for c in data.contact[: data.ncon]:
                b1, b2 = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
                if _tree_distance(model, b1, b2) <= 2:
                    continue  # Neighbouring links always sit within a few mm of each other.
                for g in (c.geom1, c.geom2):
                    b = model.geom_bodyid[g]
                    while b != 0:  # Every joint between the geom and the base moved it.
                        j0, nj = model.body_jntadr[b], model.body_jntnum[b]
                        hit[j0 : j0 + nj] = True
                        b = model.body_parentid[b]
        return hit

    try:
        middle = 0.5 * (lo + hi)
        for _ in range(10):  # A home pose clear of contact: towards the middle of the ranges.
            hit = touching(centre[None])
            if not hit.any():
                break
            centre[hit] += 0.25 * (middle[hit] - centre[hit])
        for _ in range(12):
            targets = np.clip(centre + ramp[:, None] * amp * sines, lo, hi)
            hit = touching(targets[:: max(1, int(settings.command_rate // 10))])
            if not hit.any():
                return t, targets
            amp[hit] *= 0.7
    finally:
        model.geom_margin[:], model.opt.disableflags = saved
    raise InputError("could not find a self-contact-free excitation for this robot")


def simulate_log(
    robot: RobotConfig,
    injections: list[Injection],
    settings: LogSettings,
    *,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
) -> RobotLog:
    """Simulate a fixed-base robot log with the given (undeclared) effects.

    Args:
        robot: The robot.
        injections: Effects of the vocabulary added to the simulated robot.
        settings: How the log is recorded.
        edit: Any further change to the simulated robot's spec (tests use it for effects
            outside the vocabulary).
    """
    if settings.base == "floating":
        from humimic.real2sim.simulate_floor import simulate_floating

        return simulate_floating(robot, injections, settings, edit)
    if settings.base != "fixed":
        raise InputError(f"--base {settings.base!r}: expected fixed or floating")
    rng = np.random.default_rng(settings.seed)
    base_pose = np.array([0.0, 0.0, settings.base_height, 1.0, 0.0, 0.0, 0.0])
    spec = fixed_base_spec(robot, base_pose)
    # Encoder offsets act on what the drives and the log read, applied below; the rest on the
    # robot itself.
    apply_to_spec(spec, [inj for inj in injections if inj.effect != "encoder_offset"])
    if edit is not None:
        edit(spec)
    model = spec.compile()
    jm = JointMap.of(model)  # Backlash adds a hidden joint per affected joint.
    names = jm.names
    offset = encoder_offsets(injections, names)
    if model.nu != len(names):
        raise InputError(f"{robot.name}: expected one actuator per joint")
    nominal = nominal_spec(robot)[1]
    kp = np.array([nominal[n].kp for n in names])
    kd = np.array([nominal[n].kd for n in names])
    # The experiment is designed on the nominal robot (its designer does not know the effects).
    t_cmd, cmd_q = excitation(fixed_base_spec(robot, base_pose).compile(), settings, rng)
    t, q, qd, effort = _record_hanging(model, jm, t_cmd, cmd_q, offset, settings)
    sensed = sensed_values(q + offset, qd, effort, settings, rng)
    return assemble_robot_log(robot, "fixed", base_pose, names, t, sensed, t_cmd, cmd_q, kp, kd)


def _record_hanging(
    model: mujoco.MjModel,
    jm: JointMap,
    t_cmd: np.ndarray,
    cmd_q: np.ndarray,
    offset: np.ndarray,
    settings: LogSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run the hanging robot through the commands ``cmd_q`` (at ``t_cmd``) from rest at the
    first one, its drives tracking their (offset) encoders, and record its true state.

    Returns:
        State times (N,), and the link side's positions, velocities and the drives' torques
        at them (N, J), before any sensor noise or encoder offset.
    """
    act = jm.act_log
    data = mujoco.MjData(model)
    data.qpos[jm.qadr] = cmd_q[0]
    hold_pose(model, data, (cmd_q[0] - offset)[act])
    mujoco.mj_forward(model, data)
    n_steps = round(settings.duration / PHYSICS_DT)
    state_every = round(1.0 / (settings.state_rate * PHYSICS_DT))
    cmd_every = round(1.0 / (settings.command_rate * PHYSICS_DT))
    n_states = n_steps // state_every
    q = np.zeros((n_states, len(jm.names)))
    qd = np.zeros_like(q)
    effort = np.zeros_like(q)
    for step in range(n_steps):
        if step % cmd_every == 0:
            # The drive tracks its (offset) encoder: the true joint settles at target - offset.
            target = cmd_q[min(step // cmd_every, len(t_cmd) - 1)] - offset
            data.ctrl[:] = target[act]
        if step % state_every == 0 and step // state_every < n_states:
            # The drive's torque estimate belongs to this instant's state and command.
            mujoco.mj_forward(model, data)
            i = step // state_every
            q[i] = jm.link(data.qpos, jm.play_q, jm.qadr)  # The link side.
            qd[i] = jm.link(data.qvel, jm.play_d, jm.dadr)
            effort[i, act] = data.actuator_force
        rollout.step(model, data)
    t = np.arange(n_states) * state_every * PHYSICS_DT
    return t, q, qd, effort


def assemble_robot_log(
    robot: RobotConfig,
    base: str,
    base_pose: np.ndarray,
    names: tuple[str, ...],
    t: np.ndarray,
    sensed: tuple[np.ndarray, np.ndarray, np.ndarray],
    t_cmd: np.ndarray,
    cmd_q: np.ndarray,
    kp: np.ndarray,
    kd: np.ndarray,
    imu: ImuLog | None = None,
    mocap: PoseTrack | None = None,
) -> RobotLog:
    """The simulated log: the sensed joint states (``sensed``: positions, velocities,
    torques), position commands with no velocity or torque feed-forward, and the drives'
    gains ``kp``, ``kd`` (J,) held at every command."""
    M = len(t_cmd)
    q_s, qd_s, effort_s = sensed
    return RobotLog(
        robot=robot.name,
        base=base,
        base_pose=base_pose,
        joint_names=names,
        t=t,
        q=q_s,
        qd=qd_s,
        effort=effort_s,
        t_cmd=t_cmd,
        cmd_q=cmd_q,
        cmd_qd=np.zeros((M, len(names))),
        cmd_tau=np.zeros((M, len(names))),
        kp=np.tile(kp, (M, 1)),
        kd=np.tile(kd, (M, 1)),
        imu=imu,
        mocap=mocap,
    )


def tilt_imu(log: RobotLog, roll: float, pitch: float) -> RobotLog:
    """The log as an IMU mounted tilted on its site would have logged it: its frame turned
    by ``roll`` about the site's x, then ``pitch`` about the site's y [deg] (fixed axes),
    its orientation, gyro and accelerometer read in the turned frame (by scipy, not by the base estimate's
    code: for tests and benchmarks of the mount-tilt estimate)."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    if log.imu is None:
        raise InputError(f"{log.where}: no /imu to tilt")
    m = Rotation.from_euler("xy", [roll, pitch], degrees=True)
    turned = Rotation.from_quat(log.imu.quat_w[:, [1, 2, 3, 0]]) * m
    R = m.as_matrix()
    acc = None if log.imu.acc_b is None else log.imu.acc_b @ R
    imu = replace(log.imu, quat_w=turned.as_quat()[:, [3, 0, 1, 2]], gyro_b=log.imu.gyro_b @ R,
                  acc_b=acc)  # fmt: skip
    return replace(log, imu=imu)


def hold_pose(model: mujoco.MjModel, data: mujoco.MjData, target: np.ndarray) -> None:
    """The drives have been holding ``target`` (per actuator): their delay lines are full of
    it and their filters settled on it."""
    for a in range(model.nu):
        n = int(model.actuator_history[a, 0])
        if n > 0:
            values = np.full((n, 1), target[a])
            times = -PHYSICS_DT * np.arange(n - 1, -1, -1, dtype=np.float64).reshape(n, 1)
            mujoco.mj_initCtrlHistory(model, data, a, times, values)
    for a in np.flatnonzero(model.actuator_actadr >= 0):
        data.act[model.actuator_actadr[a]] = target[a]


def sensed_values(
    q: np.ndarray,
    qd: np.ndarray,
    effort: np.ndarray,
    settings: LogSettings,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint positions, velocities and drive torques as the sensors report them (noise)."""
    return (q + rng.normal(0, settings.q_noise, q.shape),
            qd + rng.normal(0, settings.qd_noise, qd.shape),
            effort + rng.normal(0, settings.effort_noise, effort.shape))  # fmt: skip


def encoder_offsets(injections: list[Injection], names: tuple[str, ...]) -> np.ndarray:
    offset = np.zeros(len(names))
    for inj in injections:
        if inj.effect == "encoder_offset":
            problem = value_problem(inj.effect, inj.value)
            if problem is not None:
                raise InputError(f"{inj.where}: {problem}")
            for j in inj.targets:
                if j not in names:
                    raise InputError(f"{inj.where}: no joint {j!r} in the robot")
                offset[names.index(j)] += inj.value
    return offset


def imu_site_of(model: mujoco.MjModel, root: int, asked: str) -> str:
    """The IMU's site: ``asked`` (``--imu-site``), or the root body's site named *imu*."""
    if asked:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, asked) < 0:
            raise InputError(f"--imu-site {asked!r}: no such site in the robot")
        return asked
    for s in range(model.nsite):
        if model.site_bodyid[s] == root and "imu" in model.site(s).name.lower():
            return model.site(s).name
    raise InputError(
        f"the robot has no site named *imu* on its root body {model.body(root).name!r}; "
        "name the IMU's site with --imu-site"
    )
