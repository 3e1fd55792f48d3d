"""Batched physics backends behind one :class:`PhysicsBackend` protocol: a caller sets joint
targets, steps and reads batched arrays; it never touches MuJoCo itself.
:class:`MujocoCpuBackend` is the CPU one; :class:`~humimic.sim.warp_backend.MujocoWarpBackend`
implements the same protocol with MuJoCo Warp (GPU).
"""

from __future__ import annotations

import contextlib
import copy
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

from humimic.errors import InputError
from humimic.sim import rollout
from humimic.sim.params import ModelLayout, PhysicsParams

StepMethod = Literal["rollout", "threads"]


@dataclass(frozen=True, kw_only=True)
class PhysicsReadout:
    """Batched simulator state after a step or a reset (views of backend buffers; read-only).

    Attributes:
        qpos: Shape: (num_envs, nq). qvel: Shape: (num_envs, nv) (free joint: world linear,
            body angular velocity, as MuJoCo stores them).
        body_pos_w: Frame origins of the read bodies. Shape: (num_envs, B, 3).
        body_quat_w: wxyz. Shape: (num_envs, B, 4).
        body_lin_vel_w: Linear velocity of the frame origins. Shape: (num_envs, B, 3).
        body_ang_vel_w: Angular velocity. Shape: (num_envs, B, 3).
        contact_found: Number of floor contacts of each contact body. Shape: (num_envs, C).
        foot_force: Net floor contact force magnitude on each foot [N]. Shape: (num_envs, F).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    body_pos_w: np.ndarray
    body_quat_w: np.ndarray
    body_lin_vel_w: np.ndarray
    body_ang_vel_w: np.ndarray
    contact_found: np.ndarray
    foot_force: np.ndarray


class PhysicsBackend(Protocol):
    """What callers need from a batched simulator. Arrays are float64 numpy.

    Body kinematics and contacts come from the sensors
    :func:`~humimic.sim.models.training_model` compiles in, so every backend returns them from
    ``sensordata``. ``body_names`` (kinematics read), ``contact_body_names`` (contact counts) and
    ``foot_body_names`` (contact forces) fix the layout of :class:`PhysicsReadout`;
    ``joint_names`` fixes the actuator/joint order (MuJoCo order of the actuated joints).
    """

    num_envs: int
    nq: int
    nv: int
    nu: int
    num_bodies_total: int
    layout: ModelLayout
    """The model's layout: actuated joints, sensors, randomized bodies and nominal values."""

    @property
    def nthread(self) -> int | None:
        """CPU threads that step the envs (``None``: the backend steps on a GPU)."""
        ...

    joint_names: tuple[str, ...]
    body_names: tuple[str, ...]
    contact_body_names: tuple[str, ...]
    foot_body_names: tuple[str, ...]
    joint_range: np.ndarray
    """Joint position limits of the actuated joints. Shape: (J, 2)."""
    default_joint_pos: np.ndarray
    """The robot's home pose (first keyframe, else ``qpos0``) of the actuated joints.
    Shape: (J,)."""
    kp: np.ndarray
    """Nominal PD stiffness of each actuator. Shape: (J,)."""
    effort_limit: np.ndarray
    """Torque limit of each actuator. Shape: (J,)."""

    def reset_to(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Set the state of some envs (and recompute what ``read`` returns for them).
        Delay lines (actuators with a command history) start full of the first command the
        next :meth:`step` sends: a controller had been sending it while the robot held the
        start pose.

        Args:
            env_ids: Shape: (n,). qpos: Shape: (n, nq). qvel: Shape: (n, nv).
        """
        ...

    def push(self, env_ids: np.ndarray, dqvel: np.ndarray) -> None:
        """Add to the velocity of some envs, keeping the rest of their state (actuator
        activations and delay lines), and recompute what ``read`` returns for them.

        Args:
            env_ids: Shape: (n,). dqvel: Shape: (n, nv).
        """
        ...

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        """Set the PD position targets of all envs. Shape: (num_envs, J)."""
        ...

    def step(self, n_substeps: int) -> None:
        """Advance every env by ``n_substeps`` physics steps with the current targets."""
        ...

    def read(self) -> PhysicsReadout:
        """The current state of every env."""
        ...

    def set_params(self, env_ids: np.ndarray, params: PhysicsParams) -> None:
        """Apply per-env physics parameters (leading axis of ``params`` matches ``env_ids``)."""
        ...

    @property
    def sensor_slices(self) -> dict[str, slice]:
        """Where the read-out sensors sit in a row of sensor data."""
        ...

    def nominal_params(self, n: int) -> PhysicsParams:
        """Parameters that leave the model nominal, for ``n`` envs."""
        ...

    def env_state(self, env_id: int) -> np.ndarray:
        """Env ``env_id``'s full physics state (``mjSTATE_FULLPHYSICS``). Shape: (nstate,)."""
        ...

    def rollout(
        self, state: np.ndarray, controls: np.ndarray, warmstart: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Open-loop rollouts of every env from full physics states, one control per physics
        step (see :meth:`MujocoCpuBackend.rollout`)."""
        ...

    def close(self) -> None:
        """Release threads or device memory."""
        ...


@runtime_checkable
class TensorBackend(Protocol):
    """A backend whose state lives in torch tensors on ``device`` (the warp backend): the env
    sets targets and reads the state without a copy through the host."""

    device: torch.device

    def set_ctrl_tensor(self, ctrl: torch.Tensor) -> None:
        """Set the PD position targets of all envs. Shape: (num_envs, J)."""
        ...

    def read_into(self, out: torch.Tensor) -> None:
        """The state in the env's layout (joint positions, joint velocities, then the sensors:
        body positions, quaternions, linear and angular velocities, contact counts, foot force
        magnitudes), written into ``out``. Shape: (num_envs, 2J + 13B + C + F)."""
        ...


def _as_slice(idx: np.ndarray) -> slice | np.ndarray:
    """``idx`` as a basic slice when it is a contiguous increasing run, else ``idx``."""
    if idx.size and np.array_equal(idx, np.arange(idx[0], idx[0] + idx.size)):
        return slice(int(idx[0]), int(idx[0]) + idx.size)
    return idx


class LayoutBackend:
    """What every backend takes from its model's :class:`ModelLayout`: the
    :class:`PhysicsBackend` attributes the env reads."""

    layout: ModelLayout
    nq: int
    nv: int
    nu: int
    num_bodies_total: int
    body_names: tuple[str, ...]
    contact_body_names: tuple[str, ...]
    foot_body_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    joint_range: np.ndarray
    default_joint_pos: np.ndarray
    kp: np.ndarray
    effort_limit: np.ndarray

    def _take_layout(self, model: mujoco.MjModel, layout: ModelLayout) -> None:
        self.layout = layout
        self.nq, self.nv, self.nu = model.nq, model.nv, model.nu
        self.num_bodies_total = len(layout.robot_bodies)
        self.body_names = layout.body_names
        self.contact_body_names = layout.contact_body_names
        self.foot_body_names = layout.foot_body_names
        self.joint_names = layout.joint_names
        self.joint_range = layout.joint_range
        self.default_joint_pos = layout.default_joint_pos
        self.kp = layout.kp
        self.effort_limit = layout.effort_limit

    @property
    def sensor_slices(self) -> dict[str, slice]:
        """Where the read-out sensors sit in a row of sensor data: ``pos``, ``quat``,
        ``lin``, ``ang`` (Shape: (3B,) / (4B,) / (3B,) / (3B,)), ``found`` and ``force``."""
        return dict(self.layout.sensor_slices)

    def nominal_params(self, n: int) -> PhysicsParams:
        """Parameters that leave the model nominal, for ``n`` envs."""
        return self.layout.nominal_params(n)

    def _readout(self, qpos: np.ndarray, qvel: np.ndarray, sens: np.ndarray) -> PhysicsReadout:
        """The readout of these batched states and sensor rows (views where possible)."""
        n, sl = len(qpos), self.layout.sensor_slices
        return PhysicsReadout(
            qpos=qpos,
            qvel=qvel,
            body_pos_w=sens[:, sl["pos"]].reshape(n, -1, 3),
            body_quat_w=sens[:, sl["quat"]].reshape(n, -1, 4),
            body_lin_vel_w=sens[:, sl["lin"]].reshape(n, -1, 3),
            body_ang_vel_w=sens[:, sl["ang"]].reshape(n, -1, 3),
            contact_found=sens[:, sl["found"]],
            foot_force=np.linalg.norm(sens[:, sl["force"]].reshape(n, -1, 3), axis=-1),
        )


class MujocoCpuBackend(LayoutBackend):
    """``num_envs`` MuJoCo CPU simulations of one training model, stepped through
    ``mujoco.rollout`` (C++ thread pool) or a Python thread pool over ``mj_step``.

    Args:
        model: A model from :func:`~humimic.sim.models.training_model` (its sensors define
            the read-out).
        num_envs: Number of envs.
        body_names: The ``body_names`` the model was built with (same order).
        contact_body_names: The ``contact_body_names`` the model was built with.
        foot_body_names: The ``foot_body_names`` the model was built with.
        com_body: Body whose CoM ``PhysicsParams.com_offset`` moves.
        per_env_models: Give every env its own ``MjModel`` copy, needed for
            :meth:`set_params`. Without it all envs share ``model``.
        method: ``"rollout"`` (``mujoco.rollout``) or ``"threads"`` (Python thread pool).
        nthread: Worker threads (default ``os.cpu_count()``).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        num_envs: int,
        *,
        body_names: Sequence[str],
        contact_body_names: Sequence[str] = (),
        foot_body_names: Sequence[str] = (),
        com_body: str | None = None,
        per_env_models: bool = False,
        method: StepMethod = "rollout",
        nthread: int | None = None,
    ) -> None:
        if num_envs < 1:
            raise InputError(f"num_envs: must be at least 1, got {num_envs}")
        if method not in ("rollout", "threads"):
            raise InputError(f"method: expected 'rollout' or 'threads', got {method!r}")
        self.num_envs = num_envs
        self.method: StepMethod = method
        self.nthread = max(1, min(nthread or os.cpu_count() or 1, num_envs))
        self._model = model
        lay = ModelLayout.of(model, body_names, contact_body_names, foot_body_names, com_body)
        self._take_layout(model, lay)
        self._per_env = per_env_models
        self._models = [copy.copy(model) for _ in range(num_envs)] if per_env_models else []
        self._ctrl = np.zeros((num_envs, self.nu))
        self._qpos = np.tile(model.qpos0, (num_envs, 1))
        self._qvel = np.zeros((num_envs, self.nv))
        self._sens = np.zeros((num_envs, model.nsensordata))
        # Rollout state layout (mjSTATE_FULLPHYSICS): time, qpos, qvel, act, ...
        self._spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self._nstate = mujoco.mj_stateSize(model, self._spec)
        self._state = np.zeros((num_envs, self._nstate))
        self._scratch = [mujoco.MjData(model) for _ in range(self.nthread)]
        # Actuators with a command history (a transport delay, e.g. from a physics file), and
        # the envs whose delay lines still wait for the first command after a reset.
        self._hist_acts = np.flatnonzero(model.actuator_history[:, 0] > 0)
        self._unprimed = np.zeros(num_envs, dtype=bool)
        if method == "threads":
            self._datas = [mujoco.MjData(self.model_of(i)) for i in range(num_envs)]
            self._pool: ThreadPoolExecutor | None = ThreadPoolExecutor(self.nthread)
            self._rollout: mj_rollout.Rollout | None = None
        else:
            self._datas = []
            self._pool = None
            self._rollout = mj_rollout.Rollout(nthread=self.nthread)
        self._out_state = np.zeros((num_envs, 1, self._nstate))
        self._out_sens = np.zeros((num_envs, 1, model.nsensordata))
        self._ctrl_seq = np.zeros((num_envs, 1, self.nu))
        self.reset_to(np.arange(num_envs), self._qpos.copy(), self._qvel.copy())

    def model_of(self, env_id: int) -> mujoco.MjModel:
        """The model env ``env_id`` simulates."""
        return self._models[env_id] if self._per_env else self._model

    # ----------------------------------------------------------------------------- state

    def reset_to(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        qpos = np.asarray(qpos, dtype=np.float64).reshape(len(env_ids), self.nq)
        qvel = np.asarray(qvel, dtype=np.float64).reshape(len(env_ids), self.nv)
        for k, i in enumerate(env_ids):
            m = self.model_of(int(i))
            d = self._datas[i] if self._datas else self._scratch[0]
            mujoco.mj_resetData(m, d)
            d.qpos[:] = qpos[k]
            d.qvel[:] = qvel[k]
            d.ctrl[:] = self._ctrl[i]
            if self._hist_acts.size:  # Until the first command: the reset pose.
                self._init_history(m, d, qpos[k][m.jnt_qposadr[m.actuator_trnid[:, 0]]])
                self._unprimed[i] = True
            mujoco.mj_forward(m, d)
            self._qpos[i] = d.qpos
            self._qvel[i] = d.qvel
            self._sens[i] = d.sensordata
            mujoco.mj_getState(m, d, self._state[i], self._spec)

    def push(self, env_ids: np.ndarray, dqvel: np.ndarray) -> None:
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        dqvel = np.asarray(dqvel, dtype=np.float64).reshape(len(env_ids), self.nv)
        for k, i in enumerate(env_ids):
            m = self.model_of(int(i))
            if self._datas:  # Threads: each env's MjData holds its state.
                d = self._datas[i]
            else:
                d = self._scratch[0]
                mujoco.mj_setState(m, d, self._state[i], self._spec)
                d.ctrl[:] = self._ctrl[i]
            d.qvel[:] += dqvel[k]
            mujoco.mj_forward(m, d)
            self._qpos[i] = d.qpos
            self._qvel[i] = d.qvel
            self._sens[i] = d.sensordata
            mujoco.mj_getState(m, d, self._state[i], self._spec)

    def _init_history(self, m: mujoco.MjModel, d: mujoco.MjData, ctrl: np.ndarray) -> None:
        """Fill every delay line with a constant command. ``ctrl``: Shape: (nu,)."""
        dt = m.opt.timestep
        for a in self._hist_acts:
            n = int(m.actuator_history[a, 0])
            times = -dt * np.arange(n - 1, -1, -1, dtype=np.float64).reshape(n, 1)
            values = np.full((n, 1), ctrl[a])
            mujoco.mj_initCtrlHistory(m, d, int(a), times, values)

    def _prime_histories(self) -> None:
        """Fill the delay lines of the envs reset since the last step with their first
        command: a controller had been sending it while the robot held the start pose (as the
        tracking env's DR delay starts with the action base's targets in flight), not targets
        equal to the joint angles, which would let the robot sag under gravity for the length
        of the delay at every episode start."""
        for i in np.flatnonzero(self._unprimed):
            m = self.model_of(int(i))
            if self._datas:
                self._init_history(m, self._datas[i], self._ctrl[i])
            else:
                d = self._scratch[0]
                mujoco.mj_setState(m, d, self._state[i], self._spec)
                self._init_history(m, d, self._ctrl[i])
                mujoco.mj_getState(m, d, self._state[i], self._spec)
        self._unprimed[:] = False

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        self._ctrl[:] = ctrl

    def step(self, n_substeps: int) -> None:
        if self._unprimed.any():
            self._prime_histories()
        if self.method == "rollout":
            self._step_rollout(n_substeps)
        else:
            self._step_threads(n_substeps)

    def _step_rollout(self, n_substeps: int) -> None:
        assert self._rollout is not None
        if self._out_state.shape[1] != n_substeps:
            self._out_state = np.zeros((self.num_envs, n_substeps, self._nstate))
            self._out_sens = np.zeros((self.num_envs, n_substeps, self._model.nsensordata))
            self._ctrl_seq = np.zeros((self.num_envs, n_substeps, self.nu))
        self._ctrl_seq[:] = self._ctrl[:, None, :]
        rollout.batched(
            self._models if self._per_env else [self._model] * self.num_envs,
            self._scratch, self._state, self._ctrl_seq, nstep=n_substeps, runner=self._rollout,
            state_out=self._out_state, sensor_out=self._out_sens, skip_checks=True,
        )  # fmt: skip
        self._state[:] = self._out_state[:, -1]
        self._qpos[:] = self._state[:, 1 : 1 + self.nq]
        self._qvel[:] = self._state[:, 1 + self.nq : 1 + self.nq + self.nv]
        self._sens[:] = self._out_sens[:, -1]

    def env_state(self, env_id: int) -> np.ndarray:
        """Env ``env_id``'s full physics state (a copy). Shape: (``mj_stateSize``,)."""
        return self._state[env_id].copy()

    def rollout(
        self, state: np.ndarray, controls: np.ndarray, warmstart: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Open-loop rollouts of every env from given full physics states, each on its env's
        model, under a control per physics step; the envs' own states stay as they were.

        Args:
            state: Start states (``mjSTATE_FULLPHYSICS``). Shape: (num_envs, ``mj_stateSize``).
            controls: PD targets of every physics step. Shape: (num_envs, nstep, nu).
            warmstart: The constraint solver's warm start (``qacc_warmstart``) at the start,
                Shape: (num_envs, nv); default zeros. A full physics state does not hold it,
                and with a bounded number of solver iterations it changes the result: giving it
                makes a rollout exactly reproduce ``mj_step`` from the same ``MjData``.

        Returns:
            The state after each step, Shape: (num_envs, nstep, ``mj_stateSize``), and the sensor
            data after each step, Shape: (num_envs, nstep, nsensordata).

        Raises:
            InputError: If the backend steps with the thread pool, or on wrong shapes.
        """
        if self._rollout is None:
            raise InputError("rollout needs the backend's 'rollout' stepping method")
        n, nstep = self.num_envs, int(controls.shape[1])
        if state.shape != (n, self._nstate) or controls.shape != (n, nstep, self.nu):
            raise InputError(
                f"rollout: expected states ({n}, {self._nstate}) and controls ({n}, nstep, "
                f"{self.nu}), got {state.shape} and {controls.shape}"
            )
        out_state = np.zeros((n, nstep, self._nstate))
        out_sens = np.zeros((n, nstep, self._model.nsensordata))
        warm = np.zeros((n, self.nv)) if warmstart is None else np.asarray(warmstart, float)
        if warm.shape != (n, self.nv):
            raise InputError(f"rollout: warmstart must be ({n}, {self.nv}), got {warm.shape}")
        rollout.batched(
            self._models if self._per_env else [self._model] * n, self._scratch, state, controls,
            nstep=nstep, warmstart=warm, runner=self._rollout, state_out=out_state,
            sensor_out=out_sens, skip_checks=True,
        )  # fmt: skip
        return out_state, out_sens

    def _step_threads(self, n_substeps: int) -> None:
        assert self._pool is not None
        chunks = np.array_split(np.arange(self.num_envs), self.nthread)

        def work(ids: np.ndarray) -> None:
            for i in ids:
                m, d = self.model_of(int(i)), self._datas[i]
                d.ctrl[:] = self._ctrl[i]
                for _ in range(n_substeps):
                    mujoco.mj_step(m, d)
                self._qpos[i] = d.qpos
                self._qvel[i] = d.qvel
                self._sens[i] = d.sensordata

        for f in [self._pool.submit(work, c) for c in chunks]:
            f.result()

    def read(self) -> PhysicsReadout:
        return self._readout(self._qpos, self._qvel, self._sens)

    # ------------------------------------------------------------------------ parameters

    def set_params(self, env_ids: np.ndarray, params: PhysicsParams) -> None:
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if not self._per_env:
            raise InputError(
                "set_params needs per-env models: build the backend with per_env_models=True"
            )
        values = self.layout.fields(params)
        for k, i in enumerate(env_ids):
            m = self._models[i]
            for name, v in values.items():
                getattr(m, name)[:] = v[k]
            d = self._datas[i] if self._datas else self._scratch[0]
            qpos, qvel = d.qpos.copy(), d.qvel.copy()
            mujoco.mj_setConst(m, d)
            d.qpos[:], d.qvel[:] = qpos, qvel

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._rollout is not None:
            self._rollout.close()
            self._rollout = None

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()
