"""Pinocchio adapter: a Pinocchio model of a compiled MuJoCo robot, its inverse dynamics in
MuJoCo's coordinates, and payload identification from the joint-torque regressor.

The model is built from the compiled ``mujoco.MjModel`` (not by parsing the MJCF again), so
whatever humimic compiled (explicit actuators, armature, injected masses) is what Pinocchio
sees, with MuJoCo's joint order.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import mujoco
import numpy as np

from humimic.errors import InputError, UnknownNameError

# Pinocchio ships no type stubs, and cmeel puts it on the path at run time (a .pth file), so
# type checkers cannot see it: typed as Any.
pin: Any = importlib.import_module("pinocchio")
SE3: TypeAlias = Any
"""``pinocchio.SE3``: a rigid transform."""

_AXES = {
    (1.0, 0.0, 0.0): pin.JointModelRX,
    (0.0, 1.0, 0.0): pin.JointModelRY,
    (0.0, 0.0, 1.0): pin.JointModelRZ,
}


def _se3(pos: np.ndarray, quat_wxyz: np.ndarray) -> SE3:
    q = np.asarray(quat_wxyz, dtype=np.float64)
    rot = pin.Quaternion(float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    rot.normalize()
    return pin.SE3(rot.matrix(), np.asarray(pos, dtype=np.float64).copy())


def _rotations(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit wxyz quaternions. Shape: (..., 4) -> (..., 3, 3)."""
    w, x, y, z = np.moveaxis(quat_wxyz, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _translation(p: np.ndarray) -> SE3:
    return pin.SE3(np.eye(3), np.asarray(p, dtype=np.float64).copy())


@dataclass(kw_only=True)
class _TreeJoints:
    """What :meth:`PinocchioRobot.from_mujoco` has gathered of the joints so far, in
    MuJoCo's order: the model-wide lists are built body by body.

    Attributes:
        names: The 1-dof joints' names.
        dofs: MuJoCo's dof of each Pinocchio velocity coordinate (the free base's six, then
            one per 1-dof joint).
        lower, upper: Each Pinocchio position coordinate's limits (infinite where MuJoCo's
            joint has none; the free base's seven).
        free_base: The free joint became Pinocchio's free flyer.
        welded: The free joint was welded at ``base_pose`` instead.
    """

    names: list[str] = field(default_factory=list)
    dofs: list[int] = field(default_factory=list)
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    free_base: bool = False
    welded: bool = False


def _joint_model(jtype: mujoco.mjtJoint, axis: np.ndarray, jname: str) -> Any:
    """Pinocchio's joint model of a MuJoCo hinge or slide along ``axis`` (the joint frame's
    axis-aligned revolute joints where the hinge's axis is a coordinate axis: cheaper).

    Raises:
        InputError: Any other kind of joint (ball).
    """
    if jtype == mujoco.mjtJoint.mjJNT_HINGE:
        aligned = _AXES.get((float(axis[0]), float(axis[1]), float(axis[2])))
        return aligned() if aligned else pin.JointModelRevoluteUnaligned(axis)
    if jtype == mujoco.mjtJoint.mjJNT_SLIDE:
        return pin.JointModelPrismaticUnaligned(axis)
    raise InputError(f"joint {jname!r}: {jtype.name} joints are not supported")


def _add_body_joints(
    model: Any,
    mj: mujoco.MjModel,
    b: int,
    cur: SE3,
    jid: int,
    base_pose: np.ndarray | None,
    joints: _TreeJoints,
) -> tuple[SE3, int]:
    """Add MuJoCo body ``b``'s joints to the Pinocchio ``model``, in order, each on the
    previous one (the first on ``jid``, the joint carrying the parent), and record them in
    ``joints``.

    A hinge or slide is placed at its anchor in the current frame ``cur``, after which the
    body's frame is the anchor's inverse offset; the free joint (the model's first) becomes
    the free flyer, or with ``base_pose`` puts the body there, welded to the world.

    Returns:
        The body's frame in the frame of the joint that carries it, and that joint.

    Raises:
        InputError: A free joint that is not the model's first, or a ball joint.
    """
    j0, nj = int(mj.body_jntadr[b]), int(mj.body_jntnum[b])
    for j in range(j0, j0 + nj):
        jtype = mujoco.mjtJoint(int(mj.jnt_type[j]))
        jname = mj.joint(j).name or f"joint{j}"
        if jtype == mujoco.mjtJoint.mjJNT_FREE:
            if j != 0:
                raise InputError(f"joint {jname!r}: only the first joint may be free")
            joints.welded = base_pose is not None
            if base_pose is not None:
                cur = _se3(base_pose[:3], base_pose[3:])
                continue
            # MuJoCo's free joint places the body's frame itself, wherever it was.
            jid = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), jname)
            joints.free_base = True
            cur = pin.SE3.Identity()
            joints.dofs += range(int(mj.jnt_dofadr[j]), int(mj.jnt_dofadr[j]) + 6)
            joints.lower += [-np.inf] * 7
            joints.upper += [np.inf] * 7
            continue
        anchor = np.asarray(mj.jnt_pos[j], dtype=np.float64)
        jm = _joint_model(jtype, np.asarray(mj.jnt_axis[j], dtype=np.float64), jname)
        jid = model.addJoint(jid, jm, cur * _translation(anchor), jname)
        cur = _translation(-anchor)
        joints.names.append(jname)
        joints.dofs.append(int(mj.jnt_dofadr[j]))
        limited = bool(mj.jnt_limited[j])
        joints.lower.append(float(mj.jnt_range[j, 0]) if limited else -np.inf)
        joints.upper.append(float(mj.jnt_range[j, 1]) if limited else np.inf)
    return cur, jid


