"""Physics parameters of a batch of robot models and where they sit in a compiled model.

:class:`PhysicsParams` is the array form of "this robot differs from the nominal one" for a
batch of envs (what domain randomization samples and every backend applies);
:class:`ModelLayout` reads a training model's actuated joints, sensors and nominal values.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numpy as np

from humimic.errors import InputError, UnknownNameError
from humimic.sim.delta import ALL, Change, Kind, RobotDelta

if TYPE_CHECKING:  # MuJoCo loads on use: a DR profile is read without it.
    import mujoco


@dataclass(frozen=True, kw_only=True)
class PhysicsParams:
    """Per-env physics parameters (domain randomization). Every array has a leading env axis n.

    Attributes:
        friction: Sliding friction of the floor and of every robot collider. Shape: (n,).
        mass_scale: Multiplier of each robot body's mass and inertia. Shape: (n, num_bodies).
        com_offset: Added to the CoM of the backend's ``com_body`` [m]. Shape: (n, 3).
        kp_scale: Multiplier of each actuator's stiffness. Shape: (n, num_actuators).
        kd_scale: Multiplier of each actuator's damping. Shape: (n, num_actuators).
        armature_scale: Multiplier of each actuated joint's armature. Shape: (n, num_actuators).
    """

    friction: np.ndarray
    mass_scale: np.ndarray
    com_offset: np.ndarray
    kp_scale: np.ndarray
    kd_scale: np.ndarray
    armature_scale: np.ndarray

    def select(self, rows: slice | np.ndarray) -> PhysicsParams:
        """The parameters of some envs: every array indexed by ``rows`` on its env axis."""
        return PhysicsParams(**{f.name: getattr(self, f.name)[rows] for f in fields(self)})


def _robot_bodies(model: mujoco.MjModel) -> list[int]:
    return [b for b in range(1, model.nbody) if model.body_weldid[b] != 0]


# Model fields that domain randomization (PhysicsParams) changes, with their nominal values kept.
DR_FIELDS = (
    "geom_friction",
    "body_mass",
    "body_inertia",
    "body_ipos",
    "actuator_gainprm",
    "actuator_biasprm",
    "dof_armature",
)


@dataclass(frozen=True, kw_only=True)
class ModelLayout:
    """What every backend reads off a training model: the actuated joints, the read-out
    sensors, the bodies and colliders that domain randomization changes, and their nominal
    values. Build it with :meth:`of`.

    Attributes:
        joint_names: The actuated joints, in actuator (= qpos) order.
        dof: Their dof addresses. Shape: (J,).
        joint_range: Their position limits. Shape: (J, 2).
        default_joint_pos: The home pose (first keyframe, else ``qpos0``). Shape: (J,).
        kp: Nominal PD stiffness. Shape: (J,).
        effort_limit: Torque limits. Shape: (J,).
        robot_bodies: Bodies that move with the robot (mass randomization). Shape: (Bm,).
        collider_geoms: Geoms that collide (friction randomization). Shape: (G,).
        com_body: The body whose CoM ``PhysicsParams.com_offset`` moves, or -1.
        sensor_slices: Where ``pos``, ``quat``, ``lin``, ``ang``, ``found``, ``force`` sit in a
            row of sensor data.
        nominal: Copies of the :data:`DR_FIELDS` of the model.
        friction_ratio: Per collider, the model's sliding friction over the robot's own
            (a physics file's floor or sole friction), which a friction draw is scaled by:
            DR varies the friction around the file's, instead of replacing it. ``None``:
            the robot's own (no file changed it). Shape: (G,).
    """

    body_names: tuple[str, ...]
    contact_body_names: tuple[str, ...]
    foot_body_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    dof: np.ndarray
    joint_range: np.ndarray
    default_joint_pos: np.ndarray
    kp: np.ndarray
    effort_limit: np.ndarray
    robot_bodies: np.ndarray
    collider_geoms: np.ndarray
    com_body: int
    sensor_slices: dict[str, slice]
    nominal: dict[str, np.ndarray]
    friction_ratio: np.ndarray | None = None

    @classmethod
    def of(
        cls,
        model: mujoco.MjModel,
        body_names: Sequence[str],
        contact_body_names: Sequence[str] = (),
        foot_body_names: Sequence[str] = (),
        com_body: str | None = None,
    ) -> ModelLayout:
        """The layout of a model from :func:`~humimic.sim.models.training_model` built with
        these names.

        Raises:
            InputError: If the actuators do not drive the joints after the free joint in qpos
                order, or the sensors are not those of
                :func:`~humimic.sim.models.training_model`.
            UnknownNameError: If ``com_body`` is not in the model.
        """
        joints = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
        qadr = [int(model.jnt_qposadr[j]) for j in joints]
        if qadr != list(range(model.nq - model.nu, model.nq)):
            raise InputError(
                "the actuators must drive the joints after the free joint, in qpos order"
            )
        import mujoco

        cb = -1
        if com_body is not None:
            cb = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, com_body)
            if cb < 0:
                raise UnknownNameError(f"com_body {com_body!r} is not in the model")
        nb, nc, nf = len(body_names), len(contact_body_names), len(foot_body_names)
        expected = 13 * nb + nc + 3 * nf
        if model.nsensordata != expected:
            raise InputError(
                f"the model has {model.nsensordata} sensor values, expected {expected} for "
                f"{nb} bodies, {nc} contact bodies and {nf} feet: build it with training_model()"
            )
        home = model.key_qpos[0] if model.nkey else model.qpos0
        return cls(
            body_names=tuple(body_names),
            contact_body_names=tuple(contact_body_names),
            foot_body_names=tuple(foot_body_names),
            joint_names=tuple(model.joint(j).name for j in joints),
            dof=np.array([model.jnt_dofadr[j] for j in joints]),
            joint_range=np.array([model.jnt_range[j] for j in joints]),
            default_joint_pos=np.array(home[qadr]),
            kp=model.actuator_gainprm[:, 0].copy(),
            effort_limit=model.actuator_forcerange[:, 1].copy(),
            robot_bodies=np.array(_robot_bodies(model)),
            collider_geoms=np.flatnonzero((model.geom_contype | model.geom_conaffinity) != 0),
            com_body=cb,
            sensor_slices={
                "pos": slice(0, 3 * nb),
                "quat": slice(3 * nb, 7 * nb),
                "lin": slice(7 * nb, 10 * nb),
                "ang": slice(10 * nb, 13 * nb),
                "found": slice(13 * nb, 13 * nb + nc),
                "force": slice(13 * nb + nc, expected),
            },
            nominal={name: getattr(model, name).copy() for name in DR_FIELDS},
        )

    @property
    def com_column(self) -> int:
        """The column of :attr:`com_body` in :attr:`robot_bodies` (and in
        ``PhysicsParams.mass_scale``), or -1."""
        hit = np.flatnonzero(self.robot_bodies == self.com_body) if self.com_body >= 0 else []
        return int(hit[0]) if len(hit) else -1

    def fields(self, params: PhysicsParams) -> dict[str, np.ndarray]:
        """The :data:`DR_FIELDS` of the n models ``params`` describes (the nominal values where
        domain randomization leaves them): the batched form of :meth:`delta`. Shape of each: (n, *the model field's shape)."""
        nom, cb = self.nominal, self.com_body
        rb, g, dof = self.robot_bodies, self.collider_geoms, self.dof
        n = len(params.friction)
        out = {f: np.repeat(nom[f][None], n, axis=0) for f in DR_FIELDS}
        fr = params.friction[:, None]
        out["geom_friction"][:, g, 0] = (
            fr if self.friction_ratio is None else fr * self.friction_ratio
        )
        out["body_mass"][:, rb] = nom["body_mass"][rb] * params.mass_scale
        out["body_inertia"][:, rb] = nom["body_inertia"][rb] * params.mass_scale[..., None]
        if cb >= 0:
            out["body_ipos"][:, cb] += params.com_offset
        kp = nom["actuator_gainprm"][:, 0] * params.kp_scale
        out["actuator_gainprm"][:, :, 0] = kp
        out["actuator_biasprm"][:, :, 1] = -kp
        out["actuator_biasprm"][:, :, 2] = nom["actuator_biasprm"][:, 2] * params.kd_scale
        out["dof_armature"][:, dof] = nom["dof_armature"][dof] * params.armature_scale
        return out

    def delta(self, params: PhysicsParams, k: int, model: mujoco.MjModel) -> RobotDelta:
        """Env ``k`` of ``params`` as a delta of the nominal model (what a physics file with
        these values would apply through the spec; :meth:`fields` is the batched form).

        Args:
            params: Parameters of n envs.
            k: The env.
            model: The model this layout was read from (for names).

        Raises:
            ValueError: If the layout scales friction draws (:attr:`friction_ratio`): a delta
                sets one floor friction.
        """
        if self.friction_ratio is not None:
            raise ValueError("friction draws scaled per collider have no single floor friction")
        names = [model.body(int(b)).name for b in self.robot_bodies]
        items: list[Change] = [
            Change(op="set", kind="floor", field="friction", names=(ALL,),
                   value=(float(params.friction[k]),)),
            *(Change(op="scale", kind="body", field="mass", names=(b,), value=(float(s),))
              for b, s in zip(names, params.mass_scale[k], strict=True)),
        ]  # fmt: skip
        if self.com_body >= 0:
            off = tuple(float(x) for x in params.com_offset[k])
            items.append(Change(op="add", kind="body", field="com",
                                names=(model.body(self.com_body).name,), value=off))  # fmt: skip
        scaled: tuple[tuple[str, Kind, np.ndarray], ...] = (
            ("kp", "actuator", params.kp_scale), ("kd", "actuator", params.kd_scale),
            ("armature", "joint", params.armature_scale),
        )  # fmt: skip
        for field, kind, values in scaled:
            items += [
                Change(op="scale", kind=kind, field=field, names=(j,), value=(float(s),))
                for j, s in zip(self.joint_names, values[k], strict=True)
            ]
        return RobotDelta(tuple(items))

    def nominal_params(self, n: int) -> PhysicsParams:
        """Parameters that leave the model nominal, for ``n`` envs."""
        j, b = len(self.joint_names), len(self.robot_bodies)
        friction = float(self.nominal["geom_friction"][self.collider_geoms, 0].max())
        return PhysicsParams(
            friction=np.full(n, friction),
            mass_scale=np.ones((n, b)),
            com_offset=np.zeros((n, 3)),
            kp_scale=np.ones((n, j)),
            kd_scale=np.ones((n, j)),
            armature_scale=np.ones((n, j)),
        )


def physics_copies(
    model: mujoco.MjModel, layout: ModelLayout, params: PhysicsParams
) -> list[mujoco.MjModel]:
    """One copy of ``model`` per row of ``params``, with the randomized fields as a backend
    sets them (and the constants ``mj_setConst`` derives from them)."""
    import mujoco

    values = layout.fields(params)
    out = []
    for k in range(len(params.friction)):
        m = copy.copy(model)
        for name, v in values.items():
            getattr(m, name)[:] = v[k]
        mujoco.mj_setConst(m, mujoco.MjData(m))
        out.append(m)
    return out
