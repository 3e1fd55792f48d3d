"""The floating base's state at a log's samples (:func:`estimate_base`): orientation from the
IMU; position and velocity smoothed over the whole log from motion capture, the
accelerometer and the stance foot, whichever the log has."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.robotlog import ImuLog, RobotLog
from humimic.real2sim.smoother import smooth_track
from humimic.sim.joints import JointMap
from humimic.sim.models import MAX_STEP, PHYSICS_DT, REST_DEPTH, floor_and_colliders, lowest_point
from humimic.transforms import quat_conj, quat_mul, quat_slerp, quat_to_matrix, quat_to_rotvec

_SLACK = 0.05
"""How far [s] a sample may lie outside a stream's span and still be read (its end value)."""
SIGMA_MOCAP = 0.002
"""Motion capture's position noise [m] the smoother assumes."""
SIGMA_CONTACT = 0.006
"""How far [m] the lowest collider's height may be from its rest depth (feet sink deeper on
impact: 0.5-13 mm, 10th-90th percentile, in simulated walking)."""
SIGMA_STANCE = 0.3
"""How fast [m/s] the lowest collider may move (it rolls, sinks and slides)."""


@dataclass(frozen=True, kw_only=True)
class BaseEstimate:
    """The free joint's coordinates at some of a log's samples.

    Attributes:
        qpos: Position (world) and orientation (w x y z, world from root body). Shape: (n, 7).
        qvel: Linear velocity (world) and angular velocity (root body frame), as MuJoCo's free
            joint holds them. Shape: (n, 6).
        source: What they come from, in words (for reports).
        world: Whether the horizontal position is the world's (motion capture) or zero.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    source: str
    world: bool


HEADING_NOTE = np.radians(1.0)
"""A heading offset between the IMU and motion capture larger than this is reported."""


def base_source(mocap: bool, accelerometer: bool) -> str:
    """The words :class:`BaseEstimate` ``source`` uses for a log with these streams."""
    used = ["motion capture (/base_pose)"] if mocap else []
    if accelerometer:
        used.append("the accelerometer")
    used.append("the stance foot (the lowest collider at its rest depth, still)")
    return ("IMU orientation and gyro; position and velocity smoothed over the log from "
            + ", ".join(used[:-1]) + (" and " if len(used) > 1 else "") + used[-1])  # fmt: skip


def free_joint(model: mujoco.MjModel) -> int | None:
    """The model's free joint (its floating base), or ``None`` for a fixed base.

    Raises:
        InputError: More than one free joint (a robot has one base).
    """
    free = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if free.size > 1:
        raise InputError(f"the model has {free.size} free joints; a robot log has one base")
    return int(free[0]) if free.size else None


def _span(where: str, topic: str, t_src: np.ndarray, t: np.ndarray) -> None:
    if t_src.size < 2:
        raise InputError(f"{where}: topic {topic} has {t_src.size} message; need at least 2")
    outside = (t < t_src[0] - _SLACK) | (t > t_src[-1] + _SLACK)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise InputError(
            f"{where}: topic {topic} covers {t_src[0]:.3f}-{t_src[-1]:.3f} s, but a state "
            f"sample at {t[i]:.3f} s needs it"
        )


def _interp(t_src: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of each column of ``x`` (N, k) at ``t``. Shape: (n, k)."""
    return np.stack([np.interp(t, t_src, x[:, k]) for k in range(x.shape[1])], axis=1)


