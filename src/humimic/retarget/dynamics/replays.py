"""Open-loop replay of PD targets on the training model, and its checks: against a refined
motion's stored states, against the reference, on perturbed models."""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np

from humimic.configs.retarget import DynamicsConfig
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.sim import randomization as dr_mod
from humimic.sim import rollout
from humimic.sim.backend import PhysicsBackend
from humimic.sim.params import physics_copies
from humimic.sim.randomization import dr_default
from humimic.sim.setup import build_model, key_body_setup

if TYPE_CHECKING:
    from humimic.retarget.dynamics.sampler import DynamicsRetargeter


def physics_steps_per_frame(fps: float, sim_dt: float) -> int | None:
    """The whole number of ``sim_dt`` physics steps in a frame at ``fps``, or None."""
    ratio = 1.0 / (fps * sim_dt)
    n = round(ratio)
    return n if n >= 1 and abs(ratio - n) <= 1e-6 else None


def replay(model: mujoco.MjModel, initial_state: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
    """Open-loop replay: ``mj_step`` from ``initial_state`` under one control per step.

    Returns:
        The full physics state after each step. Shape: (S, ``mj_stateSize``).
    """
    spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    if initial_state.shape != (mujoco.mj_stateSize(model, spec),):
        raise InputError(
            f"initial state has shape {initial_state.shape}, the model's is "
            f"({mujoco.mj_stateSize(model, spec)},)"
        )
    if ctrl.ndim != 2 or ctrl.shape[1] != model.nu:
        raise InputError(f"controls must be (steps, {model.nu}), got {ctrl.shape}")
    return rollout.replay(model, initial_state, ctrl)[0]


def check_replay(motion: Motion) -> dict[str, float]:
    """Replay a refined motion's stored controls from its stored initial state on the
    training model it was optimized on, and compare with its stored states.

    Raises:
        InputError: If the motion has no dynamic section, or one that does not fit the
            training model (physics step, state size, controls, steps); names the motion's
            file (``motion.source``).
    """
    where = motion.source or "the motion"
    dyn = motion.dynamics
    need = ("initial_state", "ctrl", "qpos", "qvel")
    if not dyn or any(k not in dyn for k in need):
        raise InputError(f"{where}: no dynamic section: make one with humimic refine")
    try:
        task = key_body_setup(motion.robot)
    except InputError as e:  # An unknown robot name.
        raise InputError(f"{where}: {e}") from None
    if "physics_dt" in dyn and abs(float(dyn["physics_dt"]) - task.sim_dt) > 1e-12:
        raise InputError(
            f"{where}: stored physics step {float(dyn['physics_dt'])} s, the training model's "
            f"is {task.sim_dt} s"
        )
    model = build_model(task)
    state, ctrl = np.asarray(dyn["initial_state"]), np.asarray(dyn["ctrl"])
    size = mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_FULLPHYSICS))
    if state.shape != (size,):
        raise InputError(
            f"{where}: dynamics_initial_state has shape {state.shape}, the training model of "
            f"{motion.robot} needs ({size},): refine the motion again"
        )
    if ctrl.ndim != 2 or ctrl.shape[0] < 1 or ctrl.shape[1] != model.nu:
        raise InputError(
            f"{where}: dynamics_ctrl has shape {ctrl.shape}, expected (steps, {model.nu}) for "
            f"the training model of {motion.robot}"
        )
    steps = ctrl.shape[0]
    for key, width in (("qpos", model.nq), ("qvel", model.nv)):
        if np.shape(dyn[key]) != (steps, width):
            raise InputError(
                f"{where}: dynamics_{key} has shape {np.shape(dyn[key])}, expected ({steps}, "
                f"{width}): one row per step of dynamics_ctrl"
            )
    states = replay(model, state, ctrl)
    nq, nv = model.nq, model.nv
    return {
        "steps": float(states.shape[0]),
        "max_qpos_error": float(np.abs(states[:, 1 : 1 + nq] - dyn["qpos"]).max()),
        "max_qvel_error": float(np.abs(states[:, 1 + nq : 1 + nq + nv] - dyn["qvel"]).max()),
    }


