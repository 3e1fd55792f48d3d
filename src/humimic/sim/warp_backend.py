"""The MuJoCo Warp backend: :class:`MujocoWarpBackend`, ``num_envs`` worlds of one training
model stepped by MJWarp on a GPU (or, slowly, on the CPU), behind the same
:class:`~humimic.sim.backend.PhysicsBackend` interface as the CPU backend. It needs the optional
extra ``humimic[gpu]`` (``mujoco-warp``, which brings ``warp-lang``): :func:`warp_available`.
"""

from __future__ import annotations

import contextlib
import importlib.util
from collections.abc import Iterator, Sequence
from typing import Any

import mujoco
import numpy as np
import torch

from humimic.errors import HumimicError, InputError, MissingDependencyError
from humimic.sim.backend import LayoutBackend, PhysicsReadout
from humimic.sim.params import DR_FIELDS, ModelLayout, PhysicsParams
from humimic.sim.setconst import InertiaConstants

# Derived constants that mujoco_warp.set_const writes per world when DR fields are batched.
_DERIVED_FIELDS = ("body_subtreemass", "body_invweight0", "dof_invweight0", "actuator_acc0")
# Most contacts one collider makes with a plane (MuJoCo's plane colliders).
_PLANE_CONTACTS = {
    mujoco.mjtGeom.mjGEOM_SPHERE: 1,
    mujoco.mjtGeom.mjGEOM_ELLIPSOID: 1,
    mujoco.mjtGeom.mjGEOM_CAPSULE: 2,
}
_CHECK_EVERY = 50  # Steps between overflow checks (each one a host sync).


def warp_available() -> bool:
    """Whether ``mujoco_warp`` can be imported (the ``humimic[gpu]`` extra)."""
    return importlib.util.find_spec("mujoco_warp") is not None


def _import_warp() -> tuple[Any, Any]:
    if not warp_available():
        raise MissingDependencyError(
            "the warp backend needs MuJoCo Warp: pip install 'humimic[gpu]' (mujoco-warp)"
        )
    import warp as wp

    # Before mujoco_warp initializes warp: warnings only (no banner, no kernel-load lines on
    # stdout, where the benchmarks print JSON).
    wp.config.log_level = wp.LOG_WARNING
    import mujoco_warp as mjw

    return wp, mjw


def capacity(model: mujoco.MjModel) -> tuple[int, int]:
    """Contacts and constraint rows per world that no state of a robot touching only the floor
    can exceed: (nconmax, njmax).

    The bounds are every collider's largest number of contacts with a plane, 4 rows per contact
    (pyramidal cone, condim 3) and one row per joint limit. An overflow (a larger ``condim``, a
    user's smaller setting) raises :class:`~humimic.errors.HumimicError` naming the setting
    (:meth:`MujocoWarpBackend.check_overflow`) rather than dropping contacts silently.
    """
    col = np.flatnonzero((model.geom_contype | model.geom_conaffinity) != 0)
    plane = mujoco.mjtGeom.mjGEOM_PLANE
    robot = [g for g in col if model.geom_type[g] != plane]
    ncon = sum(_PLANE_CONTACTS.get(mujoco.mjtGeom(model.geom_type[g]), 4) for g in robot)
    rows_per_contact = max(2 * (int(model.geom_condim[g]) - 1) for g in robot) if robot else 0
    return max(ncon, 1), max(rows_per_contact * ncon + int(model.jnt_limited.sum()), 1)


