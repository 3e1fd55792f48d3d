"""The one place humimic steps CPU physics: batched rollouts, a plain replay, and stepping
one ``MjData`` in a closed loop.

:func:`batched` is the one call into ``mujoco.rollout`` (C++ threads, many models and start
states at once) that the CPU backend and the log predictions share; :func:`replay` is plain
``mj_step`` on one model, the reference a user's ``humimic replay`` reproduces;
:func:`step` and :func:`step_recorded` advance a live ``MjData`` for callers that compute each
control from the state they read (iLQR's feedback, the committed windows of dynamics
retargeting, real2sim's drive and balance controllers). Outside this package no module calls
``mj_step`` (``tests/test_architecture.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

FULL = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
"""The state a rollout starts from and returns: time, qpos, qvel, act, history, ..."""
CTRL = int(mujoco.mjtState.mjSTATE_CTRL)
"""Controls only (PD targets)."""


def batched(
    models: Sequence[mujoco.MjModel],
    datas: Sequence[mujoco.MjData],
    state: np.ndarray,
    control: np.ndarray,
    *,
    nstep: int,
    control_spec: int = CTRL,
    warmstart: np.ndarray | None = None,
    runner: mj_rollout.Rollout | None = None,
    state_out: np.ndarray | None = None,
    sensor_out: np.ndarray | None = None,
    skip_checks: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop rollouts of ``len(models)`` start states, one control row per physics step.

    Args:
        models: The model of each rollout (models of one structure).
        datas: One ``MjData`` per thread; their number is the number of threads.
        state: Start states (``mjSTATE_FULLPHYSICS``). Shape: (n, nstate).
        control: Controls per step, as ``control_spec`` lays them out. Shape: (n, nstep, nc).
        nstep: Physics steps.
        control_spec: What a control row holds (default: ``ctrl``).
        warmstart: The constraint solver's warm start at the start. Shape: (n, nv). With a
            bounded number of solver iterations it changes the result: the warm start of the
            ``MjData`` a state was read from makes a rollout reproduce ``mj_step`` exactly.
        runner: A persistent ``mujoco.rollout.Rollout`` (keeps its thread pool); default:
            ``mujoco.rollout.rollout``, which starts one per call.
        state_out, sensor_out: Output buffers, Shape: (n, nstep, nstate) and
            (n, nstep, nsensordata); allocated when not given.
        skip_checks: Skip MuJoCo's argument checks (the caller guarantees shapes and types).

    Returns:
        The state and the sensor data after every step.
    """
    kwargs: dict = {"control_spec": control_spec, "nstep": nstep, "skip_checks": skip_checks}
    if warmstart is not None:
        kwargs["initial_warmstart"] = np.ascontiguousarray(warmstart)
    if state_out is not None:
        kwargs["state"] = state_out
    if sensor_out is not None:
        kwargs["sensordata"] = sensor_out
    run = runner.rollout if runner is not None else mj_rollout.rollout
    out_state, out_sens = run(
        list(models), list(datas), np.ascontiguousarray(state), np.ascontiguousarray(control),
        **kwargs,
    )  # fmt: skip
    return np.asarray(out_state), np.asarray(out_sens)


def replay(
    model: mujoco.MjModel, state: np.ndarray, ctrl: np.ndarray, warm: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``mj_step`` from ``state`` (and solver warm start ``warm``, default zeros) under one
    control per step.

    Returns:
        The full physics state and the sensor data after each step (what a rollout returns).
        Shape: (S, nstate), (S, nsensordata).
    """
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, state, FULL)
    if warm is not None:
        data.qacc_warmstart[:] = warm
    states = np.zeros((ctrl.shape[0], state.size))
    sens = np.zeros((ctrl.shape[0], model.nsensordata))
    for s in range(ctrl.shape[0]):
        step(model, data, ctrl=ctrl[s])
        mujoco.mj_getState(model, data, states[s], FULL)
        sens[s] = data.sensordata
    return states, sens


def step(
    model: mujoco.MjModel, data: mujoco.MjData, nstep: int = 1, *, ctrl: np.ndarray | None = None
) -> None:
    """Advance ``data`` by ``nstep`` physics steps (``mj_step``) under ``ctrl`` (default: the
    controls it holds), in place."""
    if ctrl is not None:
        data.ctrl[:] = ctrl
    mujoco.mj_step(model, data, nstep)


def step_recorded(
    model: mujoco.MjModel, data: mujoco.MjData, ctrl: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Advance ``data`` one physics step per row of ``ctrl`` (shape (S, nu)), in place.

    Returns:
        ``qpos`` and ``qvel`` after each step. Shape: (S, nq), (S, nv).
    """
    qpos, qvel = np.zeros((len(ctrl), model.nq)), np.zeros((len(ctrl), model.nv))
    for s in range(len(ctrl)):
        step(model, data, ctrl=ctrl[s])
        qpos[s], qvel[s] = data.qpos, data.qvel
    return qpos, qvel