def _append_body_inertia(model: Any, mj: mujoco.MjModel, b: int, jid: int, cur: SE3) -> np.ndarray:
    """Append MuJoCo body ``b``'s inertia to Pinocchio joint ``jid``, the body's frame being
    ``cur`` in the joint's.

    Returns:
        The body's centre of mass in the joint's frame. Shape: (3,).
    """
    rot = cur.rotation @ pin.Quaternion(*map(float, mj.body_iquat[b])).matrix()
    com = cur.act(np.asarray(mj.body_ipos[b], dtype=np.float64))
    inertia = pin.Inertia(float(mj.body_mass[b]), com, rot @ np.diag(mj.body_inertia[b]) @ rot.T)
    model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
    return com


@dataclass(frozen=True, kw_only=True)
class PinocchioRobot:
    """A Pinocchio model of a MuJoCo robot, in MuJoCo's joint order.

    Attributes:
        model: The ``pinocchio.Model`` (gravity, armature and joint limits from MuJoCo).
        data: Its ``pinocchio.Data`` workspace (not thread-safe: one per thread).
        free_base: The first joint is MuJoCo's free joint (Pinocchio's free flyer). Its
            coordinates differ between the two; :meth:`to_pinocchio` and
            :meth:`inverse_dynamics` convert.
        joint_names: The 1-dof joints, in MuJoCo's (and the model's) order.
        body_joint: MuJoCo body name -> the Pinocchio joint that carries it (0: the universe,
            for bodies welded to the world).
        body_placement: MuJoCo body name -> its frame relative to that joint's frame.
        body_com: MuJoCo body name -> its own centre of mass in that joint's frame.
        friction_loss, damping: MuJoCo's ``dof_frictionloss`` and ``dof_damping``, which
            the Pinocchio model does not express. Shape: (nv,).
    """

    model: Any
    data: Any
    free_base: bool
    joint_names: tuple[str, ...]
    body_joint: dict[str, int]
    body_placement: dict[str, SE3]
    body_com: dict[str, np.ndarray]
    friction_loss: np.ndarray
    damping: np.ndarray

    @classmethod
    def from_mujoco(
        cls, mj: mujoco.MjModel, *, base_pose: np.ndarray | None = None
    ) -> PinocchioRobot:
        """Build the Pinocchio model of a compiled MuJoCo model's kinematic tree.

        Each MuJoCo body's frame, inertia and joints (hinge, slide, and a free base as the
        first joint) become Pinocchio joints and inertias; a body without joints is fused
        into its parent's joint. Joint damping, springs, friction loss and limits as
        constraints are not carried (inverse dynamics here is ``M qdd + C qd + g``, armature
        included in ``M``).

        Args:
            mj: The compiled model.
            base_pose: x y z qw qx qy qz: weld the free-jointed root body there instead (a
                gantry; as ``humimic sysid`` logs record). Shape: (7,).

        Raises:
            InputError: A ball joint, a free joint that is not the model's first joint, or a
                ``base_pose`` for a model without a free joint.
        """
        model = pin.Model()
        model.name = "humimic"
        model.gravity = pin.Motion(np.asarray(mj.opt.gravity, dtype=np.float64), np.zeros(3))
        # Per MuJoCo body: the Pinocchio joint carrying it, and the body frame in that joint's.
        joint_of = [0] * mj.nbody
        frame_in_joint = [pin.SE3.Identity()] * mj.nbody
        frame_id = [0] * mj.nbody
        com_in_joint = [np.zeros(3)] * mj.nbody
        joints = _TreeJoints()
        for b in range(1, mj.nbody):
            parent = int(mj.body_parentid[b])
            name = mj.body(b).name or f"body{b}"
            cur = frame_in_joint[parent] * _se3(mj.body_pos[b], mj.body_quat[b])
            cur, jid = _add_body_joints(model, mj, b, cur, joint_of[parent], base_pose, joints)
            com_in_joint[b] = _append_body_inertia(model, mj, b, jid, cur)
            frame_id[b] = model.addBodyFrame(name, jid, cur, frame_id[parent])
            joint_of[b], frame_in_joint[b] = jid, cur
        if base_pose is not None and not joints.welded:
            raise InputError("base_pose: the model has no free base to weld")
        dofs = joints.dofs
        model.armature = np.array(mj.dof_armature[dofs], dtype=np.float64)
        model.lowerPositionLimit = np.array(joints.lower, dtype=np.float64)
        model.upperPositionLimit = np.array(joints.upper, dtype=np.float64)
        bodies = [mj.body(b).name for b in range(1, mj.nbody)]
        return cls(
            model=model,
            data=model.createData(),
            free_base=joints.free_base,
            joint_names=tuple(joints.names),
            body_joint=dict(zip(bodies, joint_of[1:], strict=True)),
            body_placement=dict(zip(bodies, frame_in_joint[1:], strict=True)),
            body_com=dict(zip(bodies, com_in_joint[1:], strict=True)),
            friction_loss=np.array(mj.dof_frictionloss[dofs], dtype=np.float64),
            damping=np.array(mj.dof_damping[dofs], dtype=np.float64),
        )

    def to_pinocchio(
        self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """States in MuJoCo's coordinates -> Pinocchio's.

        The free base: MuJoCo's ``qpos`` has a wxyz quaternion, Pinocchio's xyzw; MuJoCo's
        linear velocity is in the world frame, Pinocchio's in the base frame
        (``v_b = R^T v_w``), and so ``a_b = R^T a_w - w_b x v_b``. Hinge and slide joints
        are the same in both.

        Shapes: (..., nq), (..., nv), (..., nv) in and out.
        """
        if not self.free_base:
            return qpos, qvel, qacc
        q, v, a = qpos.copy(), qvel.copy(), qacc.copy()
        q[..., 3:7] = qpos[..., [4, 5, 6, 3]]
        rot = _rotations(qpos[..., 3:7])
        v[..., :3] = np.einsum("...ji,...j->...i", rot, qvel[..., :3])
        a[..., :3] = np.einsum("...ji,...j->...i", rot, qacc[..., :3])
        a[..., :3] -= np.cross(qvel[..., 3:6], v[..., :3])
        return q, v, a

    def inverse_dynamics(self, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
        """Generalized forces ``M(q) qdd + C(q, qd) qd + g(q)`` (RNEA), in MuJoCo's
        coordinates: for a free base, the force in the world frame and the torque in the base
        frame (as ``mj_inverse``'s ``qfrc_inverse`` of a model without constraints or passive
        forces).

        Args:
            qpos: Shape: (T, nq). qvel, qacc: Shape: (T, nv).

        Returns:
            Shape: (T, nv).
        """
        q, v, a = self.to_pinocchio(qpos, qvel, qacc)
        out = np.empty(qvel.shape)
        for t in range(q.shape[0]):
            out[t] = pin.rnea(self.model, self.data, q[t], v[t], a[t])
        if self.free_base:  # The force on the base: base frame -> world frame.
            out[:, :3] = np.einsum("tij,tj->ti", _rotations(qpos[:, 3:7]), out[:, :3])
        return out

    def _joint(self, body: str) -> int:
        jid = self.body_joint.get(body)
        if jid is None:
            raise UnknownNameError(f"no body {body!r} in the robot")
        if jid == 0:
            raise InputError(f"body {body!r} is welded to the world: no joint torque feels it")
        return jid


def point_mass_parameters(mass: float, com: np.ndarray) -> np.ndarray:
    """Pinocchio's 10 inertial parameters of a point mass at ``com`` (joint frame).

    Shape: (10,).
    """
    return pin.Inertia(
        mass, np.asarray(com, dtype=np.float64), np.zeros((3, 3))
    ).toDynamicParameters()


@dataclass(frozen=True, kw_only=True)
class PayloadFit:
    """A payload identified by linear least squares on the torque regressor.

    Attributes:
        body: The body it is on.
        mass: Added mass [kg].
        mass_std: Its standard error from the fit's residual [kg] (white residuals). A log
            whose motion does not separate the mass from the other unknowns shows it here:
            with ``fit_com=True`` the G1's torso, whose waist axes meet near its joint frame's
            origin so that only its mass moment ``dm c`` shows, gets thousands of kg. Where
            the torques cannot feel the unknowns at all, ``mass`` is NaN and this infinite.
        com: Where the added mass sits, in the body's frame [m]; the body's own centre of
            mass when fitted with ``fit_com=False``; NaN when fitted but the mass is within
            three standard errors of zero. Shape: (3,).
        residual_rms: RMS of the torque residual after the fit, over the rows used [N m].
        rows: Torque rows used (samples x joints that feel the body, after the masks).
        seconds: Wall time of the fit.
    """

    body: str
    mass: float
    mass_std: float
    com: np.ndarray
    residual_rms: float
    rows: int
    seconds: float


def accelerations(
    t: np.ndarray, qd: np.ndarray, breaks: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Joint accelerations by central differences of joint velocities, and the samples
    where they hold.

    A drive's torque jumps when a new command arrives, and so does the acceleration; a
    central difference across such a jump belongs to neither side. Samples whose
    neighbours' interval ``(t[i-1], t[i+1])`` holds a break (a command time) are marked
    invalid, as are the first and last.

    Args:
        t: Sample times. Shape: (T,).
        qd: Joint velocities. Shape: (T, nv).
        breaks: Times at which the applied torque may jump. Shape: (M,).

    Returns:
        ``qdd`` (T, nv) and ``valid`` (T,) bool.
    """
    qdd = np.gradient(qd, t, axis=0)
    valid = np.ones(len(t), dtype=bool)
    valid[[0, -1]] = False
    if breaks is not None and len(t) > 2:
        tol = 1e-6 * float(np.median(np.diff(t)))
        lo = np.searchsorted(breaks, t[:-2] + tol, side="left")
        hi = np.searchsorted(breaks, t[2:] - tol, side="right")
        valid[1:-1] &= hi <= lo
    return qdd, valid


def identify_payload(
    robot: PinocchioRobot,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    tau: np.ndarray,
    body: str,
    *,
    samples: np.ndarray | None = None,
    fit_com: bool = False,
    friction: np.ndarray | None = None,
    min_speed: float = 0.05,
    limit_margin: float = 0.02,
    instrument: bool = True,
) -> PayloadFit:
    """Identify a mass added to ``body`` from joint states and joint torques, no search.

    The torques are linear in each body's inertial parameters, ``tau = Y(q, qd, qdd) pi +
    armature qdd``, so what the nominal model leaves, ``r = tau - RNEA_nominal(q, qd, qdd)``,
    is ``Y_b(q, qd, qdd) d_pi`` for a payload on ``b`` (``Y_b``: the 10 columns of ``b``'s
    joint). A point mass ``dm`` at ``c`` (joint frame) adds ``d_pi = [dm, dm c, dm (|c|^2 I -
    c c^T)]``. ``fit_com=False``: one unknown ``dm`` at the body's own centre of mass (as
    ``humimic sysid``'s ``payload_mass`` effect adds it). ``fit_com=True``: four unknowns
    ``dm, dm c`` on the first four columns; when ``dm`` is clear of zero, the point mass's
    second moments are then moved to the known side and the four refitted (twice).

    Accelerations differentiated from noisy velocities put the same noise into the regressor
    and into ``r`` (through ``-M qdd``), which biases least squares (4% low on a 0.8 kg
    wrist payload under ``humimic sysid simulate``'s sensor noise). With ``instrument=True``
    the fit is an instrumental-variable one, ``(W^T A)^-1 W^T r``, whose instruments ``W``
    are the same columns at zero velocity and acceleration (the gravity terms): they depend on
    the positions only, not on the acceleration noise.

    Rows are (sample, joint) pairs of the joints on the path from the base to ``b`` (no
    other joint's torque depends on ``b``). A joint's row is dropped where it moves slower
    than ``min_speed`` (friction loss sticks there, its force unknown) or lies within
    ``limit_margin`` of a range end (a limit's constraint force), both forces acting on that
    joint's row alone.

    Args:
        robot: The fixed-base nominal robot (no free base).
        q, qd, qdd: Joint positions, velocities, accelerations. Shape: (T, nv).
        tau: Joint torques the drives applied. Shape: (T, nv).
        body: The body the payload is on.
        samples: Samples to use (e.g. ``valid`` of :func:`accelerations`). Shape: (T,).
        fit_com: Fit where the mass sits, not only how much.
        friction: Each joint's known Coulomb friction [N m], taken as ``-friction sign(qd)``
            in the dynamics; ``None``: the model's (MuJoCo's ``frictionloss``). The model's
            joint damping is subtracted too. Shape: (nv,).
        min_speed: [rad/s].
        limit_margin: [rad or m].
        instrument: Instrumental variables (above) instead of plain least squares.

    Raises:
        InputError: The robot has a free base, the body is welded to the world, the shapes
            disagree, or no row is left.
        UnknownNameError: No such body.
    """
    start = time.perf_counter()
    jid, chain = _payload_chain(robot, body, q, qd, qdd, tau)
    friction = robot.friction_loss if friction is None else np.asarray(friction, dtype=float)
    Y, Z, r = _payload_rows(
        robot, jid, chain, q, qd, qdd, tau, friction,
        samples=samples, min_speed=min_speed, limit_margin=limit_margin,
    )  # fmt: skip
    if len(r) == 0:
        raise InputError(f"payload on {body!r}: no sample moves the joints that carry it")
    return _fit_payload(robot, body, Y, Z, r, fit_com=fit_com, instrument=instrument, start=start)


def _payload_chain(
    robot: PinocchioRobot,
    body: str,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    tau: np.ndarray,
) -> tuple[int, list[int]]:
    """The joint that carries ``body``, and the velocity indices of the joints on the path
    from the base to it (the only ones whose torque depends on the body), after checking
    :func:`identify_payload`'s inputs.

    Raises:
        InputError: The robot has a free base, the shapes disagree, or the body is welded to
            the world.
        UnknownNameError: No such body.
    """
    if robot.free_base:
        raise InputError("payload identification needs a fixed-base model (base_pose=...)")
    model, nv, T = robot.model, robot.model.nv, q.shape[0]
    for what, x in (("q", q), ("qd", qd), ("qdd", qdd), ("tau", tau)):
        if x.ndim != 2 or x.shape != (T, nv):
            raise InputError(f"{what}: expected shape ({T}, {nv}), got {x.shape}")
    jid = robot._joint(body)
    return jid, [int(model.joints[j].idx_v) for j in list(model.supports[jid])[1:]]


def _payload_rows(
    robot: PinocchioRobot,
    jid: int,
    chain: list[int],
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    tau: np.ndarray,
    friction: np.ndarray,
    *,
    samples: np.ndarray | None,
    min_speed: float,
    limit_margin: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of :func:`identify_payload`'s fit: one per used sample and joint of
    ``chain`` that moves at least ``min_speed`` and lies ``limit_margin`` inside its range.

    Returns:
        ``Y``: the 10 regressor columns of joint ``jid`` (Shape: (rows, 10)); ``Z``: its
        first four at zero velocity and acceleration, the instruments (Shape: (rows, 4));
        ``r``: the torque the nominal model, its friction loss and its damping leave
        (Shape: (rows,)).
    """
    model, nv, T = robot.model, robot.model.nv, q.shape[0]
    use = np.ones(T, dtype=bool) if samples is None else np.asarray(samples, dtype=bool)
    idx = np.flatnonzero(use)
    qc = q[idx][:, chain]
    lo, hi = model.lowerPositionLimit[chain], model.upperPositionLimit[chain]
    keep = (np.abs(qd[idx][:, chain]) >= min_speed) & (qc > lo + limit_margin)
    keep &= qc < hi - limit_margin  # (n, k): one row per sample and joint.
    cols = slice(10 * (jid - 1), 10 * jid)
    Y = np.zeros((len(idx), len(chain), 10))
    Z = np.zeros((len(idx), len(chain), 4))
    r = np.zeros((len(idx), len(chain)))
    zero = np.zeros(nv)
    for n, t in enumerate(idx):
        tau_nominal = pin.rnea(model, robot.data, q[t], qd[t], qdd[t])
        y = pin.computeJointTorqueRegressor(model, robot.data, q[t], qd[t], qdd[t])
        Y[n] = np.reshape(y, (nv, -1))[chain, cols]
        y = pin.computeJointTorqueRegressor(model, robot.data, q[t], zero, zero)
        Z[n] = np.reshape(y, (nv, -1))[chain, cols][:, :4]
        r[n] = (tau[t] - tau_nominal)[chain]
        r[n] -= (friction * np.sign(qd[t]) + robot.damping * qd[t])[chain]
    return Y[keep], Z[keep], r[keep]


def _fit_payload(
    robot: PinocchioRobot,
    body: str,
    Y: np.ndarray,
    Z: np.ndarray,
    r: np.ndarray,
    *,
    fit_com: bool,
    instrument: bool,
    start: float,
) -> PayloadFit:
    """:func:`identify_payload`'s least-squares (or instrumental-variable) fit on the rows of
    :func:`_payload_rows`; ``start`` is when the identification began (its ``seconds``)."""
    com_body = robot.body_com[body]
    if fit_com:
        A, W = Y[:, :4], Z if instrument else Y[:, :4]
    else:  # One column: a unit mass at the body's centre of mass.
        unit = point_mass_parameters(1.0, com_body)
        A, W = (Y @ unit)[:, None], ((Z @ unit[:4]) if instrument else (Y @ unit))[:, None]
    WA = W.T @ A
    if not np.linalg.cond(WA) < 1e12:  # The joints' torques do not feel these unknowns.
        return PayloadFit(
            body=body,
            mass=float("nan"),
            mass_std=float("inf"),
            com=np.full(3, np.nan),
            residual_rms=float(np.sqrt(np.mean(r**2))),
            rows=len(r),
            seconds=time.perf_counter() - start,
        )
    WA_inv = np.linalg.pinv(WA)
    sol = WA_inv @ (W.T @ r)
    mass, com_j = float(sol[0]), com_body
    # Covariance of (W^T A)^-1 W^T r for white residuals.
    res = r - A @ sol
    cov = float(res @ res) / max(len(r) - A.shape[1], 1) * WA_inv @ (W.T @ W) @ WA_inv.T
    mass_std = float(np.sqrt(max(cov[0, 0], 0.0)))
    if fit_com:
        if abs(mass) > 3.0 * mass_std:  # A centre of no (significant) mass means nothing.
            mass, com_j, res = _refit_second_moments(Y, A, W, WA_inv, r, sol)
        else:
            com_j = np.full(3, np.nan)
    return PayloadFit(
        body=body,
        mass=mass,
        mass_std=mass_std,
        com=np.asarray(robot.body_placement[body].actInv(com_j)),
        residual_rms=float(np.sqrt(np.mean(res**2))),
        rows=len(r),
        seconds=time.perf_counter() - start,
    )


def _refit_second_moments(
    Y: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    WA_inv: np.ndarray,
    r: np.ndarray,
    sol: np.ndarray,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Refit ``sol``, the fit of ``dm, dm c`` on the columns ``A`` (the first four of ``Y``)
    with instruments ``W``, twice, each time with the second moments of the point mass it
    places (the other six columns, which follow from ``dm`` and ``c``) moved to the known
    side.

    Returns:
        The mass, where it sits (joint frame; Shape: (3,)) and the fit's residual (Shape:
        (rows,)).
    """
    mass, known = float(sol[0]), np.zeros_like(r)
    for _ in range(2):  # The point mass's second moments to the known side.
        com_j = sol[1:] / mass
        known = Y[:, 4:] @ point_mass_parameters(mass, com_j)[4:]
        sol = WA_inv @ (W.T @ (r - known))
        mass = float(sol[0])
    com_j = sol[1:] / mass
    return mass, com_j, r - known - A @ sol