def _torch_device(device: str | torch.device) -> torch.device:
    """The torch device a backend on ``device`` simulates on: ``cuda`` with its index (the
    current CUDA device's when none is given), or ``cpu``.

    Raises:
        InputError: No CUDA on this machine for a ``cuda`` device, or another device type.
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"device {device}: CUDA is not available on this machine")
        dev = torch.device("cuda", torch.cuda.current_device() if dev.index is None else dev.index)
    elif dev.type != "cpu":
        raise InputError(f"device {device}: the warp backend runs on 'cuda' or 'cpu'")
    return dev


class MujocoWarpBackend(LayoutBackend):
    """``num_envs`` MJWarp worlds of one training model.

    * **Same model, same read-out.** It simulates the model of
      :func:`~humimic.sim.models.training_model` and reads the same sensors as
      :class:`~humimic.sim.backend.MujocoCpuBackend`, so the env's rewards, observations,
      terminations and domain randomization are the CPU backend's (the parity test,
      ``tests/test_warp_backend.py``, steps both from the same states).
    * **Zero copies.** Every array the env touches (``qpos``, ``qvel``, ``ctrl``,
      ``sensordata`` and the randomized model fields) is a torch view of the warp array
      (``wp.to_torch``): the env writes PD targets into ``ctrl`` and reads the state with
      tensor ops on the device (:meth:`set_ctrl_tensor`, :meth:`read_into`).
    * **CUDA graphs.** On a GPU the physics steps of one env step are captured once as a CUDA
      graph and replayed (one launch instead of hundreds of kernel launches per physics
      step); likewise the forward pass after resets.
    * **Domain randomization** batches the randomized fields per world (:meth:`set_params`).
    * **Resets** write the state of the reset worlds with tensor ops, and one forward pass
      (captured) recomputes their sensors when the state is next read, whatever number of
      resets and pushes came before.
    * **Capacity.** MJWarp allocates contacts and constraint rows up front; the defaults
      (:func:`capacity`) cannot overflow for a robot that touches only the floor, and an
      overflow raises rather than dropping contacts silently (:meth:`check_overflow`).

    It also serves the dynamics retargeter (:meth:`rollout`, the CPU backend's open-loop
    rollouts from given states).

    Args:
        model: A model from :func:`~humimic.sim.models.training_model`.
        num_envs: Number of envs (worlds).
        body_names: The ``body_names`` the model was built with (same order).
        contact_body_names: The ``contact_body_names`` the model was built with.
        foot_body_names: The ``foot_body_names`` the model was built with.
        com_body: Body whose CoM ``PhysicsParams.com_offset`` moves.
        per_env_models: Batch the randomized model fields per world, needed for
            :meth:`set_params`.
        device: ``cuda``, ``cuda:N`` or ``cpu`` (slow; tests).
        nconmax: Contacts per world (pooled over worlds); default :func:`capacity`.
        njmax: Constraint rows per world; default :func:`capacity`.
        cuda_graph: Replay the physics steps as a CUDA graph (GPU only).

    Raises:
        MissingDependencyError: Without ``mujoco_warp``.
        InputError: On bad sizes, or a model MJWarp cannot simulate, or actuators with a
            command history (the transport delay of a physics file), which this backend does
            not simulate.
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
        device: str | torch.device = "cuda",
        nconmax: int | None = None,
        njmax: int | None = None,
        cuda_graph: bool = True,
    ) -> None:
        wp, mjw = _import_warp()
        self._wp, self._mjw = wp, mjw
        if num_envs < 1:
            raise InputError(f"num_envs: must be at least 1, got {num_envs}")
        if model.actuator_history[:, 0].any():
            raise InputError(
                "the warp backend does not simulate actuators with a command history (a "
                "physics file's delay) yet: use the CPU backend for this model"
            )
        dev = _torch_device(device)
        self.device = dev
        self._wp_device = wp.get_device(str(dev))
        self.num_envs = num_envs
        self.nthread: int | None = None
        lay = ModelLayout.of(model, body_names, contact_body_names, foot_body_names, com_body)
        self._take_layout(model, lay)
        self._per_env = per_env_models
        bound_con, bound_rows = capacity(model)
        self.nconmax = bound_con if nconmax is None else int(nconmax)
        self.njmax = bound_rows if njmax is None else int(njmax)
        if self.nconmax < 1 or self.njmax < 1:
            raise InputError(f"nconmax, njmax: must be at least 1, got {nconmax}, {njmax}")
        self.cuda_graph = cuda_graph and dev.type == "cuda"

        self._put_model(model, per_env_models)
        self._take_views(model, lay, per_env_models)
        # Compile every kernel of a step and a forward pass before any capture, then start
        # all worlds at qpos0, at rest.
        with self._scope():
            mjw.step(self._m, self._d)
        qpos0 = np.tile(model.qpos0, (num_envs, 1))
        self.reset_to(np.arange(num_envs), qpos0, np.zeros((num_envs, self.nv)))

    def _put_model(self, model: mujoco.MjModel, per_env_models: bool) -> None:
        """Copy ``model`` to the device (the randomized fields and the constants derived from
        them batched per world with ``per_env_models``) and allocate the worlds' data.

        Raises:
            InputError: A model MJWarp cannot simulate.
        """
        mjw, num_envs = self._mjw, self.num_envs
        batch = {f: num_envs for f in (*DR_FIELDS, *_DERIVED_FIELDS)} if per_env_models else {}
        with self._scope():
            try:
                self._m = mjw.put_model(model, batch_sizes=batch)
            except NotImplementedError as e:
                raise InputError(f"MuJoCo Warp cannot simulate this model: {e}") from None
            # No printed warnings: the solver's iteration limits are reached routinely (10
            # iterations, as mjlab), and check_overflow raises on a capacity overflow.
            self._m.opt.warn_overflow = 0
            self._d = mjw.make_data(model, nworld=num_envs, nconmax=self.nconmax, njmax=self.njmax)

    def _take_views(self, model: mujoco.MjModel, lay: ModelLayout, per_env_models: bool) -> None:
        """Take the torch views of the device arrays the backend reads and writes, and set up
        the bookkeeping of resets, graphs and overflow checks.

        Raises:
            InputError: A model whose full physics state holds more than time, qpos, qvel and
                act.
        """
        num_envs, dev = self.num_envs, self.device
        t = self._wp.to_torch
        d, m = self._d, self._m
        self._qpos, self._qvel, self._ctrl = t(d.qpos), t(d.qvel), t(d.ctrl)
        self._sens, self._overflow = t(d.sensordata), t(d.overflow)
        self._warmstart, self._time = t(d.qacc_warmstart), t(d.time)
        self._act = t(d.act) if model.na else None
        self._nstate = mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_FULLPHYSICS))
        if self._nstate != 1 + model.nq + model.nv + model.na:
            raise InputError(
                "the warp backend keeps time, qpos, qvel and act of a full physics state: this "
                "model's state holds more (mocap bodies, user data or plugins)"
            )
        self._fields = (
            {f: t(getattr(m, f)) for f in (*DR_FIELDS, *_DERIVED_FIELDS)} if per_env_models else {}
        )
        # The constants mj_setConst derives from the randomized fields, batched on the device.
        self._constants = InertiaConstants(model, dev) if per_env_models else None
        self._pending = False
        self._n_sens_copy = lay.sensor_slices["found"].stop  # pos, quat, lin, ang, found
        self._force = lay.sensor_slices["force"]
        self._graphs: dict[str, Any] = {}
        self._steps = 0
        self._reset_mask = torch.zeros(num_envs, dtype=torch.bool, device=dev)

    # ----------------------------------------------------------------------------- streams

    @contextlib.contextmanager
    def _scope(self) -> Iterator[None]:
        """Run warp work on the backend's device, ordered after the torch work queued so far
        on the current torch stream, and torch work queued later after it."""
        wp = self._wp
        with wp.ScopedDevice(self._wp_device):
            if self.device.type != "cuda":
                yield
                return
            torch_stream = wp.stream_from_torch(torch.cuda.current_stream(self.device))
            warp_stream = wp.get_stream(self._wp_device)
            warp_stream.wait_stream(torch_stream)
            yield
            torch_stream.wait_stream(warp_stream)

    def _run(self, key: str, fn: Any) -> None:
        """``fn()`` (warp launches only), replayed from a CUDA graph captured at its first call
        when graphs are on."""
        wp = self._wp
        with self._scope():
            if not self.cuda_graph:
                fn()
                return
            graph = self._graphs.get(key)
            if graph is None:
                with wp.ScopedCapture(device=self._wp_device) as cap:
                    fn()
                graph = self._graphs[key] = cap.graph
            wp.capture_launch(graph)

    # ------------------------------------------------------------------------------- state

    def _mark(self, ids: torch.Tensor) -> None:
        """The worlds ``ids`` changed state: recompute what ``read`` returns for them before
        the next read (:meth:`_refresh`)."""
        self._reset_mask[ids] = True
        self._pending = True

    def _refresh(self) -> None:
        """The forward pass the marked worlds wait for (one for all of them; it runs over all
        worlds, and the others keep the sensor data their last step left)."""
        if not self._pending:
            return
        kept = self._sens.clone()
        self._run("forward", lambda: self._mjw.forward(self._m, self._d))
        torch.where(self._reset_mask[:, None], self._sens, kept, out=self._sens)
        self._reset_mask.zero_()
        self._pending = False

    def _ids(self, env_ids: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(env_ids, dtype=np.int64).reshape(-1), device=self.device)

    def _rows(self, x: np.ndarray, n: int, width: int) -> torch.Tensor:
        t = torch.as_tensor(np.asarray(x, dtype=np.float32).reshape(n, width))
        return t.to(self.device, non_blocking=True)

    def reset_to(self, env_ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        ids = self._ids(env_ids)
        n = int(ids.numel())
        # mj_resetData's effect on what the dynamics read; the control is kept (CPU backend).
        self._qpos[ids] = self._rows(qpos, n, self.nq)
        self._qvel[ids] = self._rows(qvel, n, self.nv)
        self._warmstart[ids] = 0.0
        self._time[ids] = 0.0
        if self._act is not None:
            self._act[ids] = 0.0
        self._mark(ids)

    def push(self, env_ids: np.ndarray, dqvel: np.ndarray) -> None:
        ids = self._ids(env_ids)
        self._qvel[ids] += self._rows(dqvel, int(ids.numel()), self.nv)
        self._mark(ids)

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        self._ctrl.copy_(torch.as_tensor(ctrl))

    def set_ctrl_tensor(self, ctrl: torch.Tensor) -> None:
        """Set the PD targets of all envs from a tensor (any device). Shape: (num_envs, J)."""
        self._ctrl.copy_(ctrl)

    def step(self, n_substeps: int) -> None:
        mjw, m, d = self._mjw, self._m, self._d

        def steps() -> None:
            for _ in range(n_substeps):
                mjw.step(m, d)

        if self._pending:  # A step recomputes every world's sensors: no forward pass needed.
            self._reset_mask.zero_()
            self._pending = False
        self._run(f"step{n_substeps}", steps)
        self._steps += 1
        if self._steps % _CHECK_EVERY == 0:
            self.check_overflow()

    def check_overflow(self) -> None:
        """Raise if any world has run out of contacts or constraint rows since the backend was
        built (MJWarp's overflow flags stay set).

        Raises:
            HumimicError: Naming the setting to raise.
        """
        ot = self._mjw.OverflowType
        caps = {
            int(ot.NEFC): f"constraint rows (njmax = {self.njmax})",
            int(ot.BROADPHASE): f"collision pairs (nconmax = {self.nconmax})",
            int(ot.NARROWPHASE): f"contacts (nconmax = {self.nconmax})",
            int(ot.NJMAX_NNZ): f"constraint Jacobian entries (njmax = {self.njmax})",
        }
        flags = 0
        for v in self._overflow.unique().tolist():  # One host sync.
            flags |= int(v)
        hit = [what for bit, what in caps.items() if flags & bit]
        if hit:
            raise HumimicError(
                f"MuJoCo Warp ran out of {', '.join(hit)}: contacts were dropped. Raise "
                "nconmax / njmax (TrackingConfig.warp)"
            )

    def _state_parts(self) -> list[torch.Tensor]:
        """The warp arrays of a full physics state (``mjSTATE_FULLPHYSICS``), in its order."""
        parts = [self._time[:, None], self._qpos, self._qvel]
        return parts if self._act is None else [*parts, self._act]

    def env_state(self, env_id: int) -> np.ndarray:
        """Env ``env_id``'s full physics state (``mjSTATE_FULLPHYSICS``). Shape: (nstate,)."""
        row = torch.cat([p[env_id] for p in self._state_parts()])
        return row.double().cpu().numpy()

    def rollout(
        self, state: np.ndarray, controls: np.ndarray, warmstart: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Open-loop rollouts of every env from given full physics states under a control per
        physics step, as :meth:`MujocoCpuBackend.rollout
        <humimic.sim.backend.MujocoCpuBackend.rollout>` (the same arguments and results);
        the envs' own states stay as they were.

        Raises:
            InputError: On wrong shapes.
        """
        n, nstep = self.num_envs, int(controls.shape[1])
        if state.shape != (n, self._nstate) or controls.shape != (n, nstep, self.nu):
            raise InputError(
                f"rollout: expected states ({n}, {self._nstate}) and controls ({n}, nstep, "
                f"{self.nu}), got {state.shape} and {controls.shape}"
            )
        if warmstart is not None and warmstart.shape != (n, self.nv):
            raise InputError(f"rollout: warmstart must be ({n}, {self.nv}), got {warmstart.shape}")
        parts = self._state_parts()
        own = [p.clone() for p in (*parts, self._ctrl, self._warmstart, self._sens)]
        widths = [p.shape[1] for p in parts]
        start = self._rows(state, n, self._nstate)
        for dst, src in zip(parts, start.split(widths, dim=1), strict=True):
            dst.copy_(src)
        self._warmstart.copy_(0.0 if warmstart is None else self._rows(warmstart, n, self.nv))
        ctrl = self._rows(controls, n, nstep * self.nu).view(n, nstep, self.nu)
        out_state = torch.empty(n, nstep, self._nstate, device=self.device)
        out_sens = torch.empty(n, nstep, self._sens.shape[1], device=self.device)
        mjw, m, d = self._mjw, self._m, self._d
        for k in range(nstep):
            self._ctrl.copy_(ctrl[:, k])
            self._run("step1", lambda: mjw.step(m, d))
            out_state[:, k] = torch.cat(parts, dim=1)
            out_sens[:, k] = self._sens
        for dst, src in zip((*parts, self._ctrl, self._warmstart, self._sens), own, strict=True):
            dst.copy_(src)
        return out_state.double().cpu().numpy(), out_sens.double().cpu().numpy()

    def read(self) -> PhysicsReadout:
        self._refresh()
        qpos, qvel, sens = (t.double().cpu().numpy() for t in (self._qpos, self._qvel, self._sens))
        return self._readout(qpos, qvel, sens)

    def read_into(self, out: torch.Tensor) -> None:
        """The state in the env's layout, written into ``out`` on the backend's device: joint
        positions and velocities, then the body sensors (positions, quaternions, linear and
        angular velocities), contact counts and foot force magnitudes. Shape: (num_envs,
        2J + 13B + C + F)."""
        self._refresh()
        J, k = self.nu, self._n_sens_copy
        out[:, :J] = self._qpos[:, 7:]
        out[:, J : 2 * J] = self._qvel[:, 6:]
        out[:, 2 * J : 2 * J + k] = self._sens[:, :k]
        force = self._sens[:, self._force].view(self.num_envs, -1, 3)
        torch.linalg.vector_norm(force, dim=-1, out=out[:, 2 * J + k :])

    # ------------------------------------------------------------------------ parameters

    def set_params(self, env_ids: np.ndarray, params: PhysicsParams) -> None:
        """Set the physics of the worlds ``env_ids`` (needs ``per_env_models``).

        The randomized fields (:data:`~humimic.sim.params.DR_FIELDS`) and the constants derived
        from them (subtree masses, inverse weights, actuator accelerations) are batched per
        world (``put_model``'s ``batch_sizes``). The constants of the envs being reset are
        computed in a few batched tensor operations on the device
        (:class:`~humimic.sim.setconst.InertiaConstants`, equal to ``mj_setConst``'s to float64
        round-off): ``mj_setConst`` per env on the host (its cost grows with the resets per
        step) and ``mujoco_warp.set_const`` (a kernel launch per dof and per body row) were both
        slower (BENCHMARKS.md).

        Raises:
            InputError: Without per-env models.
        """
        if self._constants is None:
            raise InputError(
                "set_params needs per-env models: build the backend with per_env_models=True"
            )
        ids = self._ids(env_ids)
        values = {
            f: torch.as_tensor(v).to(self.device, non_blocking=True)
            for f, v in self.layout.fields(params).items()
        }
        values.update(
            self._constants(
                values["body_mass"],
                values["body_inertia"],
                values["body_ipos"],
                values["dof_armature"],
            )
        )
        for f, v in values.items():
            self._fields[f][ids] = v.to(self._fields[f].dtype)

    def close(self) -> None:
        """Drop the captured graphs."""
        self._graphs.clear()


__all__ = ["MujocoWarpBackend", "capacity", "warp_available"]