def _interp_quat(t_src: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation between the neighbouring samples. Shape: (n, 4)."""
    i = np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, t_src.size - 2)
    u = np.clip((t - t_src[i]) / (t_src[i + 1] - t_src[i]), 0.0, 1.0)
    return quat_slerp(q[i], q[i + 1], u)


def _turned(yaw: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """``quat`` (n, 4) turned by ``yaw`` (n,) about the world's vertical."""
    q_yaw = np.zeros((yaw.size, 4))
    q_yaw[:, 0], q_yaw[:, 3] = np.cos(yaw / 2), np.sin(yaw / 2)
    return quat_mul(q_yaw, quat)


TILT_EVERY = 0.02
"""Time [s] between the samples whose stance sole the mount tilt reads."""


def _sole_tilt(
    model: mujoco.MjModel, log: RobotLog, quat_wb: np.ndarray, floor: int, colliders: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sole_tilt` at samples :data:`TILT_EVERY` apart whose lowest collider is on a
    body with a sole (:func:`sole_frames`); nothing found (infinite error) without one."""
    soles = sole_frames(model, colliders)
    if not soles:
        return np.zeros(3), np.full(3, np.inf)
    fj = free_joint(model)
    jm = JointMap.of(model)
    qa = int(model.jnt_qposadr[fj])
    data = mujoco.MjData(model)
    picks = np.unique(np.searchsorted(log.t, np.arange(log.t[0], log.t[-1], TILT_EVERY)))
    ts, up, sole = [], [], []
    for k in picks:
        data.qpos[:] = model.qpos0
        data.qpos[qa : qa + 7] = 0.0, 0.0, 0.0, *quat_wb[k]
        data.qpos[jm.qadr] = log.q[k]
        mujoco.mj_kinematics(model, data)
        body = lowest_point(model, data, floor, colliders)[2]
        if body not in soles:
            continue
        R_wb = quat_to_matrix(quat_wb[k])
        ts.append(log.t[k])
        up.append(R_wb[2])  # The world's up in the root's axes.
        sole.append(R_wb.T @ data.xmat[body].reshape(3, 3) @ soles[body])
    if not ts:
        return np.zeros(3), np.full(3, np.inf)
    return sole_tilt(np.array(ts), np.array(up), np.array(sole))


def prediction_step(log: RobotLog) -> float:
    """The physics step [s] for predictions of a floating-base log: the longest step up to
    :data:`~humimic.sim.models.MAX_STEP` that divides the log's state interval (20 ms states:
    5 ms; 2 ms states: 2 ms), never under :data:`~humimic.sim.models.PHYSICS_DT`. On the
    floor most of a diagnosis is contact physics; a 5 ms step makes it five times cheaper
    than 1 ms, and it is the step tracking policies are trained at."""
    if log.t.size < 2:
        return PHYSICS_DT
    dt_state = float(np.median(np.diff(log.t)))
    step = dt_state / max(1, int(np.ceil(dt_state / MAX_STEP - 1e-9)))
    return max(step, PHYSICS_DT)


def rest_depth(model: mujoco.MjModel) -> float:
    """How deep [m] the model's feet sink into the floor when it stands: its numeric
    :data:`~humimic.sim.models.REST_DEPTH` (set by
    :func:`~humimic.sim.models.floating_prediction_spec`), else 0."""
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, REST_DEPTH)
    return float(model.numeric_data[model.numeric_adr[i]]) if i >= 0 else 0.0


def estimate_base(
    model: mujoco.MjModel, log: RobotLog, idx: np.ndarray | None = None
) -> BaseEstimate:
    """The floating base's coordinates at the log's state samples ``idx`` (default: all).

    Orientation and angular velocity come from the IMU (its site's fixed rotation in the root
    body undone; with motion capture, its heading turned onto motion capture's world by
    :func:`heading_offset`; the gyro's bias, :func:`gyro_bias`, removed where it shows above
    :data:`GYRO_BIAS_NOTE`; the mount's tilt, :func:`mount_tilt` against motion capture or
    :func:`sole_tilt` against the stance soles, removed above :data:`MOUNT_TILT_NOTE`).
    Position and linear velocity come from the whole log at once
    (:func:`smooth_track`, run on the IMU site's track, so that the accelerometer needs no
    angular acceleration): motion capture's position where the log has ``/base_pose``; the
    accelerometer's specific force where it has ``linear_acceleration``; and at every sample
    the stance foot: the robot's lowest collider is taken to rest on the floor, as deep as the
    model's feet sink standing, which gives a height (read only without motion capture) and
    the linear velocity that keeps that point still given the joint velocities and the gyro.
    Without motion capture the horizontal position is zero (a flat floor does not care).

    Args:
        model: A floating-base model with the log's joints (and the IMU's site).
        log: The log, with ``/imu``.
        idx: State sample indices (``None``: every sample). Shape: (n,).

    Raises:
        InputError: No IMU, an IMU site the model lacks or that is not on the root body, or
            a stream that does not cover the log's states (naming the log and the topic).
    """
    fj, imu, sid = _checked_imu(model, log)
    t = log.t
    _span(log.where, "/imu", imu.t, t)
    att = _attitude(model, log, imu, sid)
    R_wb = quat_to_matrix(att.quat_wb)
    r_w = R_wb @ model.site_pos[sid]  # Root origin to the IMU, world axes. Shape: (n, 3).
    omega_w = np.einsum("nij,nj->ni", R_wb, att.omega_b)
    lever_v = np.cross(omega_w, r_w)
    z_stance, v_stance = _stance(model, log, fj, att)
    pos = np.zeros((t.size, 3))
    sigma = np.full((t.size, 3), np.inf)
    if log.mocap is not None:
        pos[:] = _interp(log.mocap.t, log.mocap.pos_w, t)
        sigma[:] = SIGMA_MOCAP
    else:
        pos[:, 2] = z_stance
        sigma[:, 2] = SIGMA_CONTACT
    acc = None
    if imu.acc_b is not None:
        f_w = np.einsum("nij,nj->ni", quat_to_matrix(att.quat_ws), _interp(imu.t, imu.acc_b, t))
        acc = f_w + model.opt.gravity
    # The IMU site's track (root origin + lever arm), smoothed part by part of the log.
    p_s, v_s = _smoothed_parts(log, acc, pos + r_w, sigma, v_stance + lever_v)
    idx = np.arange(t.size) if idx is None else np.asarray(idx, dtype=np.int64)
    qpos, qvel = np.zeros((idx.size, 7)), np.zeros((idx.size, 6))
    qpos[:, :3] = (p_s - r_w)[idx]
    qpos[:, 3:] = att.quat_wb[idx]
    qvel[:, :3] = (v_s - lever_v)[idx]
    qvel[:, 3:] = att.omega_b[idx]
    world = log.mocap is not None
    if not world:
        qpos[:, :2] = 0.0
    source = base_source(world, acc is not None) + _corrections_note(att, world)
    return BaseEstimate(qpos=qpos, qvel=qvel, source=source, world=world)


def _checked_imu(model: mujoco.MjModel, log: RobotLog) -> tuple[int, ImuLog, int]:
    """The model's free joint, the log's IMU and the IMU's site in the model, checked.

    Raises:
        InputError: A fixed-base model, no IMU, or an IMU site the model lacks or that is
            not on the root body.
    """
    fj = free_joint(model)
    if fj is None:
        raise InputError("estimate_base needs a floating-base model")
    where = log.where
    imu = log.imu
    if imu is None:
        raise InputError(
            f"{where}: a floating-base log needs topic /imu (orientation and angular "
            "velocity of the base) for its predictions"
        )
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, imu.site)
    if sid < 0:
        raise InputError(
            f"{where}: metadata robot.imu_site {imu.site!r} is not a site of the robot"
        )
    root = int(model.jnt_bodyid[fj])
    if int(model.site_bodyid[sid]) != root:
        raise InputError(
            f"{where}: metadata robot.imu_site {imu.site!r} is not on the root body "
            f"{model.body(root).name!r}; only an IMU on the floating base is supported so far"
        )
    return fj, imu, sid


@dataclass(frozen=True, kw_only=True)
class _Attitude:
    """The base's orientation and angular velocity at a log's state samples, from its IMU.

    Attributes:
        quat_ws, quat_wb: World from the IMU's site and from the root body (w x y z, heading
            on motion capture's where the log has it). Shape: (n, 4).
        omega_b: Angular velocity, root body axes. Shape: (n, 3).
        heading: The turn onto motion capture's heading [rad] (zero without it). Shape: (n,).
        floor, colliders: The floor and the robot geoms that collide with it.
        mocap: Whether motion capture's orientation was the reference.
        bias: The gyro's bias [rad/s, IMU axes], removed if ``biased``.
        tilt: The IMU mount's tilt [rad, root axes], removed if ``tilted``.
    """

    quat_ws: np.ndarray
    quat_wb: np.ndarray
    omega_b: np.ndarray
    heading: np.ndarray
    floor: int
    colliders: list[int]
    mocap: bool
    bias: np.ndarray
    biased: bool
    tilt: np.ndarray
    tilted: bool


def _attitude(model: mujoco.MjModel, log: RobotLog, imu: ImuLog, sid: int) -> _Attitude:
    """The base's orientation and angular velocity from the IMU at site ``sid``: the site's
    rotation in the root body undone, the heading turned onto motion capture's, the gyro's
    bias and the mount's tilt removed where they show (see :func:`estimate_base`).

    Raises:
        InputError: Motion capture that does not cover the log's states, or a model with no
            floor.
    """
    t = log.t
    q_bs = model.site_quat[sid] / np.linalg.norm(model.site_quat[sid])  # Body from site.
    R_bs = quat_to_matrix(q_bs)
    omega_b = _interp(imu.t, imu.gyro_b, t) @ R_bs.T
    # The gyro's constant bias, against motion capture's orientation where the log has it
    # (independent of the IMU), else against the IMU's own orientation.
    if log.mocap is not None:
        q_ref = quat_mul(log.mocap.quat_w, np.broadcast_to(q_bs, log.mocap.quat_w.shape))
        bias, bias_se = gyro_bias(log.mocap.t, q_ref, imu.t, imu.gyro_b)
    else:
        bias, bias_se = gyro_bias(imu.t, imu.quat_w, imu.t, imu.gyro_b)
    biased = bool(np.linalg.norm(bias) > max(GYRO_BIAS_NOTE, 5 * np.linalg.norm(bias_se)))
    if biased:
        omega_b = omega_b - bias @ R_bs.T
    quat_ws = _interp_quat(imu.t, imu.quat_w, t)
    quat_wb = quat_mul(quat_ws, quat_conj(np.broadcast_to(q_bs, quat_ws.shape)))
    heading = np.zeros(t.size)
    quat_mo = None
    if log.mocap is not None:
        _span(log.where, "/base_pose", log.mocap.t, t)
        quat_mo = _interp_quat(log.mocap.t, log.mocap.quat_w, t)
        heading = heading_offset(quat_wb, quat_mo, t)
        quat_ws, quat_wb = _turned(heading, quat_ws), _turned(heading, quat_wb)
    f, colliders = floor_and_colliders(model)
    # The IMU's mount tilt (its frame not quite the site's): against motion capture, or
    # against the stance soles, which lie flat on the floor.
    if quat_mo is not None:
        tilt, tilt_se = mount_tilt(quat_wb, quat_mo, t)
    else:
        tilt, tilt_se = _sole_tilt(model, log, quat_wb, f, colliders)
    tilted = bool(np.linalg.norm(tilt) > max(MOUNT_TILT_NOTE, 5 * np.linalg.norm(tilt_se)))
    if tilted:
        angle = float(np.linalg.norm(tilt))
        q_e = np.array([np.cos(angle / 2), *(np.sin(angle / 2) * tilt / angle)])
        quat_wb = quat_mul(quat_wb, np.broadcast_to(quat_conj(q_e), quat_wb.shape))
        omega_b = omega_b @ quat_to_matrix(q_e).T
        if quat_mo is not None:  # What the tilt held of the heading.
            more = heading_offset(quat_wb, quat_mo, t)
            quat_ws, quat_wb = _turned(more, quat_ws), _turned(more, quat_wb)
            heading = heading + more
    return _Attitude(quat_ws=quat_ws, quat_wb=quat_wb, omega_b=omega_b, heading=heading,
                     floor=f, colliders=colliders, mocap=quat_mo is not None, bias=bias,
                     biased=biased, tilt=tilt, tilted=tilted)  # fmt: skip


def _stance(
    model: mujoco.MjModel, log: RobotLog, fj: int, att: _Attitude
) -> tuple[np.ndarray, np.ndarray]:
    """The stance foot at every state sample: the lowest collider rests on the floor, as deep
    as the model's feet sink when it stands (its contacts are soft), and does not move.

    Returns:
        The root's height that puts it there [m] (n,), and the root's linear velocity (world)
        that keeps it still [m/s] (n, 3), given the joints and the angular velocity.
    """
    n = log.t.size
    depth = rest_depth(model)
    jm = JointMap.of(model)
    qa, da = int(model.jnt_qposadr[fj]), int(model.jnt_dofadr[fj])
    data = mujoco.MjData(model)
    jacp = np.zeros((3, model.nv))
    z_stance, v_stance = np.zeros(n), np.zeros((n, 3))
    for k in range(n):
        data.qpos[:] = model.qpos0
        data.qpos[qa : qa + 7] = 0.0, 0.0, 0.0, *att.quat_wb[k]
        data.qpos[jm.qadr] = log.q[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        best, point, body = lowest_point(model, data, att.floor, att.colliders)
        z_stance[k] = -best - depth
        data.qvel[:] = 0.0
        data.qvel[da + 3 : da + 6] = att.omega_b[k]
        data.qvel[jm.dadr] = log.qd[k]
        mujoco.mj_jac(model, data, jacp, None, point, body)
        v_stance[k] = -(jacp @ data.qvel)
    return z_stance, v_stance


def _smoothed_parts(
    log: RobotLog,
    acc: np.ndarray | None,
    pos: np.ndarray,
    sigma: np.ndarray,
    vel: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`smooth_track` of a point on its own over each unbroken part of the log (a gap
    breaks the filter's prediction), with :data:`SIGMA_STANCE` on ``vel``. Shape: (n, 3) each."""
    n = log.t.size
    p_s, v_s = np.zeros((n, 3)), np.zeros((n, 3))
    bounds = np.concatenate([[0], log.gaps() + 1, [n]])
    for a, b in itertools.pairwise(bounds):
        part = slice(int(a), int(b))
        p_s[part], v_s[part] = smooth_track(
            log.t[part], None if acc is None else acc[part], pos[part], sigma[part], vel[part],
            SIGMA_STANCE)  # fmt: skip
    return p_s, v_s


def _corrections_note(att: _Attitude, world: bool) -> str:
    """What :class:`BaseEstimate` ``source`` adds for the corrections made to the IMU: the
    gyro's bias, the mount's tilt and the heading's turn, where they were made."""
    source = ""
    if att.biased:
        source += (f"; the gyro's bias ({', '.join(f'{1e3 * b:+.1f}' for b in att.bias)} mrad/s, "
                   "IMU axes) removed, measured against "
                   + ("motion capture's orientation" if world
                      else "the IMU's own orientation"))  # fmt: skip
    if att.tilted:
        source += (f"; the IMU's mount tilt ({', '.join(f'{np.degrees(v):+.2f}' for v in att.tilt[:2])}"
                   " deg about the root's x and y) removed, measured against "
                   + ("motion capture's orientation" if att.mocap
                      else "the stance soles"))  # fmt: skip
    turn, drift = float(np.mean(att.heading)), float(np.ptp(att.heading))
    if abs(turn) > HEADING_NOTE or drift > HEADING_NOTE:
        source += f"; the IMU's heading turned {np.degrees(turn):+.1f} deg onto motion capture's"
        if drift > HEADING_NOTE:
            source += f", following its drift ({np.degrees(drift):.1f} deg over the log)"
    return source


GYRO_BIAS_NOTE = 0.002
"""A gyro bias [rad/s] larger than this (and than five standard errors) is removed and named."""


GYRO_BIAS_SEGMENT = 1.0
"""Length [s] of the stretches over which the gyro's rotation is compared with a reference's."""


def gyro_bias(
    t_ref: np.ndarray, quat_ref: np.ndarray, t: np.ndarray, gyro: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A gyro's constant bias [rad/s, its own axes] and the bias's standard error, against an
    orientation track of the gyro's frame (``quat_ref``: world from gyro, w x y z, at
    ``t_ref``). The gyro's readings (at ``t``) are integrated into a rotation over each
    stretch of :data:`GYRO_BIAS_SEGMENT`; the rotation that is left between it and the
    track's own over the stretch, over its length, is that stretch's bias (integrating over a
    stretch keeps the track's sample noise out: differentiating it at the sample rate would
    not). Stretches with a gap in either stream (an interval over three times its median) are
    left out.

    An IMU whose orientation output integrates its own gyro carries the bias into that
    orientation where gravity does not correct it (the heading): against the IMU's own
    orientation only the rest shows; against motion capture, all of it.
    """
    dt = np.diff(t)
    if dt.size < 2 or t_ref.size < 3:
        return np.zeros(3), np.full(3, np.inf)
    gap = dt > 3 * np.median(dt)
    # The gyro's orientation track, from the identity at the first sample: each interval
    # turns by the mean of its two readings.
    w = 0.5 * (gyro[:-1] + gyro[1:]) * dt[:, None]
    angle = np.linalg.norm(w, axis=1)
    step = np.concatenate([np.cos(angle / 2)[:, None],
                           (np.sinc(angle / (2 * np.pi)) / 2)[:, None] * w], axis=1)  # fmt: skip
    track = np.zeros((t.size, 4))
    track[0] = 1.0, 0.0, 0.0, 0.0
    for k in range(dt.size):
        track[k + 1] = quat_mul(track[k], step[k])
    ref = _interp_quat(t_ref, quat_ref, t)
    inside = (t >= t_ref[0]) & (t <= t_ref[-1])
    # Where the reference has a gap, its interpolated rotation is not the one it made.
    dt_ref = np.diff(t_ref)
    big = dt_ref > 3 * np.median(dt_ref)
    gap_from, gap_to = t_ref[:-1][big], t_ref[1:][big]
    edges = np.arange(t[inside][0], t[inside][-1], GYRO_BIAS_SEGMENT) if inside.any() else []
    biases = []
    for a in edges:
        i, j = np.searchsorted(t, [a, a + GYRO_BIAS_SEGMENT])
        j = min(j, t.size - 1)
        if j - i < 2 or gap[i:j].any() or not (inside[i] and inside[j]):
            continue
        if np.any((gap_from < t[j]) & (gap_to > t[i])):
            continue
        moved_gyro = quat_mul(quat_conj(track[i]), track[j])
        moved_ref = quat_mul(quat_conj(ref[i]), ref[j])
        left = quat_to_rotvec(quat_mul(quat_conj(moved_gyro), moved_ref))  # End's axes.
        # The bias acted in the axes of every moment of the stretch: what is left is, to
        # second order, the bias as the middle's axes hold it, seen in the end's axes; turn
        # it back into the middle's.
        m = (i + j) // 2
        left = quat_to_matrix(quat_mul(quat_conj(track[m]), track[j])) @ left
        biases.append(-left / (t[j] - t[i]))
    if len(biases) < 2:
        return np.zeros(3), np.full(3, np.inf)
    b = np.array(biases)
    return b.mean(axis=0), b.std(axis=0, ddof=1) / np.sqrt(len(b))


MOUNT_TILT_NOTE = np.radians(0.2)
"""An IMU mount tilt [rad] larger than this (and than five standard errors) is removed and named.
Standing, the G1's soles lean 0.06 deg (their spheres sink unevenly) and read as that much tilt,
while 0.4 / 0.3 deg of roll / pitch left in the base's orientation tripled the held-out k-step
error of standing logs (1.06 -> 3.40 mrad on seed 2; ``benchmarks/sysid_floor_checks.py --only
tilt``): small, but well above the soles' lean."""

TILT_SEGMENT = 1.0
"""Length [s] of the stretches whose median tilt the mount's estimate averages."""

SOLE_FLAT = np.radians(10.0)
"""A stance sole leaning more than this [rad] from the median lean is rolling (heel or toe), or
the foot is not flat: not read (a median about the lean, not the vertical, so that a mount
tilted by more than this is still found)."""


def _segment_mean(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean over :data:`TILT_SEGMENT` stretches of the medians of ``x`` (n, d) within each
    stretch (samples correlate within one; a rolling foot's outliers stay out), and its
    standard error; ``inf`` with fewer than two stretches."""
    if t.size == 0:
        return np.zeros(x.shape[1]), np.full(x.shape[1], np.inf)
    seg = np.floor((t - t[0]) / TILT_SEGMENT).astype(np.int64)
    medians = np.array([np.median(x[seg == k], axis=0) for k in np.unique(seg)])
    if len(medians) < 2:
        return np.zeros(x.shape[1]), np.full(x.shape[1], np.inf)
    return medians.mean(axis=0), medians.std(axis=0, ddof=1) / np.sqrt(len(medians))


def mount_tilt(
    quat_wb: np.ndarray, quat_ref: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The IMU mount's tilt against a reference orientation of the root body (motion capture,
    its heading already the IMU's: see :func:`heading_offset`): the fixed rotation e [rad,
    root body axes, roll and pitch; the yaw is the heading's] with ``quat_wb = quat_ref *
    exp(e)``, and its standard error."""
    d = quat_to_rotvec(quat_mul(quat_conj(quat_ref), quat_wb))
    e, se = _segment_mean(t, d[:, :2])
    return np.array([e[0], e[1], 0.0]), np.array([se[0], se[1], 0.0])


def sole_frames(model: mujoco.MjModel, colliders: list[int]) -> dict[int, np.ndarray]:
    """The bodies with a sole: at least three floor colliders whose centers lie on a plane
    (as the G1's four foot spheres), each with that plane's normal in the body's axes,
    pointing from the sole to the body's origin. Shape of each: (3,)."""
    soles: dict[int, np.ndarray] = {}
    for b in sorted({int(model.geom_bodyid[g]) for g in colliders}):
        centers = np.array([model.geom_pos[g] for g in colliders if model.geom_bodyid[g] == b])
        if len(centers) < 3:
            continue
        c = centers - centers.mean(axis=0)
        _, sv, vt = np.linalg.svd(c)
        if sv[1] < 1e-3 or sv[-1] > 0.05 * sv[1]:  # On a line, or no plane.
            continue
        n = vt[-1]
        soles[b] = n if n @ -centers.mean(axis=0) > 0 else -n
    return soles


def sole_tilt(t: np.ndarray, up_b: np.ndarray, sole_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The IMU mount's tilt from the stance soles: a sole flat on the floor points up, so the
    rotation that turns the sole's normal onto the estimate's up (both in the root body's
    axes, at stance samples: ``up_b``, ``sole_b``, shape (n, 3)) is the orientation's error
    e [rad, root body axes; the component about the up axis is not seen], with
    ``quat_wb = quat_true * exp(e)``; and its standard error. Samples whose sole leans more
    than :data:`SOLE_FLAT` from the median lean are a heel or toe rolling, and not read."""
    # up = exp(-e) sole: e, across the sole, is minus the rotation from the sole to up.
    cross = np.cross(sole_b, up_b)
    sin = np.linalg.norm(cross, axis=1)
    angle = np.arctan2(sin, np.einsum("ni,ni->n", sole_b, up_b))
    e = -cross * (angle / np.maximum(sin, 1e-12))[:, None]
    if e.size == 0:
        return np.zeros(3), np.full(3, np.inf)
    flat = np.linalg.norm(e - np.median(e, axis=0), axis=1) < SOLE_FLAT
    return _segment_mean(t[flat], e[flat])


HEADING_SMOOTH = 1.0
"""The window [s] over which a line is fitted to the IMU's heading offset against motion capture."""


def heading_offset(quat_imu: np.ndarray, quat_mocap: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The yaw [rad] about the world's vertical that turns the IMU's world onto motion
    capture's at each time ``t``: an IMU's tilt is absolute (gravity), its heading is not (it
    starts anywhere and drifts). The per-sample yaw of ``quat_mocap * conj(quat_imu)`` (both
    world from the root body, shape (n, 4)), unwrapped and averaged over
    :data:`HEADING_SMOOTH` about each sample by a straight line (a drift is followed, at the
    log's ends too, where the window is one-sided). Shape: (n,)."""
    d = quat_to_matrix(quat_mul(quat_mocap, quat_conj(quat_imu)))
    yaw = np.unwrap(np.arctan2(d[:, 1, 0], d[:, 0, 0]))
    # A line fitted to the samples within half a window of each sample (times may be uneven),
    # from running sums; its value at the sample.
    s = np.asarray(t, dtype=float) - t[0]
    lo = np.searchsorted(s, s - HEADING_SMOOTH / 2, side="left")
    hi = np.searchsorted(s, s + HEADING_SMOOTH / 2, side="right")

    def window(x: np.ndarray) -> np.ndarray:
        total = np.concatenate([[0.0], np.cumsum(x)])
        return total[hi] - total[lo]

    n, sy = (hi - lo).astype(float), window(yaw)
    st = window(s) - n * s  # Sums of the times relative to each sample, and so on.
    stt = window(s * s) - 2 * s * window(s) + n * s * s
    sty = window(s * yaw) - s * sy
    det = n * stt - st * st
    flat = det <= 1e-12 * np.maximum(n * stt, 1e-300)  # One sample, or all at one time.
    line = np.where(flat, sy / n, (sy * stt - st * sty) / np.where(flat, 1.0, det))
    # Back into (-pi, pi] about the first sample's turn, keeping the series continuous.
    return line - 2 * np.pi * np.round(line[0] / (2 * np.pi))
