"""The dynamics retargeter: receding-horizon sampling MPC over PD targets in MuJoCo, with an
iLQR polish of each window's best sample."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import mujoco
import numpy as np

from humimic.configs.retarget import DynamicsConfig
from humimic.errors import InputError, RetargetError
from humimic.motion import Motion
from humimic.retarget.contacts import step_speed
from humimic.retarget.dynamics.ilqr import ilqr
from humimic.retarget.dynamics.inverse import inverse_dynamics_torques
from humimic.retarget.dynamics.plans import DynamicsResult, knot_weights
from humimic.retarget.dynamics.replays import (
    _tilt_and_fall,
    _up_z,
    physics_steps_per_frame,
)
from humimic.sim import randomization as dr_mod
from humimic.sim import rollout
from humimic.sim.backend import PhysicsBackend
from humimic.sim.params import physics_copies
from humimic.sim.randomization import DomainRandomization, dr_default, dr_none
from humimic.sim.setup import SimSetup, build_backend, build_model, key_body_setup
from humimic.transforms import quat_to_matrix

_UPPER = ("waist", "shoulder", "elbow", "wrist")


@dataclass(frozen=True, kw_only=True)
class _WindowSearch:
    """What sampling found for one window (:meth:`DynamicsRetargeter._sample_window`).

    Attributes:
        offsets: The best sample's offsets from the nominal targets. Shape: (H, nu).
        controls: Its PD targets, within the control bounds. Shape: (H, nu).
        cost: Its cost.
        iterations: Sampling iterations run.
        rollouts: Physics steps simulated, all samples and members.
    """

    offsets: np.ndarray
    controls: np.ndarray
    cost: float
    iterations: int
    rollouts: int


class DynamicsRetargeter:
    """Receding-horizon sampling MPC that turns a kinematic reference into a dynamically
    feasible one: a reference the simulated robot can replay open-loop.

    A kinematic reference can be physically impossible: replay its joint positions as PD
    targets and the robot falls. Following SPIDER (Pan et al., "SPIDER: Scalable
    Physics-Informed Dexterous Retargeting", 2025) and DIAL-MPC (Xue et al., "Full-Order
    Sampling-Based MPC for Torque-Level Locomotion Control via Diffusion-Style Annealing",
    2024), retargeting becomes optimal control solved by sampling in the simulator:

    * nominal PD targets: with ``feedforward`` (the default), the targets whose PD torque is
      the reference's inverse-dynamics torque (:func:`inverse_dynamics_torques`: the base's
      share carried by the planted feet), so that the sampler starts from a plan that holds
      the robot up against gravity and accelerates it along the reference; without, the next
      frame's joint positions. Targets may lie beyond the joint range (the robot model's
      actuators do not clamp them, as on the real motor drivers): a low-gain servo needs that
      to reach its torque limit near the range's ends;
    * decision variables: offsets added to the nominal targets at knots ``knot_dt`` apart
      over a ``horizon_s`` window, linearly interpolated to the control rate (the reference's
      frame rate) and held over each control step's physics steps; after the first window,
      the first knot is the previous window's plan (continuity of the targets);
    * each iteration draws ``samples`` plans around the current mean (the mean itself is one
      of them) with noise that grows along the window and shrinks across iterations, rolls
      every one out in MuJoCo from the window's start state (``mujoco.rollout`` threads,
      through the tracking backend's :meth:`~humimic.sim.backend.MujocoCpuBackend.rollout`),
      scores it, and moves the mean to the MPPI average of the elites;
    * ``polish_iterations`` of iLQR (:mod:`humimic.retarget.dynamics.ilqr`) then refine the
      best sample, one control per control step, on the cost's Gauss-Newton model
      (:meth:`_stage`), each step accepted only if the exact cost falls: sampling finds the
      basin, the polish removes the noise that a few hundred samples leave in hundreds of
      knot values;
    * cost per control step: tracked-body positions, pelvis height and tilt, joint angles and
      pelvis velocity against the reference, effort, and a fall penalty; the last step counts
      twice;
    * receding horizon: the polished plan (without the polish: the best plan evaluated, not
      the unevaluated mean) is committed for ``commit_s``, stepped with ``mj_step`` on one
      ``MjData`` that runs through the motion, so the stored trajectory is exactly what an
      open-loop replay of the stored controls produces
      (:func:`~humimic.retarget.dynamics.replays.replay`); every window's rollouts start from
      its state and solver warm start;
    * robust option: every sample is also scored on ``ensemble`` perturbed models, and the
      mean or the worst cost counts.

    The physics is the training model (:func:`humimic.sim.setup.build_model`) the tracking
    policy will see: the same actuators, contacts and time step.

    Args:
        motion: The kinematic reference (its frame rate is the control rate; the physics
            step must divide the frame period).
        cfg: The sampler's settings.
        setup: What is simulated: the training model, the bodies scored (the root first) and
            the backend of the rollouts, ``cpu`` (``mujoco.rollout``) or ``warp`` (MuJoCo
            Warp on ``device``). Default: the robot's key bodies on the CPU
            (:func:`~humimic.sim.setup.key_body_setup`).
        nthread: Rollout threads of the CPU backend (default: all cores).
        device: Where the ``warp`` backend simulates (``cuda``; ``cpu`` for tests).

    Raises:
        InputError: If the settings or the motion do not fit.
    """

    def __init__(
        self,
        motion: Motion,
        cfg: DynamicsConfig | None = None,
        *,
        setup: SimSetup | None = None,
        nthread: int | None = None,
        device: str = "cpu",
    ) -> None:
        cfg = cfg or DynamicsConfig()
        task, decimation = _checked_setup(motion, cfg, setup)
        self.motion, self.cfg, self.decimation = motion, cfg, decimation
        self.step_dt = 1.0 / motion.fps
        self.physics_dt = task.sim_dt
        model = build_model(task)
        members = cfg.ensemble + 1
        n = cfg.samples * members
        dr = _ensemble_ranges(dr_default()) if cfg.ensemble else dr_none()
        if nthread is not None:
            task = replace(task, num_threads=nthread)
        self.backend: PhysicsBackend = build_backend(
            task, n, model=model, per_env_models=dr.randomizes_model, device=device
        )
        self.model = model
        # The models a plan's exact cost is simulated on in the iLQR polish: the nominal, then
        # the ensemble's (the sampler's draws).
        self.members = [model]
        if cfg.ensemble:
            self.members += self._perturb_ensemble(dr)
        self._take_reference(task)
        self.nominal = self._nominal_targets()

    def _perturb_ensemble(self, dr: DomainRandomization) -> list[mujoco.MjModel]:
        """Draw the ensemble's ``cfg.ensemble`` perturbed physics (seed ``cfg.seed + 1``) and
        give member ``e``'s to the backend's ``e + 1``-th block of ``cfg.samples`` envs (the
        first block keeps the nominal physics).

        Returns:
            The members' models, for the polish's exact cost.
        """
        cfg, be = self.cfg, self.backend
        rng = np.random.default_rng(cfg.seed + 1)
        smp = dr_mod.sample(dr, cfg.ensemble, num_bodies=be.num_bodies_total, num_joints=be.nu,
                            rng=rng, com_column=be.layout.com_column)  # fmt: skip
        for e in range(cfg.ensemble):
            ids = np.arange((e + 1) * cfg.samples, (e + 2) * cfg.samples)
            be.set_params(ids, smp.physics.select(np.full(len(ids), e)))
        return physics_copies(self.model, be.layout, smp.physics)

    def _take_reference(self, task: SimSetup) -> None:
        """Read what the cost compares against from the motion, in the backend's joint order
        and the setup's body order (the reference's joints, bodies, root and planted feet),
        and the robot's sizes, gains and control bounds.

        Raises:
            InputError: The motion lacks one of the backend's joints or the setup's bodies.
        """
        motion, cfg, model, be = self.motion, self.cfg, self.model, self.backend
        missing = [n for n in be.joint_names if n not in motion.joint_names] + [
            n for n in task.body_names if n not in motion.body_names
        ]
        if missing:
            raise InputError(f"the motion has no joint or body named {missing}")
        jidx = [motion.joint_names.index(j) for j in be.joint_names]
        bidx = [motion.body_names.index(b) for b in task.body_names]
        self.ref_joint = np.ascontiguousarray(motion.joint_pos[:, jidx])
        self.ref_joint_vel = motion.joint_vel[:, jidx]
        self.ref_body = np.ascontiguousarray(motion.body_pos_w[:, bidx])
        self.ref_quat_root = motion.body_quat_w[:, 0]
        self.ref_root_vel = motion.body_lin_vel_w[:, 0]
        self.root = 0  # task.body_names[0] is the pelvis (the floating base): _checked_setup.
        self.joint_lo, self.joint_hi = be.joint_range[:, 0], be.joint_range[:, 1]
        self.kp = be.kp
        self.kd = -model.actuator_biasprm[:, 2].copy()
        self.effort = np.where(be.effort_limit > 0, be.effort_limit, 1.0)
        self.joint_noise = np.array(
            [cfg.upper_body_noise if any(u in j for u in _UPPER) else 1.0 for j in be.joint_names]
        )
        self.nq, self.nv, self.nu = model.nq, model.nv, model.nu
        self.sl = be.sensor_slices
        self.nb = len(task.body_names)
        self.body_names = tuple(task.body_names)
        self.foot_body_names = tuple(b for b in be.foot_body_names if b in self.body_names)
        self.feet = [self.body_names.index(b) for b in self.foot_body_names]
        self.body_ids = [model.body(b).id for b in self.body_names]
        self.joint_qpos = np.array([model.joint(j).qposadr[0] for j in be.joint_names])
        self.joint_dofs = np.array([model.joint(j).dofadr[0] for j in be.joint_names])
        # The reference's feet on the ground: low (within 3 cm of their lowest) and slow.
        fz = self.ref_body[:, self.feet, 2]
        fv = step_speed(self.ref_body[:, self.feet, :2], motion.fps)
        self.ref_planted = (fz < fz.min(axis=0) + 0.03) & (fv < 0.3)  # (T, feet)
        # PD targets beyond a joint's range still command torque, up to the motor's limit at
        # the range's end (the model's actuators do not clamp their controls).
        reach = self.effort / self.kp
        self.ctrl_lo, self.ctrl_hi = self.joint_lo - reach, self.joint_hi + reach

    def _nominal_targets(self) -> np.ndarray:
        """The nominal targets of the control steps (row t: frame t to t + 1), around which
        the sampler searches: the next frame's joints, or with feedforward the targets whose
        PD torque at the step's middle is the reference's inverse-dynamics torque (kept as
        ``reference_torque``: None if the motion's qpos is another model's). Shape: (T - 1,
        nu).

        Raises:
            InputError: Feedforward for a motion whose qpos is another model's.
        """
        motion, cfg, model, be = self.motion, self.cfg, self.model, self.backend
        self.reference_torque: np.ndarray | None = None
        if motion.qpos.shape[1] == model.nq:
            self.reference_torque = inverse_dynamics_torques(
                model, motion.qpos, motion.fps, be.joint_names, be.foot_body_names
            )
        if cfg.feedforward == 0:
            nominal = self.ref_joint[1:]
        else:
            tau = self.reference_torque
            if tau is None:
                raise InputError(
                    f"the motion's qpos has {motion.qpos.shape[1]} values, the model {model.nq}"
                )
            ff = (tau + self.kd * self.ref_joint_vel) / self.kp  # kp (u - q) - kd qd = tau
            mid = 0.5 * (self.ref_joint[1:] + self.ref_joint[:-1])
            nominal = mid + cfg.feedforward * 0.5 * (ff[1:] + ff[:-1])
        return np.clip(nominal, self.ctrl_lo, self.ctrl_hi)

    # ------------------------------------------------------------------------------ costs

    def _costs(self, states: np.ndarray, sens: np.ndarray, ctrl: np.ndarray, f0: int) -> np.ndarray:
        """Cost of every rollout. ``states``/``sens`` after each physics step, Shape:
        (n, S, ·); ``ctrl`` (n, S, nu); frames ``f0 + 1 ...`` are the references of the
        control steps' ends. Returns Shape: (n,)."""
        cfg, d = self.cfg, self.decimation
        st, se, u = states[:, d - 1 :: d], sens[:, d - 1 :: d], ctrl[:, d - 1 :: d]
        n, H = st.shape[:2]
        frames = np.arange(f0 + 1, f0 + 1 + H)
        body = se[..., self.sl["pos"]].reshape(n, H, self.nb, 3)
        e_body = np.mean(np.sum((body - self.ref_body[frames]) ** 2, axis=-1), axis=-1)
        root = body[:, :, self.root]
        ref_root = self.ref_body[frames, self.root]
        e_height = (root[..., 2] - ref_root[:, 2]) ** 2
        quat = se[..., self.sl["quat"]].reshape(n, H, self.nb, 4)[:, :, self.root]
        tilt, fallen = _tilt_and_fall(
            root[..., 2], ref_root[:, 2], _up_z(quat), _up_z(self.ref_quat_root[frames]), cfg
        )
        q = st[..., 1 + 7 : 1 + self.nq]
        qd = st[..., 1 + self.nq + 6 : 1 + self.nq + self.nv]
        e_joint = np.mean((q - self.ref_joint[frames]) ** 2, axis=-1)
        lin = se[..., self.sl["lin"]].reshape(n, H, self.nb, 3)
        e_vel = np.sum((lin[:, :, self.root] - self.ref_root_vel[frames]) ** 2, axis=-1)
        tau = np.clip(self.kp * (u - q) - self.kd * qd, -self.effort, self.effort)
        e_tau = np.mean((tau / self.effort) ** 2, axis=-1)
        feet_v = lin[:, :, self.feet, :2]
        e_foot = np.sum(self.ref_planted[frames] * np.sum(feet_v**2, axis=-1), axis=-1)
        c = (
            cfg.body_weight * e_body / 0.01
            + cfg.foot_weight * e_foot / 0.09
            + cfg.root_weight * (e_height / 0.01 + tilt**2 / 0.09)
            + cfg.joint_weight * e_joint / 0.09
            + cfg.velocity_weight * e_vel
            + cfg.effort_weight * e_tau
        )
        c = c + cfg.fall_cost * np.maximum.accumulate(fallen, axis=1)
        c[:, -1] *= 2.0
        return c.sum(axis=1) / (H + 1)

    def _plan_cost(self, state: np.ndarray, warm: np.ndarray, u: np.ndarray, f0: int) -> float:
        """The cost of one plan (Shape: (H, nu), a control per control step) from ``state``
        and solver warm start ``warm`` at frame ``f0``, simulated with ``mj_step`` on every
        member model and combined as the sampler combines them."""
        ctrl = np.repeat(u, self.decimation, axis=0)
        costs = []
        for m in self.members:
            states, sens = rollout.replay(m, state, ctrl, warm)
            costs.append(self._costs(states[None], sens[None], ctrl[None], f0)[0])
        return float(np.mean(costs) if self.cfg.robust == "mean" else np.max(costs))

    def _stage(
        self, data: mujoco.MjData, frame: int, weight: float, u: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The Gauss-Newton model of :meth:`_costs`'s terms at one control step's end
        (``data`` there, reference ``frame``, the step's weight, its control ``u``) for the
        iLQR polish: residuals and their Jacobian in the tangent state (Shape: (m, 2 nv)),
        and the effort's gradient and Hessian in ``u``. Approximations, which the line
        search on the exact cost keeps from making a plan worse: the tilt and fall terms are
        left out; the body terms are read at the step's end, where :meth:`_costs` reads the
        sensors that ``mj_step`` computed before the step's last physics step (5 ms
        earlier; within 15% of the cost, ``test_polish_models_the_samplers_cost``); the feet's
        speed is linearized in the velocities only, and the effort in ``u`` only."""
        cfg, m, nv, nb = self.cfg, self.model, self.nv, self.nb
        mujoco.mj_kinematics(m, data)
        mujoco.mj_comPos(m, data)
        jp, jr = np.zeros((3, nv)), np.zeros((3, nv))
        res, jac = [], []

        def add(r: np.ndarray, jq: np.ndarray | None, jv: np.ndarray | None, scale: float) -> None:
            rows = r.shape[0]
            res.append(scale * r)
            jac.append(scale * np.hstack([np.zeros((rows, nv)) if jq is None else jq,
                                          np.zeros((rows, nv)) if jv is None else jv]))  # fmt: skip

        for i, b in enumerate(self.body_ids):
            mujoco.mj_jacBody(m, data, jp, jr, b)
            add(
                data.xpos[b] - self.ref_body[frame, i],
                jp,
                None,
                math.sqrt(cfg.body_weight / 0.01 / nb),
            )
            if i == self.root:
                z = data.xpos[b, 2:3] - self.ref_body[frame, i, 2:3]
                add(z, jp[2:3], None, math.sqrt(cfg.root_weight / 0.01))
                add(jp @ data.qvel - self.ref_root_vel[frame], None, jp.copy(),
                    math.sqrt(cfg.velocity_weight))  # fmt: skip
            elif i in self.feet and self.ref_planted[frame, self.feet.index(i)]:
                add(jp[:2] @ data.qvel, None, jp[:2].copy(), math.sqrt(cfg.foot_weight / 0.09))
        jq = np.zeros((self.nu, nv))
        jq[np.arange(self.nu), self.joint_dofs] = 1.0
        add(data.qpos[self.joint_qpos] - self.ref_joint[frame], jq, None,
            math.sqrt(cfg.joint_weight / 0.09 / self.nu))  # fmt: skip
        # Effort: mean squared torque relative to the limits, linear in u (state held).
        q, qd = data.qpos[self.joint_qpos], data.qvel[self.joint_dofs]
        tau = self.kp * (u - q) - self.kd * qd
        g = weight * cfg.effort_weight / self.nu * 2.0 * tau * self.kp / self.effort**2
        h = np.diag(weight * cfg.effort_weight / self.nu * 2.0 * (self.kp / self.effort) ** 2)
        r, J = np.concatenate(res), np.vstack(jac)
        return math.sqrt(weight) * r, math.sqrt(weight) * J, g, h

    # ------------------------------------------------------------------------------- solve

    def run(self, progress: Callable[[int], Any] | None = None) -> DynamicsResult:
        """Optimize the whole motion. ``progress(n)`` is called with the frames committed."""
        cfg, d = self.cfg, self.decimation
        T = self.motion.num_frames
        H_full = max(1, round(cfg.horizon_s / self.step_dt))
        C = max(1, round(cfg.commit_s / self.step_dt))
        rng = np.random.default_rng(cfg.seed)

        state = self._initial_state()
        initial = state.copy()
        # The committed motion is stepped with mj_step on one MjData, as replay() does, so
        # that the stored states are exactly what a replay gives; every window's rollouts
        # start from its state and its solver warm start.
        spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        live = mujoco.MjData(self.model)
        mujoco.mj_setState(self.model, live, initial, spec)
        ctrl_out, qpos_out, qvel_out = [], [], []
        f0 = 0
        plan_prev: np.ndarray | None = None  # offsets at the control steps of the last window
        iters, costs = [], []
        steps = 0
        t_wall, t_cpu = time.perf_counter(), time.process_time()
        while f0 < T - 1:
            H = min(H_full, T - 1 - f0)
            ref_u = self.nominal[f0 : f0 + H]  # (H, J): targets toward the next frames
            found = self._sample_window(state, live.qacc_warmstart, f0, ref_u, plan_prev, rng)
            steps += found.rollouts
            offs_b, u_b, committed = found.offsets, found.controls, found.cost
            if cfg.polish_iterations:
                u_b, committed = self._polish(state, live.qacc_warmstart.copy(), u_b, f0)
                offs_b = u_b - ref_u
            costs.append((found.cost, committed))
            c = min(C, H)
            u_b = np.repeat(u_b, d, axis=0)
            ctrl_out.append(u_b[: c * d])
            seg_q, seg_v = rollout.step_recorded(self.model, live, u_b[: c * d])
            qpos_out.append(seg_q)
            qvel_out.append(seg_v)
            mujoco.mj_getState(self.model, live, state, spec)
            plan_prev = offs_b[c:] if c < H else None
            iters.append(found.iterations)
            f0 += c
            if progress is not None:
                progress(c)
        return DynamicsResult(
            initial_state=initial,
            ctrl=np.concatenate(ctrl_out),
            qpos=np.concatenate(qpos_out),
            qvel=np.concatenate(qvel_out),
            physics_dt=self.physics_dt,
            decimation=d,
            seconds=time.perf_counter() - t_wall,
            cpu_seconds=time.process_time() - t_cpu,
            rollouts=steps,
            iterations=np.array(iters),
            window_costs=np.array(costs).reshape(-1, 2),
        )

    def _sample_window(
        self,
        state: np.ndarray,
        warmstart: np.ndarray,
        f0: int,
        ref_u: np.ndarray,
        plan_prev: np.ndarray | None,
        rng: np.random.Generator,
    ) -> _WindowSearch:
        """The sampling iterations of the window at frame ``f0``: ``cfg.samples`` plans per
        iteration around the mean (itself one of them), rolled out on every member from
        ``state`` and solver warm start ``warmstart``, until ``cfg.iterations`` or two
        iterations in a row that improve the best cost by less than ``cfg.min_improvement``.

        Args:
            state: The window's start (``mjSTATE_FULLPHYSICS``).
            warmstart: The solver's warm start there (``qacc_warmstart``). Shape: (nv,).
            f0: The window's first frame.
            ref_u: The nominal targets of the window's control steps. Shape: (H, nu).
            plan_prev: The last window's offsets beyond what it committed (the mean's warm
                start), or ``None`` for the first window. Shape: (H', nu).
            rng: The sampling noise.

        Raises:
            RetargetError: Every rollout diverged (NaN cost).
        """
        cfg, be, d = self.cfg, self.backend, self.decimation
        members, N = cfg.ensemble + 1, cfg.samples
        H = ref_u.shape[0]
        W = knot_weights(H, self.step_dt, cfg.knot_dt)  # (H, K)
        K = W.shape[1]
        mean = self._warm_mean(plan_prev, K)
        # The window's start state and solver warm start, for every rollout.
        start = np.ascontiguousarray(np.broadcast_to(state, (N * members, state.size)))
        warm = np.ascontiguousarray(np.broadcast_to(warmstart, (N * members, self.nv)))
        ramp = 1.0 + (cfg.horizon_noise - 1.0) * np.arange(K) / max(K - 1, 1)
        sigma0 = cfg.noise * ramp[:, None] * self.joint_noise[None]  # (K, J)
        if plan_prev is not None:
            sigma0[0] = 0.0  # The first knot continues the committed targets.
        best_c, best = np.inf, None
        stall, it, steps = 0, 0, 0
        for it in range(cfg.iterations):
            sigma = sigma0 * cfg.anneal**it
            knots = mean + rng.standard_normal((N, K, self.nu)) * sigma
            knots[0] = mean
            if it == 0 and plan_prev is not None:
                knots[1] = 0.0  # The nominal targets, as a candidate.
            offs = np.einsum("hk,nkj->nhj", W, knots)  # (N, H, J)
            u = np.clip(ref_u + offs, self.ctrl_lo, self.ctrl_hi)
            u_steps = np.repeat(u, d, axis=1)  # (N, H d, J)
            ctrl = np.tile(u_steps, (members, 1, 1))
            states, sens = be.rollout(start, ctrl, warm)
            steps += ctrl.shape[0] * ctrl.shape[1]
            cost_all = self._costs(states, sens, ctrl, f0).reshape(members, N)
            cost = cost_all.mean(0) if cfg.robust == "mean" else cost_all.max(0)
            k = int(np.argmin(cost))
            improved = best_c - cost[k]
            if cost[k] < best_c:
                best_c = float(cost[k])
                best = (offs[k].copy(), u[k].copy())
            mean = self._mppi_mean(cost, knots)
            if it > 0 and improved < cfg.min_improvement * abs(best_c):
                stall += 1
                if stall >= 2:
                    break
            else:
                stall = 0
        if best is None:  # Every cost was NaN: the simulation diverged in every rollout.
            raise RetargetError(
                f"dynamics: every sampled rollout of the window at frame {f0} diverged "
                "(NaN cost); lower --dyn.noise or --dyn.feedforward"
            )
        return _WindowSearch(
            offsets=best[0], controls=best[1], cost=best_c, iterations=it + 1, rollouts=steps
        )

    def _warm_mean(self, plan_prev: np.ndarray | None, K: int) -> np.ndarray:
        """The sampling mean a window starts from: zero offsets, or the last plan's remaining
        offsets (``plan_prev``, one per control step) at the window's ``K`` knots, zero
        beyond them. Shape: (K, nu)."""
        mean = np.zeros((K, self.nu))
        if plan_prev is not None:  # Warm start: the last plan's remaining offsets.
            tk = np.arange(K) * self.cfg.knot_dt / self.step_dt  # knot times in steps
            src = np.arange(plan_prev.shape[0])
            for j in range(self.nu):
                mean[:, j] = np.interp(tk, src, plan_prev[:, j], right=0.0)
        return mean

    def _mppi_mean(self, cost: np.ndarray, knots: np.ndarray) -> np.ndarray:
        """The next sampling mean: the MPPI average of the ``cfg.elites`` cheapest samples'
        knots (Shape: (N, K, nu)), weighted on their costs (Shape: (N,)) normalized by the
        elites' spread. Shape: (K, nu)."""
        order = np.argsort(cost)[: self.cfg.elites]
        ce = cost[order]
        z = (ce - ce[0]) / (ce.std() + 1e-12)
        w = np.exp(-z / self.cfg.temperature)
        return np.einsum("n,nkj->kj", w / w.sum(), knots[order])

    def _polish(
        self, state: np.ndarray, warm: np.ndarray, u: np.ndarray, f0: int
    ) -> tuple[np.ndarray, float]:
        """``cfg.polish_iterations`` of iLQR on a window's plan (Shape: (H, nu), a control
        per control step) from ``state``/``warm`` at frame ``f0``
        (:func:`humimic.retarget.dynamics.ilqr.ilqr`, on the nominal model's derivatives and the
        members' exact cost). Returns the polished plan and its cost."""
        H = u.shape[0]

        def stage(data: mujoco.MjData, t: int, ut: np.ndarray) -> Any:
            return self._stage(data, f0 + 1 + t, (2.0 if t == H - 1 else 1.0) / (H + 1), ut)

        out = ilqr(
            self.model, state, warm, u, decimation=self.decimation, stage=stage,
            cost=lambda plan: self._plan_cost(state, warm, plan, f0),
            lower=self.ctrl_lo, upper=self.ctrl_hi, iterations=self.cfg.polish_iterations,
        )  # fmt: skip
        return out.controls, out.cost

    def _initial_state(self) -> np.ndarray:
        """The reference's first frame, at rest relative to its motion (its velocities)."""
        m, be = self.motion, self.backend
        qvel = np.zeros(self.nv)
        qvel[:3] = m.body_lin_vel_w[0, 0]
        rot = quat_to_matrix(m.qpos[0, 3:7])
        qvel[3:6] = rot.T @ m.body_ang_vel_w[0, 0]
        qvel[6:] = self.ref_joint_vel[0]
        be.set_ctrl(np.tile(self.ref_joint[0], (be.num_envs, 1)))
        be.reset_to(np.array([0]), m.qpos[0][None], qvel[None])
        return be.env_state(0)

    def reference_controls(self) -> np.ndarray:
        """The kinematic reference as open-loop PD targets of every physics step (the next
        frame's joints over each frame). Shape: ((T - 1) decimation, nu)."""
        u = np.clip(self.ref_joint[1:], self.joint_lo, self.joint_hi)
        return np.repeat(u, self.decimation, axis=0)


def _checked_setup(
    motion: Motion, cfg: DynamicsConfig, setup: SimSetup | None
) -> tuple[SimSetup, int]:
    """The setup the retargeter simulates (``setup``, or the robot's key bodies on the CPU)
    and its physics steps per frame, after checking that the settings and the motion fit it.

    Raises:
        InputError: If the settings or the motion do not fit.
    """
    cfg.validate()
    task = setup or key_body_setup(motion.robot)
    if task.robot != motion.robot:
        raise InputError(f"the motion is for {motion.robot!r}, the setup for {task.robot!r}")
    if motion.num_frames < 3:
        raise InputError(f"the motion has {motion.num_frames} frames; at least 3 needed")
    decimation = physics_steps_per_frame(motion.fps, task.sim_dt)
    if decimation is None:
        raise InputError(
            f"the motion's {motion.fps} fps is not a whole number of {task.sim_dt} s "
            "physics steps per frame: resample it (e.g. humimic retarget --ik.fps 50)"
        )
    if task.body_names[0] != motion.body_names[0]:
        raise InputError(f"the setup's first body must be the base {motion.body_names[0]!r}")
    return task, decimation


def _ensemble_ranges(dr: DomainRandomization) -> DomainRandomization:
    """The ensemble's ranges: half-width around nominal for friction, masses and PD gains;
    the CoM offsets and armature as ``dr`` has them."""

    def half(r: tuple[float, float], nominal: float, log: bool) -> tuple[float, float]:
        if log:
            return (math.sqrt(r[0] * nominal), math.sqrt(r[1] * nominal))
        return (0.5 * (r[0] + nominal), 0.5 * (r[1] + nominal))

    return replace(
        dr,
        friction=half(dr.friction, 1.0, False),
        mass_scale=half(dr.mass_scale, 1.0, True),
        kp_scale=half(dr.kp_scale, 1.0, True),
        kd_scale=half(dr.kd_scale, 1.0, True),
    )


__all__ = [
    "DynamicsResult",
    "DynamicsRetargeter",
    "knot_weights",
]
