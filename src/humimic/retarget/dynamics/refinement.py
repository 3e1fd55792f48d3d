"""``humimic refine``: the dynamics retargeter run on a motion, the refined motion and its
report."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from humimic.configs.retarget import DynamicsConfig
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.retarget.dynamics.inverse import reference_flight
from humimic.retarget.dynamics.replays import evaluate_replay, perturbed_models
from humimic.retarget.dynamics.sampler import DynamicsRetargeter
from humimic.sim.setup import key_body_setup


def refine(
    motion: Motion,
    cfg: DynamicsConfig | None = None,
    *,
    robustness: int = 8,
    progress: Callable[[int], Any] | None = None,
    nthread: int | None = None,
    backend: Literal["cpu", "warp"] = "cpu",
    device: str = "cpu",
) -> tuple[Motion, dict[str, Any]]:
    """``humimic refine``: the dynamically feasible version of ``motion`` and its report.

    The refined motion's frames are the optimized rollout's states at the reference's frame
    times (its kinematics recomputed from them); its ``dynamics`` section holds the initial
    state, the controls and the states of every physics step. The report compares the
    open-loop replay of the kinematic reference (its next frame's joints as PD targets) with
    that of the result (:func:`evaluate_replay`), and replays the result on ``robustness``
    perturbed models (``default`` domain-randomization ranges). ``backend`` and ``device``
    choose the simulator of the sampled rollouts (:class:`DynamicsRetargeter`); the replays
    are MuJoCo's on the CPU either way.
    """
    from humimic.motion import motion_from_qpos

    setup = replace(key_body_setup(motion.robot), backend=backend)
    dyn = DynamicsRetargeter(motion, cfg, setup=setup, nthread=nthread, device=device)
    res = dyn.run(progress=progress)
    kin = evaluate_replay(dyn, dyn.reference_controls(), res.initial_state)
    mine = evaluate_replay(dyn, res.ctrl, res.initial_state)
    perturbed = [
        evaluate_replay(dyn, res.ctrl, res.initial_state, m)
        for m in perturbed_models(dyn.model, dyn.backend, robustness, dyn.cfg.seed + 2)
    ]
    seconds = (motion.num_frames - 1) / motion.fps
    report: dict[str, Any] = {
        "robot": motion.robot,
        "frames": motion.num_frames,
        "motion_seconds": seconds,
        "reference_flight": reference_flight(motion, dyn.model),
        "reference_torque": _torque_report(dyn),
        "kinematic_replay": kin,
        "dynamics_replay": mine,
        "robustness": {
            "replays": robustness,
            "stayed_up": float(np.mean([1.0 - p["fell"] for p in perturbed]))
            if perturbed
            else None,
            "mpjpe_mm_mean": float(np.mean([p["mpjpe_mm"] for p in perturbed]))
            if perturbed
            else None,
        },
        "wall_seconds": res.seconds,
        "cpu_seconds": res.cpu_seconds,
        "cpu_seconds_per_motion_second": res.cpu_seconds / seconds,
        "physics_steps": res.rollouts,
        "samples": dyn.cfg.samples * (dyn.cfg.ensemble + 1),
        "mean_iterations_per_window": float(np.mean(res.iterations)),
        "window_cost": {
            "sampled": float(res.window_costs[:, 0].mean()),
            "committed": float(res.window_costs[:, 1].mean()),
        },
        "backend": backend,
        "device": device if backend == "warp" else "cpu",
        "threads": dyn.backend.nthread,
    }
    frames = res.frame_qpos()
    out = motion_from_qpos(
        dyn.model, frames, motion.fps, motion.robot, extras=motion.extras,
        info={**(motion.info or {}), "refined": {"config": dataclasses.asdict(dyn.cfg),
                                                  "report": report}},
    )  # fmt: skip
    if out.body_names != motion.body_names:
        raise InputError("the training model's bodies differ from the motion's")
    dynamics = {
        "initial_state": res.initial_state,
        "ctrl": res.ctrl,
        "qpos": res.qpos,
        "qvel": res.qvel,
        "physics_dt": np.array(res.physics_dt),
    }
    return replace(out, dynamics=dynamics), report


def _torque_report(dyn: DynamicsRetargeter) -> dict[str, Any] | None:
    """How far the reference's inverse-dynamics torques pass the motors' limits: the largest
    ratio |torque| / limit, its joint, and the frames where some joint's ratio exceeds 1."""
    tau = dyn.reference_torque
    if tau is None:
        return None
    ratio = np.abs(tau) / dyn.effort
    j = int(np.argmax(ratio.max(axis=0)))
    return {
        "max_over_limit": float(ratio[:, j].max()),
        "joint": dyn.backend.joint_names[j],
        "frames_over_limit": int((ratio > 1.0).any(axis=1).sum()),
    }


__all__ = [
    "refine",
]
