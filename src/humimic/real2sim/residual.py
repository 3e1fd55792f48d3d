"""Where the simulator disagrees with a log: k-step open-loop prediction error
(:class:`Predictor`, :func:`kstep_error`) of a :class:`~humimic.real2sim.correction.Correction`.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.correction import Correction
from humimic.real2sim.floating import BaseEstimate, estimate_base, free_joint
from humimic.real2sim.robotlog import RobotLog
from humimic.sim import rollout
from humimic.sim.joints import JointMap
from humimic.sim.models import MAX_STEP, PHYSICS_DT

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED
_MAX_BATCH_BYTES = 96 * 2**20
"""Rollout outputs are produced in chunks of at most this size."""
_EPS = 1e-7
"""Clock tolerance [s] when finding the command in force (step times are sums of floats)."""
SETTLE = 0.1
"""Windows start at least this long [s] after a gap in a log: the commands a drive acts on
(a delay of up to 50 ms is searched) must come from the same stretch of the log."""


@dataclass(frozen=True, kw_only=True)
class KStepError:
    """k-step prediction error of a model on a log.

    Attributes:
        horizon_s: Window length [s].
        kstep_rmse_rad: RMSE of joint positions over all windows, samples and joints [rad].
        per_joint: RMSE per joint [rad]. Shape: (J,).
        residual: Prediction minus log at every state sample of every window, by window.
            Shape: (W, S, J).
        starts: State index of each window's start. Shape: (W,).
    """

    horizon_s: float
    kstep_rmse_rad: float
    per_joint: np.ndarray
    residual: np.ndarray
    starts: np.ndarray

    def as_report(self, joint_names: tuple[str, ...]) -> dict:
        return {
            "kstep_rmse_rad": self.kstep_rmse_rad,
            "horizon_s": self.horizon_s,
            "per_joint": {n: float(e) for n, e in zip(joint_names, self.per_joint, strict=True)},
        }


class Predictor:
    """k-step open-loop predictions over the windows of one span of a log.

    Windows start from logged states and are driven, open loop, by the logged commands (held
    between command messages, as the drives do); the prediction is compared with the logged
    joint positions over the window. All windows of a span, and several candidate models at
    once, run as one threaded rollout call (:func:`humimic.sim.rollout.batched`): the diagnosis
    evaluates hundreds of candidate corrections per round this way.

    Args:
        model: Any compiled model with the log's joints (used for sizes and checks).
        log: The log. Its gains must be constant per joint (drives are rarely re-tuned inside
            an identification run; a log that does is refused rather than mispredicted).
        horizon: Window length [s].
        stride: Time between window starts [s] (default: the horizon).
        span: The fraction of the log to use, e.g. (0.7, 1.0) for the held-out last 30%.
        every, phase: Keep every ``every``-th window of the span, starting at ``phase``
            (interleaved subsets for cross-validation).
        nthread: Rollout threads (default: the CPU count).
        base_track: A floating base's :func:`~humimic.real2sim.floating.estimate_base` at
            every state sample of this log and model (another predictor's :attr:`track`),
            so that predictors of one log estimate it once (default: estimated here).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        log: RobotLog,
        *,
        horizon: float = 0.5,
        stride: float | None = None,
        span: tuple[float, float] = (0.0, 1.0),
        every: int = 1,
        phase: int = 0,
        nthread: int | None = None,
        base_track: BaseEstimate | None = None,
    ) -> None:
        fj = _checked_model(model, log, horizon, stride)
        self.dt = float(model.opt.timestep)
        """The physics step [s] the predictions take (the model's)."""
        if not PHYSICS_DT - 1e-12 <= self.dt <= MAX_STEP + 1e-12:
            raise InputError(
                f"predictions step at {PHYSICS_DT * 1e3:g} to {MAX_STEP * 1e3:g} ms; the "
                f"model steps at {self.dt * 1e3:g} ms"
            )
        _check_log(log)
        self.log = log
        self.horizon = horizon
        stride = horizon if stride is None else stride
        dt_state = float(np.median(np.diff(log.t)))
        self.sub = round(dt_state / self.dt)
        if self.sub < 1 or abs(self.sub * self.dt - dt_state) > 0.05 * dt_state:
            raise InputError(
                f"{log.where}: states every {dt_state * 1e3:.3g} ms: need a multiple of "
                f"{self.dt * 1e3:g} ms"
            )
        self.samples = round(horizon / dt_state)
        if self.samples < 1:
            raise InputError(
                f"--horizon {horizon}: shorter than the state interval of {log.where} "
                f"({dt_state * 1e3:.3g} ms)"
            )
        self.starts = _window_starts(log, horizon, self.samples, round(stride / dt_state), span,
                                     every, phase)  # fmt: skip
        steps = self.samples * self.sub
        # Time at the start of every physics step of every window, and of the step after the
        # window (its command is the one in force at the last sample).
        self.clock = log.t[self.starts][:, None] + self.dt * np.arange(steps + 1)[None, :]
        self._act_log = JointMap.of(model).act_log
        self.track: BaseEstimate | None = None
        """The floating base's state at every state sample (``None``: a fixed base)."""
        self.base: BaseEstimate | None = None
        """The floating base's state at each window's start (``None``: a fixed base)."""
        if fj is not None:
            self.track = base_track or estimate_base(model, log)
            if len(self.track.qpos) != log.t.size:
                raise ValueError("base_track: one state per state sample of the log expected")
            self.base = replace(self.track, qpos=self.track.qpos[self.starts],
                                qvel=self.track.qvel[self.starts])  # fmt: skip
        self.nthread = nthread or os.cpu_count() or 1
        self._datas: dict[tuple[int, ...], list[mujoco.MjData]] = {}
        self._index_cache: dict[float, np.ndarray] = {}

    def _threads(self, model: mujoco.MjModel) -> list[mujoco.MjData]:
        key = _structure(model)
        if key not in self._datas:
            self._datas[key] = [mujoco.MjData(model) for _ in range(self.nthread)]
        return self._datas[key]

    @property
    def num_windows(self) -> int:
        return int(self.starts.size)

    def _in_force(self, delay: float, times: np.ndarray) -> np.ndarray:
        """Index of the command the drive acts on at ``times`` given a transport delay."""
        key = round(delay, 9)
        if times is self.clock and key in self._index_cache:
            return self._index_cache[key]
        idx = self.log.command_index(times - delay + _EPS)
        if times is self.clock:
            self._index_cache[key] = idx
        return idx

    def controls(self, c: Correction) -> np.ndarray:
        """Rollout controls: ctrl (nu) then qfrc_applied (nv), per window and physics step."""
        log, W, K = self.log, self.num_windows, self.clock.shape[1]
        m, jm = c.model, JointMap.of(c.model)
        out = np.zeros((W, K, m.nu + m.nv))
        for d in np.unique(c.delay):
            acts = np.flatnonzero(c.delay == d)
            idx = self._in_force(float(d), self.clock)
            joints = jm.act_log[acts]
            out[:, :, acts] = log.cmd_q[idx][:, :, joints] - c.offset[joints]
            # Feed-forward torque and the velocity target's share of the PD law.
            ff = log.cmd_tau[idx][:, :, joints] + c.gain_scale[acts] * (
                log.kd[0][joints] * log.cmd_qd[idx][:, :, joints]
            )
            out[:, :, m.nu + jm.dadr[joints]] = ff
        return out

    def initial_states(self, c: Correction, ctrl: np.ndarray) -> np.ndarray:
        """Logged state at each window's start (the true one, under an encoder offset) and the
        drive filters' state after the commands before it."""
        log, m, jm = self.log, c.model, JointMap.of(c.model)
        s = np.zeros((self.num_windows, mujoco.mj_stateSize(m, _STATE)))
        lay = _state_layout(m)
        s[:, lay["time"].start] = log.t[self.starts]
        q = log.q[self.starts] - c.offset
        qpos, qvel = s[:, lay["qpos"]], s[:, lay["qvel"]]
        qpos[:, jm.qadr] = q
        qvel[:, jm.dadr] = log.qd[self.starts]
        if self.base is not None:
            fj = free_joint(m)
            assert fj is not None
            qa, da = int(m.jnt_qposadr[fj]), int(m.jnt_dofadr[fj])
            qpos[:, qa : qa + 7] = self.base.qpos
            qvel[:, da : da + 6] = self.base.qvel
        for j in np.flatnonzero(jm.play_q >= 0):
            # The play sits at the end the drive pushes against: the motor leads the link.
            a = int(np.flatnonzero(jm.act_log == j)[0])
            torque = self.kp[a] * c.gain_scale[a] * (ctrl[:, 0, a] - q[:, j])
            half = float(m.jnt_range[m.dof_jntid[jm.play_d[j]], 1])
            play = -np.sign(torque) * half
            qpos[:, jm.play_q[j]] = play
            qpos[:, jm.qadr[j]] = q[:, j] - play
        if m.na:
            act = ctrl[:, 0, : m.nu].copy()  # Settled on the current command...
            tau = m.actuator_dynprm[:, 0]
            for a in np.flatnonzero(tau > 0):  # ... unless it filters: run its filter.
                j = jm.act_log[a]
                n = min(int(np.ceil(16 * tau[a] / self.dt)), 4000)
                back = log.t[self.starts][:, None] - self.dt * np.arange(n, 0, -1)[None, :]
                u = log.cmd_q[self._in_force(float(c.delay[a]), back), j] - c.offset[j]
                alpha = 1.0 - np.exp(-self.dt / tau[a])
                x = u[:, 0].copy()
                for k in range(1, n):
                    x += alpha * (u[:, k] - x)
                act[:, a] = x
            for a in np.flatnonzero(m.actuator_actadr >= 0):
                s[:, lay["act"].start + m.actuator_actadr[a]] = act[:, a]
        return s

    def _set_gains(self, c: Correction) -> None:
        set_gains(c, self.kp, self.kd)

    @property
    def kp(self) -> np.ndarray:
        """Commanded kp of the joint each actuator drives (the log's, constant)."""
        return self.log.kp[0][self._act_log]

    @property
    def kd(self) -> np.ndarray:
        return self.log.kd[0][self._act_log]

    def run(self, corrections: list[Correction], effort: bool = False) -> np.ndarray:
        """Residual (prediction minus log) of each correction. Shape: (C, W, S, J), or with
        ``effort`` (C, W, S, J, 2): joint positions [rad] and drive torques [N m] (the log's
        effort against the modelled actuator force).

        The logged gains (times each correction's gain scale) are set on the models while
        predicting and put back afterwards.
        """
        W, S = self.num_windows, self.samples
        if effort and self.log.effort is None:
            raise InputError(
                f"{self.log.where}: the log has no effort (drive torque) to compare with"
            )
        J = self.log.q.shape[1]
        out = np.empty((len(corrections), W, S, J, 2) if effort else (len(corrections), W, S, J))
        # Models of one structure run together: a backlash joint adds a degree of freedom,
        # and where it sits decides the state's meaning and the data's sparse layout.
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, c in enumerate(corrections):
            groups.setdefault(_structure(c.model), []).append(i)
        for members in groups.values():
            self._run_group([corrections[i] for i in members], effort, out, members)
        return out

    def _run_group(
        self, corrections: list[Correction], effort: bool, out: np.ndarray, where: list[int]
    ) -> None:
        W, S, sub = self.num_windows, self.samples, self.sub
        K = S * sub
        m0 = corrections[0].model
        jm, lay = JointMap.of(m0), _state_layout(m0)
        nstate = mujoco.mj_stateSize(m0, _STATE)
        per = max(1, _MAX_BATCH_BYTES // (W * K * nstate * 8))
        for lo in range(0, len(corrections), per):
            chunk = corrections[lo : lo + per]
            models, states, ctrls = [], [], []
            saved = [(c.model.actuator_gainprm.copy(), c.model.actuator_biasprm.copy())
                     for c in chunk]  # fmt: skip
            try:
                for c in chunk:
                    self._set_gains(c)
                    ctrl = self.controls(c)
                    ctrls.append(ctrl)
                    states.append(self.initial_states(c, ctrl))
                    models += [c.model] * W
                result = rollout.batched(
                    models, self._threads(m0), np.concatenate(states),
                    np.concatenate(ctrls)[:, :K], control_spec=_CONTROL, nstep=K,
                )[0]  # fmt: skip
            finally:
                for c, (g, b) in zip(chunk, saved, strict=True):
                    c.model.actuator_gainprm[:], c.model.actuator_biasprm[:] = g, b
            at = result[:, sub - 1 :: sub].reshape(len(chunk), W, S, -1)
            link = jm.link(at[..., lay["qpos"]], jm.play_q, jm.qadr)
            samples = self.starts[:, None] + np.arange(1, S + 1)[None, :]
            offsets = np.stack([c.offset for c in chunk])[:, None, None, :]
            res_q = link + offsets - self.log.q[samples][None]
            rows = where[lo : lo + len(chunk)]
            if not effort:
                out[rows] = res_q
                continue
            assert self.log.effort is not None
            out[rows, ..., 0] = res_q
            for n, (c, ctrl) in enumerate(zip(chunk, ctrls, strict=True)):
                force = self._actuator_force(c, at[n], ctrl[:, sub::sub, : c.model.nu])
                out[rows[n], ..., 1] = force - self.log.effort[samples]

    def _actuator_force(self, c: Correction, state: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
        """Drive torque per joint at the state samples (W, S, J) from the states (W, S, n)
        and the commands the drives act on next (W, S, nu), as MuJoCo computes it."""
        m, lay, jm = c.model, _state_layout(c.model), JointMap.of(c.model)
        q = state[..., lay["qpos"]][..., jm.qadr]  # The motor side: what the drive acts on.
        qd = state[..., lay["qvel"]][..., jm.dadr]
        u = ctrl.copy()
        tau = m.actuator_dynprm[:, 0]
        for a in np.flatnonzero((tau > 0) & (m.actuator_actadr >= 0)):
            act = state[..., lay["act"].start + m.actuator_actadr[a]]
            u[..., a] = act + (u[..., a] - act) * (1.0 - np.exp(-self.dt / tau[a]))
        j = jm.act_log
        kp, kd = self.kp * c.gain_scale, self.kd * c.gain_scale
        f = kp * (u - q[..., j]) - kd * qd[..., j]
        lim = m.actuator_forcelimited.astype(bool)
        f[..., lim] = np.clip(
            f[..., lim], m.actuator_forcerange[lim, 0], m.actuator_forcerange[lim, 1]
        )
        out = np.zeros_like(q)
        out[..., j] = f
        return out

    def run_with_torque(
        self,
        c: Correction,
        torque: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
        history: int,
    ) -> np.ndarray:
        """Residual (W, S, J) of a correction plus an extra joint torque, closed loop.

        At every state sample, ``torque(errors, velocities, positions)`` maps the last
        ``history`` measured position errors (command in force minus measured position),
        velocities and positions, each (W, history, J) oldest first, to a torque (W, J) held
        until the next sample (a residual actuator model running at the state rate).
        """
        log, W, S, sub = self.log, self.num_windows, self.samples, self.sub
        m, jm = c.model, JointMap.of(c.model)
        saved = m.actuator_gainprm.copy(), m.actuator_biasprm.copy()
        try:
            self._set_gains(c)
            ctrl = self.controls(c)
            state = self.initial_states(c, ctrl)
            idx = np.maximum(self.starts[:, None] + np.arange(1 - history, 1)[None, :], 0)
            cmd = log.cmd_q[log.command_index(log.t[idx] + _EPS)]
            errs, vels, poss = cmd - log.q[idx], log.qd[idx].copy(), log.q[idx].copy()
            lay = _state_layout(m)
            out = np.empty((W, S, len(jm.names)))
            for i in range(S):
                chunk = ctrl[:, i * sub : (i + 1) * sub].copy()
                chunk[:, :, m.nu + jm.dadr] += torque(errs, vels, poss)[:, None, :]
                state = rollout.batched(
                    [m] * W, self._threads(m), state, chunk, control_spec=_CONTROL, nstep=sub
                )[0][:, -1]  # fmt: skip
                q = jm.link(state[:, lay["qpos"]], jm.play_q, jm.qadr) + c.offset
                k = self.starts + i + 1
                out[:, i] = q - log.q[k]
                now = log.cmd_q[log.command_index(log.t[k] + _EPS)]
                errs = np.concatenate([errs[:, 1:], (now - q)[:, None]], axis=1)
                qd = jm.link(state[:, lay["qvel"]], jm.play_d, jm.dadr)
                vels = np.concatenate([vels[:, 1:], qd[:, None]], axis=1)
                poss = np.concatenate([poss[:, 1:], q[:, None]], axis=1)
        finally:
            m.actuator_gainprm[:], m.actuator_biasprm[:] = saved
        return out

    def error(self, c: Correction) -> KStepError:
        return self.report(self.run([c])[0])

    def with_base(self, qpos: np.ndarray, qvel: np.ndarray) -> Predictor:
        """This predictor with the floating base at the windows' starts replaced (shape as
        :attr:`base`'s): what the predictions would be had the base been estimated so."""
        if self.base is None:
            raise ValueError("with_base: a fixed-base predictor has no base estimate")
        if qpos.shape != self.base.qpos.shape or qvel.shape != self.base.qvel.shape:
            raise ValueError("with_base: one base state per window expected")
        other = copy.copy(self)
        other.base = replace(self.base, qpos=qpos, qvel=qvel)
        return other

    def report(self, residual: np.ndarray) -> KStepError:
        """Summarize a residual (W, S, J) of this predictor's windows."""
        return KStepError(
            horizon_s=self.horizon,
            kstep_rmse_rad=float(np.sqrt(np.mean(residual**2))),
            per_joint=np.sqrt(np.mean(residual**2, axis=(0, 1))),
            residual=residual,
            starts=self.starts,
        )


def _checked_model(
    model: mujoco.MjModel, log: RobotLog, horizon: float, stride: float | None
) -> int | None:
    """The model's free joint (``None``: a fixed base), once the horizon, the stride and the
    model are checked against the log: its joints, in order, of hinges and slides (and a free
    base), its base the log's.

    Raises:
        InputError: What does not fit, naming the log.
    """
    where = log.where
    if not (np.isfinite(horizon) and horizon > 0):
        raise InputError(f"--horizon {horizon}: expected a positive number of seconds")
    if stride is not None and not (np.isfinite(stride) and stride > 0):
        raise InputError(f"stride {stride}: expected a positive number of seconds")
    if JointMap.of(model).names != log.joint_names:
        raise InputError(f"{where}: the model's joints are not the log's joints (order matters)")
    fj = free_joint(model)
    n_free = 0 if fj is None else 1
    if model.nv != model.njnt + 5 * n_free or model.nq != model.njnt + 6 * n_free:
        raise InputError("predictions need a model of hinge and slide joints (and a free base)")
    if fj is not None and log.base != "floating":
        raise InputError(f"{where}: a floating-base model needs a floating-base log "
                         f"(metadata robot.base is {log.base!r})")  # fmt: skip
    if fj is None and log.base != "fixed":
        raise InputError(f"{where}: a floating-base log (robot on the floor) needs a "
                         "floating-base model")  # fmt: skip
    return fj


def _check_log(log: RobotLog) -> None:
    """Refuse a log that changes its gains while it runs, or has fewer than two states.

    Raises:
        InputError: Naming the log (and the first joint whose gain changes).
    """
    for gains, what in ((log.kp, "kp"), (log.kd, "kd")):
        changed = np.flatnonzero(np.ptp(gains, axis=0) > 1e-9 * (1 + np.abs(gains).max()))
        if changed.size:
            raise InputError(
                f"{log.where}: the log changes {what} of {log.joint_names[changed[0]]!r} while "
                "it runs; the diagnosis needs constant gains per joint"
            )
    if log.t.size < 2:
        raise InputError(
            f"{log.where}: {log.t.size} message on /joint_states; predictions need at least 2"
        )


def _window_starts(
    log: RobotLog,
    horizon: float,
    samples: int,
    stride: int,
    span: tuple[float, float],
    every: int,
    phase: int,
) -> np.ndarray:
    """State index of each window's start: ``stride`` states apart (at least one) within the
    ``span`` of the log, none spanning a gap or starting within :data:`SETTLE` after one, then
    every ``every``-th from ``phase``.

    Raises:
        InputError: No window is left, saying how many the span holds and why.
    """
    first = int(np.searchsorted(log.t, log.t[0] + span[0] * log.duration))
    last = (
        int(np.searchsorted(log.t, log.t[0] + span[1] * log.duration, side="right")) - samples - 1
    )
    starts = np.arange(first, max(last, first), max(1, stride))
    # No window spans a gap in the log, or starts within SETTLE after one.
    whole = log.unbroken(starts, samples, SETTLE)
    broken = int(np.count_nonzero(~whole))
    starts = starts[whole]
    kept = starts[phase::every]
    if kept.size == 0:
        length = (span[1] - span[0]) * log.duration
        part = (
            f"the log ({log.duration:.3g} s)"
            if tuple(span) == (0.0, 1.0)
            else f"its {span[0]:.0%}-{span[1]:.0%} span ({length:.3g} s)"
        )
        spans = f" (and {broken} that span a gap in the log)" if broken else ""
        raise InputError(
            f"{log.where}: too short for --horizon {horizon:g} s windows: {part} holds "
            f"{starts.size} window{'' if starts.size == 1 else 's'}{spans}, "
            f"{phase + 1} needed"
        )
    return kept


def set_gains(c: Correction, kp: np.ndarray, kd: np.ndarray) -> None:
    """Set commanded PD gains (per actuator) on a correction's model, times its gain scale."""
    m = c.model
    kp, kd = kp * c.gain_scale, kd * c.gain_scale
    m.actuator_gainprm[:, 0] = kp
    m.actuator_biasprm[:, 0] = 0.0
    m.actuator_biasprm[:, 1] = -kp
    m.actuator_biasprm[:, 2] = -kd


def _structure(model: mujoco.MjModel) -> tuple[int, ...]:
    """What models must share to run in one batch on the same ``MjData``: their sizes and their
    kinematic tree (two models with a play joint in different places have the same sizes but
    a different state layout and sparse inertia)."""
    return (model.nq, model.nu, model.na, *model.dof_parentid, *model.jnt_qposadr)


def _state_layout(model: mujoco.MjModel) -> dict[str, slice]:
    """Where time, qpos, qvel and act sit in a full-physics state vector."""
    parts = [("time", mujoco.mjtState.mjSTATE_TIME), ("qpos", mujoco.mjtState.mjSTATE_QPOS),
             ("qvel", mujoco.mjtState.mjSTATE_QVEL), ("act", mujoco.mjtState.mjSTATE_ACT)]  # fmt: skip
    out, at = {}, 0
    for name, flag in parts:
        n = mujoco.mj_stateSize(model, flag)
        out[name] = slice(at, at + n)
        at += n
    return out


def kstep_error(
    model: mujoco.MjModel | Correction,
    log: RobotLog,
    *,
    horizon: float = 0.5,
    stride: float | None = None,
    span: tuple[float, float] = (0.0, 1.0),
) -> KStepError:
    """Open-loop k-step predictions of a model (or a :class:`Correction`) against ``log``.

    Args:
        model: A fixed-base model whose joints are the log's joints, in order, one position
            actuator per joint (gains are set from the logged kp/kd), or a correction.
        log: The log.
        horizon: Window length [s].
        stride: Time between window starts [s] (default: the horizon).
        span: The fraction of the log to use, e.g. (0.7, 1.0) for the held-out last 30%.
    """
    c = model if isinstance(model, Correction) else Correction.of(model)
    return Predictor(c.model, log, horizon=horizon, stride=stride, span=span).error(c)
