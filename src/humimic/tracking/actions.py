"""What a policy's action is added to: the action bases of the tracking task.

The PD target of every joint is ``base(frame) + scale * action`` (plus DR's joint offsets):

* ``default``: the robot's default pose, the same every frame (BeyondMimic's choice: the
  policy has to produce the whole motion);
* ``reference``: the reference's joint positions of the next frame (the kinematic open loop;
  the action is a residual around the motion);
* ``feedforward``: the PD targets ``humimic refine`` stored, which replay the clip open-loop
  on the nominal model (the action is a residual around a controller that already performs
  the motion on nominal physics);
* ``feedback``: those targets plus time-varying LQR feedback around the refined trajectory
  (:func:`humimic.sim.lqr.tvlqr_gains`), ``u_t + K_t (x - x_t)``: a model-based expert that
  reads the simulator's full state (base position and velocity included, which a real robot
  estimates), and the action is a residual around it.
"""

from __future__ import annotations

from typing import Any, get_args

import numpy as np

from humimic.configs.choices import ActionBaseName as ActionBase
from humimic.errors import InputError

ACTION_BASES: tuple[str, ...] = get_args(ActionBase)
STORED_BASES: tuple[str, ...] = ("feedforward", "feedback")
"""The action bases that need a refined motion (its stored controls and states)."""


def has_stored_controls(motion: Any) -> bool:
    """Whether a motion has the dynamic section of ``humimic refine`` (its stored controls)."""
    dyn = getattr(motion, "dynamics", None)
    return bool(dyn) and "ctrl" in dyn


def stored_targets(motion: Any, sim_dt: float, decimation: int) -> np.ndarray | None:
    """The PD targets of each control step of a refined motion's dynamic section (Shape:
    (frames - 1, J)), or None without one.

    Raises:
        InputError: The section is not at the physics step ``sim_dt`` or does not hold each
            target over a control step's ``decimation`` physics steps (as ``humimic refine``
            writes it at the policy rate).
    """
    if not has_stored_controls(motion):
        return None
    dyn = motion.dynamics
    ctrl, d = np.asarray(dyn["ctrl"]), decimation
    if (
        abs(float(dyn.get("physics_dt", 0.0)) - sim_dt) > 1e-12
        or ctrl.shape[0] != (motion.num_frames - 1) * d
        or not np.array_equal(ctrl[::d].repeat(d, axis=0), ctrl)
    ):
        raise InputError(
            f"{getattr(motion, 'source', '') or 'the motion'}: its dynamic section does not match the task "
            f"(physics step {sim_dt} s, {d} physics steps per frame, one target per frame): "
            "refine the motion again at the policy rate"
        )
    return ctrl[::d]


def stored_states(motion: Any, decimation: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The simulated state of a refined motion at each frame: ``qpos`` Shape: (T, nq) and
    ``qvel`` Shape: (T, nv), frame 0 from its initial state, frame ``f`` the state after
    physics step ``f * decimation``; None without a dynamic section. These velocities are
    the ones the stored controls continue from (the frames' finite differences are not)."""
    if not has_stored_controls(motion):
        return None
    dyn = motion.dynamics
    qpos, qvel = np.asarray(dyn["qpos"]), np.asarray(dyn["qvel"])
    nq, nv = qpos.shape[1], qvel.shape[1]
    start = np.asarray(dyn["initial_state"])
    q = np.concatenate([start[None, 1 : 1 + nq], qpos[decimation - 1 :: decimation]])
    v = np.concatenate([start[None, 1 + nq : 1 + nq + nv], qvel[decimation - 1 :: decimation]])
    return q, v


def base_table(
    base: str, motion: Any, joint_index: list[int], sim_dt: float, decimation: int
) -> np.ndarray | None:
    """The action base of every frame, in the env's joint order (Shape: (T, J); the last
    frame repeats the one before), or None for ``default`` (the default pose).

    Args:
        base: One of :data:`ACTION_BASES`.
        motion: The reference.
        joint_index: The env's joints as indices into the motion's joints (stored controls
            are in the training model's actuator order already).
        sim_dt: Physics step [s]. decimation: Physics steps per frame.

    Raises:
        InputError: ``feedforward`` or ``feedback`` on a motion without stored controls, or an
            unknown base.
    """
    if base == "default":
        return None
    if base == "reference":
        jp = np.asarray(motion.joint_pos)[:, joint_index]
        return np.concatenate([jp[1:], jp[-1:]])
    if base in STORED_BASES:
        ctrl = stored_targets(motion, sim_dt, decimation)
        if ctrl is None:
            raise InputError(
                f"{getattr(motion, 'source', '') or 'the motion'}: the action base {base!r} "
                "needs a refined motion (humimic refine) with its stored controls"
            )
        # Stored in the training model's actuator order, which is the env's joint order.
        return np.concatenate([ctrl, ctrl[-1:]])
    raise InputError(f"action base {base!r}: expected one of {', '.join(ACTION_BASES)}")


__all__ = [
    "ACTION_BASES",
    "STORED_BASES",
    "ActionBase",
    "base_table",
    "has_stored_controls",
    "stored_states",
    "stored_targets",
]