def evaluate_replay(
    dyn: DynamicsRetargeter,
    ctrl: np.ndarray,
    initial_state: np.ndarray,
    model: mujoco.MjModel | None = None,
) -> dict[str, float]:
    """Open-loop replay of ``ctrl`` from ``initial_state`` (on ``model``, default: the
    nominal training model), against the reference of ``dyn``.

    Returns:
        ``seconds_until_fall`` (the clip's length if it never falls: pelvis below
        ``fall_height`` of the reference's, or tilted ``fall_tilt`` from it),
        ``fell`` (0 or 1), ``mpjpe_mm`` (tracked bodies' world positions against the
        reference, mean over the frames before a fall), ``foot_skating_mm_per_s`` (mean
        horizontal speed of a foot body below 3 cm above its lowest height in the clip's
        reference, while the reference foot is that low too), ``effort`` (mean squared torque
        relative to the motors' limits).
    """
    model = dyn.model if model is None else model
    assert model is not None
    cfg, d = dyn.cfg, dyn.decimation
    states = replay(model, initial_state, ctrl)
    nq, nv = model.nq, model.nv
    qpos = np.concatenate([initial_state[None, 1 : 1 + nq], states[d - 1 :: d, 1 : 1 + nq]])
    T = qpos.shape[0]
    data = mujoco.MjData(model)
    bodies = [model.body(b).id for b in dyn.body_names]
    feet = [dyn.body_names.index(f) for f in dyn.foot_body_names]
    pos = np.zeros((T, len(bodies), 3))
    up = np.zeros(T)
    for t in range(T):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        pos[t] = data.xpos[bodies]
        up[t] = data.xmat[bodies[0]][8]
    ref = dyn.ref_body[:T]
    _, fallen = _tilt_and_fall(pos[:, 0, 2], ref[:, 0, 2], up, _up_z(dyn.ref_quat_root[:T]), cfg)
    first = int(np.argmax(fallen)) if fallen.any() else T
    live = slice(0, max(first, 1))
    err = np.linalg.norm(pos[live] - ref[live], axis=-1).mean()
    fps = 1.0 / dyn.step_dt
    skate = []
    for f in feet:
        low_ref = ref[:, f, 2] < ref[:, f, 2].min() + 0.03
        low = pos[:, f, 2] < pos[live, f, 2].min() + 0.03
        both = (low & low_ref)[1:first]
        v = np.linalg.norm(np.diff(pos[:first, f, :2], axis=0), axis=-1) * fps
        if both.any():
            skate.append(v[both].mean())
    q = states[:, 1 + 7 : 1 + nq]
    qd = states[:, 1 + nq + 6 : 1 + nq + nv]
    tau = np.clip(dyn.kp * (ctrl - q) - dyn.kd * qd, -dyn.effort, dyn.effort)
    return {
        "seconds_until_fall": first / fps if fallen.any() else (T - 1) / fps,
        "fell": float(fallen.any()),
        "mpjpe_mm": 1000.0 * float(err),
        "foot_skating_mm_per_s": 1000.0 * float(np.mean(skate)) if skate else 0.0,
        "effort": float(np.mean((tau[: first * d] / dyn.effort) ** 2)) if first else 0.0,
    }


def perturbed_models(
    model: mujoco.MjModel, backend: PhysicsBackend, count: int, seed: int
) -> list[mujoco.MjModel]:
    """``count`` copies of ``model`` with friction, masses, CoM, PD gains and armature drawn
    from the ``default`` domain-randomization ranges (robustness of a replay)."""
    rng = np.random.default_rng(seed)
    smp = dr_mod.sample(dr_default(), count, num_bodies=backend.num_bodies_total,
                        num_joints=backend.nu, rng=rng,
                        com_column=backend.layout.com_column)  # fmt: skip
    return physics_copies(model, backend.layout, smp.physics)


def _tilt_and_fall(
    root_z: np.ndarray,
    ref_root_z: np.ndarray,
    up: np.ndarray,
    up_ref: np.ndarray,
    cfg: DynamicsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The pelvis's tilt against the reference's (from the z components of their z axes;
    signed) and whether the robot has fallen: pelvis below ``fall_height`` of the reference's
    height, or tilted more than ``fall_tilt``. The one fall test of the optimizer and the
    replay report."""
    tilt = np.arccos(np.clip(up, -1.0, 1.0)) - np.arccos(np.clip(up_ref, -1.0, 1.0))
    return tilt, (root_z < cfg.fall_height * ref_root_z) | (np.abs(tilt) > cfg.fall_tilt)


def _up_z(q: np.ndarray) -> np.ndarray:
    """z component of the body z axis of wxyz quaternions: ``1 - 2 (x^2 + y^2)``."""
    return 1.0 - 2.0 * (q[..., 1] ** 2 + q[..., 2] ** 2)


__all__ = [
    "check_replay",
    "evaluate_replay",
    "perturbed_models",
    "physics_steps_per_frame",
    "replay",
]
