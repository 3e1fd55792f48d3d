"""Where the simulator disagrees with a log: k-step open-loop prediction error.

Windows start from logged states and are driven, open loop, by the logged commands (held
between command messages, as the drives do); the prediction is compared with the logged joint
positions over the window. Issue 4, step 1 (the before/after numbers of the report).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.real2sim.robotlog import RobotLog
from humimic.real2sim.simulate import PHYSICS_DT


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


def kstep_error(
    model: mujoco.MjModel,
    log: RobotLog,
    *,
    horizon: float = 0.5,
    stride: float | None = None,
    span: tuple[float, float] = (0.0, 1.0),
    gain_scale: np.ndarray | None = None,
) -> KStepError:
    """Open-loop k-step predictions of ``model`` against ``log``.

    Args:
        model: A fixed-base model whose joints are the log's joints, in order, one position
            actuator per joint (gains are set from the logged kp/kd).
        log: The log.
        horizon: Window length [s].
        stride: Time between window starts [s] (default: the horizon).
        span: The fraction of the log to use, e.g. (0.7, 1.0) for the held-out last 30%.
        gain_scale: Per actuator, the ratio of the applied to the commanded gains (a model of
            ``gain_mismatch``; default 1).
    """
    names = tuple(model.joint(j).name for j in range(model.njnt))
    if names != log.joint_names:
        raise InputError("the model's joints are not the log's joints (order matters)")
    if abs(model.opt.timestep - PHYSICS_DT) > 1e-12:
        raise InputError(
            f"predictions step at {PHYSICS_DT} s; the model steps at {model.opt.timestep}"
        )
    stride = horizon if stride is None else stride
    dt_state = float(np.median(np.diff(log.t)))
    samples = round(horizon / dt_state)
    sub = round(dt_state / PHYSICS_DT)
    first = int(np.searchsorted(log.t, log.t[0] + span[0] * log.duration))
    last = (
        int(np.searchsorted(log.t, log.t[0] + span[1] * log.duration, side="right")) - samples - 1
    )
    starts = np.arange(first, max(last, first), max(1, round(stride / dt_state)))
    if starts.size == 0:
        raise InputError(f"the log is shorter than one {horizon} s window in the span {span}")
    act_joint = model.actuator_trnid[:, 0]
    data = mujoco.MjData(model)
    residual = np.zeros((starts.size, samples, model.njnt))
    saved = model.actuator_gainprm.copy(), model.actuator_biasprm.copy()
    try:
        scale = np.ones(model.nu) if gain_scale is None else np.asarray(gain_scale)
        _predict(model, data, log, starts, samples, sub, act_joint, residual, scale)
    finally:  # The logged gains are set on the model while predicting; give it back as it was.
        model.actuator_gainprm[:], model.actuator_biasprm[:] = saved
    rmse_joint = np.sqrt(np.mean(residual**2, axis=(0, 1)))
    return KStepError(
        horizon_s=horizon,
        kstep_rmse_rad=float(np.sqrt(np.mean(residual**2))),
        per_joint=rmse_joint,
        residual=residual,
        starts=starts,
    )


def _predict(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    log: RobotLog,
    starts: np.ndarray,
    samples: int,
    sub: int,
    act_joint: np.ndarray,
    residual: np.ndarray,
    scale: np.ndarray,
) -> None:
    hist = [(a, int(model.actuator_history[a, 0])) for a in range(model.nu)]
    hist = [(a, n) for a, n in hist if n > 0]
    for w, s in enumerate(starts):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = log.q[s]
        data.qvel[:] = log.qd[s]
        t = log.t[s]
        data.time = t
        for a, n in hist:  # Drives with a control history remember the commands before t.
            times = t - PHYSICS_DT * np.arange(n - 1, -1, -1, dtype=np.float64)
            values = log.cmd_q[log.command_index(times), act_joint[a]]
            mujoco.mj_initCtrlHistory(
                model, data, a, times.reshape(n, 1), np.ascontiguousarray(values.reshape(n, 1))
            )
        # The command in force at each step, found once per window (times accumulate exactly
        # as the loop's clock would).
        steps = samples * sub
        clock = np.add.accumulate(np.concatenate([[t], np.full(steps - 1, PHYSICS_DT)]))
        in_force = log.command_index(clock)
        current = -1
        for k in range(steps):
            c = int(in_force[k])
            if c != current:
                current = c
                kp, kd = log.kp[c][act_joint] * scale, log.kd[c][act_joint] * scale
                model.actuator_gainprm[:, 0] = kp
                model.actuator_biasprm[:, 1] = -kp
                model.actuator_biasprm[:, 2] = -kd
                data.ctrl[:] = log.cmd_q[c][act_joint]
                data.qfrc_applied[:] = log.cmd_tau[c] + log.kd[c] * log.cmd_qd[c]
            mujoco.mj_step(model, data)
            if (k + 1) % sub == 0:
                i = (k + 1) // sub - 1
                residual[w, i] = data.qpos - log.q[s + i + 1]
