"""Sampling-based dynamics retargeting: knots, the stored replay, the CLI (real CMU walk)."""

from __future__ import annotations

from dataclasses import replace
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.configs import DynamicsConfig, RetargetConfig
from humimic.datasets import load_clip
from humimic.errors import InputError
from humimic.motion import Motion, load_motion, save_motion
from humimic.retarget import Retargeter
from humimic.retarget.dynamics import check_replay, knot_weights, refine

SMALL = DynamicsConfig(samples=24, iterations=3, horizon_s=0.3)


@cache
def _walk(root: Path) -> Motion:
    """0.8 s of the CMU walk, retargeted kinematically at 50 fps."""
    clip = load_clip(root / "cmu" / "35_01.bvh").slice(1, 97)
    return Retargeter("g1", "cmu", RetargetConfig(fps=50.0)).run(clip).motion


@cache
def _refined(root: Path) -> tuple[Motion, dict]:
    return refine(_walk(root), SMALL, robustness=2, nthread=1)


def test_knot_weights_interpolate_linearly() -> None:
    w = knot_weights(11, 0.02, 0.1)  # 0.2 s of 50 Hz steps, knots every 0.1 s: 3 knots
    assert w.shape == (11, 3)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w[[0, 5, 10]], np.eye(3), atol=1e-12)  # Exact at the knots.
    np.testing.assert_allclose(w[2], [0.6, 0.4, 0.0], atol=1e-12)
    values = np.array([1.0, -1.0, 3.0])
    np.testing.assert_allclose(w @ values, np.interp(np.arange(11) * 0.02, [0, 0.1, 0.2], values))


def test_refined_motion_replays_open_loop_and_tracks_closer(shared_data: Path) -> None:
    motion, report = _refined(shared_data)
    walk = _walk(shared_data)
    assert motion.num_frames == walk.num_frames and motion.dynamics is not None
    # The stored states are exactly what an open-loop replay of the stored controls gives.
    r = check_replay(motion)
    assert r["steps"] == (walk.num_frames - 1) * 4
    assert r["max_qpos_error"] <= 1e-12 and r["max_qvel_error"] <= 1e-12  # mj_step both ways
    # The frames are the rollout's states.
    np.testing.assert_allclose(motion.qpos[1:], motion.dynamics["qpos"][3::4], atol=1e-12)
    kin, dyn = report["kinematic_replay"], report["dynamics_replay"]
    assert not dyn["fell"]
    assert dyn["mpjpe_mm"] < kin["mpjpe_mm"], report  # Sampling beats the raw reference.
    assert report["robustness"]["replays"] == 2 and report["physics_steps"] > 0
    torque = report["reference_torque"]
    assert torque["max_over_limit"] > 0 and 0 <= torque["frames_over_limit"] <= walk.num_frames
    # The iLQR polish lowers the windows' costs below the best samples'.
    assert report["window_cost"]["committed"] < 0.9 * report["window_cost"]["sampled"], report


def test_motion_file_keeps_the_dynamic_section(shared_data: Path, tmp_path: Path) -> None:
    motion, _ = _refined(shared_data)
    back = load_motion(save_motion(motion, tmp_path / "r.npz"))
    assert back.dynamics is not None and motion.dynamics is not None
    for k, v in motion.dynamics.items():
        np.testing.assert_array_equal(back.dynamics[k], v)
    assert back.info is not None and "refined" in back.info
    assert check_replay(back)["max_qpos_error"] <= 1e-9


def test_replay_detects_changed_controls_and_missing_sections(
    shared_data: Path, tmp_path: Path
) -> None:
    motion, _ = _refined(shared_data)
    assert motion.dynamics is not None
    ctrl = motion.dynamics["ctrl"].copy()
    ctrl[len(ctrl) // 2] += 0.05
    bad = save_motion(replace(motion, dynamics={**motion.dynamics, "ctrl": ctrl}),
                      tmp_path / "bad.npz")  # fmt: skip
    assert main(["replay", str(bad)]) == 1
    plain = save_motion(_walk(shared_data), tmp_path / "plain.npz")
    assert main(["replay", str(plain)]) == 2
    with pytest.raises(InputError, match=r"dyn\.samples"):
        DynamicsConfig(samples=1).validate()
    with pytest.raises(InputError, match=r"dyn\.polish_iterations"):
        DynamicsConfig(polish_iterations=-1).validate()


def test_cli_refine_writes_motion_and_report(shared_data: Path, tmp_path: Path) -> None:
    src = save_motion(_walk(shared_data), tmp_path / "walk.npz")
    out, rep = tmp_path / "refined.npz", tmp_path / "refined.json"
    args = ["refine", str(src), "--out", str(out), "--report", str(rep), "--quiet",
            "--dyn.samples", "8", "--dyn.iterations", "1", "--dyn.polish_iterations", "1",
            "--robustness", "0"]  # fmt: skip
    assert main(args) == 0
    assert out.is_file() and rep.is_file()
    assert main(["replay", str(out)]) == 0
    # Bad input: exit code 2, nothing written.
    assert main(["refine", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.npz")]) == 2
    assert main(["refine", str(src), "--out", str(tmp_path / "y.npz"), "--dyn.samples", "1"]) == 2
    assert not (tmp_path / "x.npz").exists() and not (tmp_path / "y.npz").exists()


def test_mcap_round_trip_keeps_the_dynamic_section(shared_data: Path, tmp_path: Path) -> None:
    motion, _ = _refined(shared_data)
    src = save_motion(motion, tmp_path / "r.npz")
    assert main(["convert", str(src), str(tmp_path / "r.mcap")]) == 0
    assert main(["convert", str(tmp_path / "r.mcap"), str(tmp_path / "back.npz")]) == 0
    back = load_motion(tmp_path / "back.npz")
    assert back.dynamics is not None and motion.dynamics is not None
    for k, v in motion.dynamics.items():
        np.testing.assert_array_equal(back.dynamics[k], v)  # Lossless (float repr in JSON).
    assert main(["replay", str(tmp_path / "r.mcap")]) == 0


def test_cli_retarget_dynamics_checks_the_frame_rate_first(
    shared_data: Path, tmp_path: Path
) -> None:
    out = tmp_path / "w.npz"
    args = ["retarget", str(shared_data / "cmu" / "35_01.bvh"), "--out", str(out),
            "--method", "dynamics", "--ik.fps", "30", "--quiet"]  # fmt: skip
    assert main(args) == 2  # 30 fps is not a whole number of 5 ms physics steps.
    assert not out.exists()


def test_eval_open_loop_targets_of_a_refined_motion() -> None:
    """A refined motion's open loop in ``humimic eval`` is its stored PD targets, one per
    control step; a section that does not fit the task is refused, not reinterpreted."""
    from types import SimpleNamespace

    from humimic.tracking.actions import stored_targets
    from humimic.tracking.config import g1_tracking

    task = g1_tracking("none")
    d, frames = task.decimation, 5
    per_frame = np.arange(4 * 29, dtype=float).reshape(4, 29)
    dyn = {"ctrl": per_frame.repeat(d, axis=0), "physics_dt": np.float64(task.sim_dt)}
    refined = SimpleNamespace(dynamics=dyn, num_frames=frames)
    np.testing.assert_array_equal(stored_targets(refined, task.sim_dt, d), per_frame)
    assert stored_targets(SimpleNamespace(dynamics=None, num_frames=frames), task.sim_dt, d) is None
    varying = dict(dyn, ctrl=np.arange(16 * 29, dtype=float).reshape(16, 29))
    for bad in (dict(dyn, physics_dt=np.float64(0.002)), varying):
        with pytest.raises(InputError, match="refine the motion again"):
            stored_targets(SimpleNamespace(dynamics=bad, num_frames=frames), task.sim_dt, d)


@pytest.mark.parametrize("g", [9.81, 3.0])
def test_reference_flight_measures_how_ballistic_a_hop_is(g: float) -> None:
    """A hop of the home pose whose height follows a parabola of curvature ``g``: the flight
    frames (both feet 5 cm up) and the centre of mass's vertical acceleration there."""
    from humimic.motion import motion_from_qpos
    from humimic.retarget.dynamics import reference_flight
    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model

    model = tracking_model(g1_tracking("none"))
    fps, flight_s = 50.0, 0.4
    t = np.arange(60) / fps - 0.2  # 0.2 s standing, the hop, then standing again.
    tau = np.clip(t, 0.0, flight_s)
    lift = g * flight_s / 2 * tau - g / 2 * tau**2
    q = np.tile(model.key_qpos[0], (len(t), 1))
    q[:, 2] += lift
    report = reference_flight(motion_from_qpos(model, q, fps, "g1"), model)
    assert report["flight_frames"] == int((lift > 0.05).sum()) > 0
    assert report["com_z_acc_in_flight"] == pytest.approx(-g, rel=1e-6)
    assert report["gravity_z"] == pytest.approx(-9.81)
    # The closest free fall misses the hop by its curvature's excess over the flight frames:
    # (9.81 - g) / 2 t^2 less its best straight line.
    ts = t[lift > 0.05]
    bend = ts**2 - np.polyval(np.polyfit(ts, ts**2, 1), ts)
    gap = 1000 * (9.81 - g) / 2 * np.sqrt(np.mean(bend**2))
    assert report["ballistic_gap_mm"] == pytest.approx(gap, abs=1e-6)
    assert (report["ballistic_gap_mm"] > 5.0) == (g < 9.0)


def test_inverse_dynamics_targets_hold_a_crouch() -> None:
    """Standing still in a crouch (knees bent 0.8 rad, the feet flat on the floor), the
    inverse-dynamics torques (the weight carried by the two feet) added to the PD targets
    hold the pose; the pose alone as target sags under gravity. Simulated for 0.5 s on the
    training model, which the torques never see run."""
    import mujoco

    from humimic.retarget.dynamics import inverse_dynamics_torques
    from humimic.robots import get_robot
    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model

    model = tracking_model(g1_tracking("none"))
    joints = tuple(model.joint(model.actuator_trnid[i, 0]).name for i in range(model.nu))
    feet = tuple(get_robot("g1").feet.values())
    pose = model.key_qpos[0].copy()
    data = mujoco.MjData(model)
    data.qpos[:] = pose
    mujoco.mj_kinematics(model, data)
    foot_z = data.xpos[model.body(feet[0]).id, 2]
    for side in ("left", "right"):
        for joint, angle in (("hip_pitch", -0.4), ("knee", 0.8), ("ankle_pitch", -0.4)):
            pose[7 + joints.index(f"{side}_{joint}_joint")] = angle
    data.qpos[:] = pose
    mujoco.mj_kinematics(model, data)
    pose[2] -= data.xpos[model.body(feet[0]).id, 2] - foot_z  # Feet back on the floor.
    q = np.tile(pose, (5, 1))
    tau = inverse_dynamics_torques(model, q, 50.0, joints, feet)
    assert tau.shape == (5, model.nu)
    np.testing.assert_allclose(tau, tau[:1].repeat(5, axis=0), atol=1e-9)  # Static: constant.
    assert tau[0, joints.index("left_knee_joint")] < -10.0  # Extending: the knees carry it.

    def sag(ctrl: np.ndarray) -> float:
        data.qpos[:], data.qvel[:] = pose, 0.0
        data.ctrl[:] = ctrl
        for _ in range(100):
            mujoco.mj_step(model, data)
        return float(np.abs(data.qpos[7:] - pose[7:]).max())

    plain, held = sag(pose[7:]), sag(pose[7:] + tau[0] / model.actuator_gainprm[:, 0])
    assert plain > 0.05, plain
    assert held < 0.2 * plain, (held, plain)


def test_dynamics_targets_may_pass_the_joint_range() -> None:
    """The sampler's targets reach past a joint's range by effort / kp (the model does not
    clamp them), so that a low-gain servo can reach its torque limit at the range's ends."""
    from humimic.motion import motion_from_qpos
    from humimic.retarget.dynamics import DynamicsRetargeter
    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model

    model = tracking_model(g1_tracking("none"))
    motion = motion_from_qpos(model, np.tile(model.key_qpos[0], (4, 1)), 50.0, "g1")
    dyn = DynamicsRetargeter(motion, SMALL, nthread=1)
    reach = dyn.effort / dyn.kp
    np.testing.assert_allclose(dyn.ctrl_lo, dyn.joint_lo - reach)
    np.testing.assert_allclose(dyn.ctrl_hi, dyn.joint_hi + reach)
    assert not model.actuator_ctrllimited.any()


def test_polish_lowers_a_noisy_plans_cost_on_the_ensemble() -> None:
    """Standing still, a plan of noisy PD targets: the iLQR polish lowers its exact cost,
    which is the mean (or worst) over the nominal model and the ensemble's perturbed ones."""
    from humimic.motion import motion_from_qpos
    from humimic.retarget.dynamics import DynamicsRetargeter
    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model

    model = tracking_model(g1_tracking("none"))
    motion = motion_from_qpos(model, np.tile(model.key_qpos[0], (10, 1)), 50.0, "g1")
    cfg = replace(SMALL, ensemble=2, polish_iterations=2)
    dyn = DynamicsRetargeter(motion, cfg, nthread=1)
    assert len(dyn.members) == 3
    # The members are the sampler's perturbed models, CoM offsets included.
    for e, m in enumerate(dyn.members[1:]):
        sampled = dyn.backend.model_of((e + 1) * cfg.samples)  # type: ignore[union-attr]
        for field in ("body_mass", "body_ipos", "geom_friction", "actuator_gainprm"):
            np.testing.assert_array_equal(getattr(m, field), getattr(sampled, field))
        assert not np.allclose(m.body_ipos, model.body_ipos)
    state, warm = dyn._initial_state(), np.zeros(dyn.nv)
    rng = np.random.default_rng(0)
    noisy = dyn.nominal[:9] + 0.15 * rng.standard_normal((9, dyn.nu))
    before = dyn._plan_cost(state, warm, noisy, 0)
    polished, after = dyn._polish(state, warm, noisy, 0)
    assert after == pytest.approx(dyn._plan_cost(state, warm, polished, 0))
    assert after < 0.2 * before, (after, before)
    worst = DynamicsRetargeter(motion, replace(cfg, robust="worst"), nthread=1)
    assert worst._plan_cost(state, warm, noisy, 0) > before  # The worst member over the mean.


def test_polish_models_the_samplers_cost() -> None:
    """The Gauss-Newton model the polish builds (``_stage``: squared residuals at each
    control step's end plus the effort) is the sampler's cost, but for what it leaves out
    (tilt and falls: none here, with the pelvis terms off) and for reading the body sensors
    one physics step later than ``_costs`` does: within 15%, on a crouching plan."""
    import mujoco

    from humimic.motion import motion_from_qpos
    from humimic.retarget.dynamics import DynamicsRetargeter
    from humimic.sim.rollout import replay as _simulate
    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model

    model = tracking_model(g1_tracking("none"))
    motion = motion_from_qpos(model, np.tile(model.key_qpos[0], (12, 1)), 50.0, "g1")
    dyn = DynamicsRetargeter(motion, replace(SMALL, root_weight=0.0), nthread=1)
    state, H, d = dyn._initial_state(), 11, dyn.decimation
    plan = dyn.nominal[:H] + 0.3 * np.sin(np.arange(H))[:, None] * (dyn.joint_noise > 0.9)
    ctrl = np.repeat(plan, d, axis=0)
    states, sens = _simulate(dyn.model, state, ctrl)
    exact = dyn._costs(states[None], sens[None], ctrl[None], 0)[0]
    data = mujoco.MjData(dyn.model)
    spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    modelled = 0.0
    for t in range(H):
        mujoco.mj_setState(dyn.model, data, states[(t + 1) * d - 1], spec)
        weight = (2.0 if t == H - 1 else 1.0) / (H + 1)
        r, _, _, _ = dyn._stage(data, t + 1, weight, plan[t])
        q, qd = data.qpos[dyn.joint_qpos], data.qvel[dyn.joint_dofs]
        tau = dyn.kp * (plan[t] - q) - dyn.kd * qd
        modelled += r @ r + weight * dyn.cfg.effort_weight * np.mean((tau / dyn.effort) ** 2)
    assert exact > 0.01
    assert modelled == pytest.approx(exact, rel=0.15), (modelled, exact)


def test_feedforward_base_at_zero_residual_replays_the_stored_controls(shared_data: Path) -> None:
    """With the ``feedforward`` action base a zero action sends exactly the PD targets
    ``humimic refine`` stored, and an episode from the first frame (no noise, nominal
    physics) retraces the refined trajectory: the env resets to the stored simulated state."""
    import torch

    from humimic.tracking.config import AdaptiveSampling, ResetNoise, g1_tracking
    from humimic.tracking.env import TrackingEnv

    motion, _ = _refined(shared_data)
    assert motion.dynamics is not None
    task = replace(
        g1_tracking("none"), action_base="feedforward", start_frame=0,
        reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=((0.0, 0.0),) * 6,  # type: ignore[arg-type]
                         joint_pos=(0.0, 0.0)),
        adaptive=AdaptiveSampling(enabled=False), episode_length_s=10.0,
    )  # fmt: skip
    env = TrackingEnv(task, motion, 2)
    try:
        ctrl, d = motion.dynamics["ctrl"], task.decimation
        states = motion.dynamics["qpos"]
        worst = 0.0
        for f in range(motion.num_frames - 2):
            env.step(torch.zeros(2, env.num_actions))
            np.testing.assert_allclose(env.joint_targets[0].numpy(), ctrl[f * d], atol=1e-6)
            qpos = env.backend.read().qpos[0]
            worst = max(worst, float(np.abs(qpos - states[(f + 1) * d - 1]).max()))
        assert worst < 2e-3, worst  # float32 targets: the same trajectory, not bit for bit.
    finally:
        env.close()


def test_feedback_base_corrects_a_perturbed_start(shared_data: Path) -> None:
    """From a start pushed sideways and tilted (the reset's velocity offsets, fixed), the
    ``feedback`` base's LQR brings the posture back to the refined trajectory; the stored
    controls alone (``feedforward``) do not. Measured at the clip's end: the body positions
    relative to the root (the posture) and in the world."""
    import torch

    from humimic.tracking.config import AdaptiveSampling, ResetNoise, g1_tracking
    from humimic.tracking.env import TrackingEnv

    motion, _ = _refined(shared_data)
    kick = ((0.0, 0.0), (0.3, 0.3), (0.0, 0.0), (0.5, 0.5), (0.0, 0.0), (0.0, 0.0))
    posture, world = {}, {}
    for base in ("feedforward", "feedback"):
        task = replace(
            g1_tracking("none"), action_base=base, start_frame=0, episode_length_s=10.0,
            reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=kick, joint_pos=(0.0, 0.0)),  # type: ignore[arg-type]
            adaptive=AdaptiveSampling(enabled=False),
        )  # fmt: skip
        env = TrackingEnv(task, motion, 1)
        try:
            for _ in range(motion.num_frames - 2):
                _, _, done, _ = env.step(torch.zeros(1, env.num_actions))
                assert not bool(done[0]), base  # Neither falls within the clip.
            s = env.state
            err = s.body_pos_w - s.ref_body_pos_w
            world[base] = float(err.norm(dim=-1).mean())
            r = s.root_index
            posture[base] = float((err - err[:, r : r + 1]).norm(dim=-1).mean())
        finally:
            env.close()
    assert posture["feedback"] < 0.5 * posture["feedforward"], posture
    assert world["feedback"] < world["feedforward"], world


def test_delay_aware_feedback_base_issues_each_target_ahead_of_its_step(shared_data: Path) -> None:
    """On a robot whose commands act 2 policy steps late (DR's action delay fixed at 2), the
    ``feedback`` base designed for that delay (``feedback_delay=2``) issues the stored target
    of the step its command will act on, so the drives receive each step's stored target in
    time and the episode retraces the refined trajectory; designed for no delay it sends them
    late and ends farther from it."""
    import torch

    from humimic.sim.randomization import dr_none
    from humimic.tracking.config import AdaptiveSampling, ResetNoise, g1_tracking
    from humimic.tracking.env import TrackingEnv

    motion, _ = _refined(shared_data)
    assert motion.dynamics is not None
    ctrl, states = motion.dynamics["ctrl"], motion.dynamics["qpos"]
    world, worst_target = {}, {}
    for design in (0, 2):
        task = replace(
            g1_tracking(replace(dr_none(), action_delay=(2, 2))), action_base="feedback",
            feedback_delay=design, start_frame=0, episode_length_s=10.0,
            reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=((0.0, 0.0),) * 6,  # type: ignore[arg-type]
                             joint_pos=(0.0, 0.0)),
            adaptive=AdaptiveSampling(enabled=False),
        )  # fmt: skip
        env = TrackingEnv(task, motion, 1)
        try:
            d, worst = task.decimation, 0.0
            for f in range(motion.num_frames - 2):
                _, _, done, _ = env.step(torch.zeros(1, env.num_actions))
                assert not bool(done[0]), design
                applied = env.joint_targets[0].numpy()
                worst = max(worst, float(np.abs(applied - ctrl[f * d]).max()))
            worst_target[design] = worst
            qpos = env.backend.read().qpos[0]
            world[design] = float(
                np.abs(qpos[:3] - states[(motion.num_frames - 2) * d - 1][:3]).max()
            )
        finally:
            env.close()
    # In time: the stored target up to the LQR's small corrections of float32 round-off.
    assert worst_target[2] < 0.02, worst_target
    assert worst_target[0] > 5 * worst_target[2], worst_target  # Late by two steps.
    assert world[2] < 0.01 and world[2] < 0.5 * world[0], world


def test_feedforward_student_view_labels_replay_the_feedback_teacher(shared_data: Path) -> None:
    """DAgger into a student that acts around the stored targets alone (``feedforward``, no
    LQR, no simulator state) under a ``feedback`` teacher: a teacher (here a fixed linear map
    of its observations) in its own env, and the same teacher's labels (its action plus
    ``teacher_offset``) sent to the student's env (:class:`StudentView`), give the same
    trajectory, PD targets and teacher observations step by step, from a perturbed start
    where the LQR's correction is large. The teacher's action alone, without the offset,
    does not."""
    import torch

    from humimic.tracking.config import AdaptiveSampling, ResetNoise, g1_tracking
    from humimic.tracking.distill import StudentView
    from humimic.tracking.env import TrackingEnv

    motion, _ = _refined(shared_data)
    kick = ((0.0, 0.0), (0.3, 0.3), (0.0, 0.0), (0.5, 0.5), (0.0, 0.0), (0.0, 0.0))

    def task(base: str):
        return replace(
            g1_tracking("none"), action_base=base, start_frame=0, episode_length_s=10.0,
            reset=ResetNoise(pose=((0.0, 0.0),) * 6, velocity=kick, joint_pos=(0.0, 0.0)),  # type: ignore[arg-type]
            adaptive=AdaptiveSampling(enabled=False),
        )  # fmt: skip

    def teacher(policy: torch.Tensor) -> torch.Tensor:
        gen = torch.Generator().manual_seed(0)  # The same map every call.
        W = 0.02 * torch.randn(29, policy.shape[1], generator=gen)
        return policy @ W.T

    def run(with_offset: bool) -> tuple[float, float, float]:
        """Worst differences to the teacher's own episode: qpos, PD targets, observations."""
        student_env = TrackingEnv(task("feedforward"), motion, 1)
        view = StudentView(student_env, "feedback")
        env = TrackingEnv(task("feedback"), motion, 1)
        worst = [0.0, 0.0, 0.0]
        try:
            obs_t, obs_s = env.get_observations(), view.get_observations()
            for _ in range(motion.num_frames - 2):
                a = teacher(obs_t["policy"])
                label = teacher(obs_s["teacher_policy"])
                if with_offset:
                    label = label + obs_s["teacher_offset"]
                obs_t, _, done_t, _ = env.step(a)
                obs_s, _, done_s, _ = view.step(label)
                assert not bool(done_t[0]) and not bool(done_s[0])
                q_t, q_s = env.backend.read().qpos[0], student_env.backend.read().qpos[0]
                worst[0] = max(worst[0], float(np.abs(q_t - q_s).max()))
                worst[1] = max(
                    worst[1], float((env.joint_targets - student_env.joint_targets).abs().max())
                )
                for g in ("policy", "proprio_history"):
                    diff = (obs_t[g] - obs_s["teacher_" + g]).abs().max()
                    worst[2] = max(worst[2], float(diff))
            return worst[0], worst[1], worst[2]
        finally:
            env.close()
            view.close()

    # The correction matters here: the teacher's base is far from the student's.
    view = StudentView(TrackingEnv(task("feedforward"), motion, 1), "feedback")
    try:
        assert float(view.get_observations()["teacher_offset"].abs().max()) > 0.1
    finally:
        view.close()
    q, targets, obs = run(with_offset=True)
    assert q < 1e-5 and targets < 1e-5 and obs < 1e-4, (q, targets, obs)
    q, targets, _ = run(with_offset=False)
    assert targets > 0.05 and q > 1e-2, (q, targets)


def test_expert_teacher_reads_its_own_view_and_moves_to_the_students_base() -> None:
    """:class:`ExpertTeacher` is the trained actor, weight for weight: on an env's plain
    observations it acts as the actor; given ``teacher_policy`` it reads that instead of
    ``policy`` and adds ``teacher_offset``."""
    import torch
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    from humimic.tracking.distill import ExpertTeacher

    gen = torch.Generator().manual_seed(1)
    obs = TensorDict({"policy": torch.randn(4, 6, generator=gen)}, batch_size=[4])
    groups = {"teacher": ["policy"]}
    kw = {"hidden_dims": [8], "activation": "elu", "obs_normalization": False}
    actor = MLPModel(obs, groups, "teacher", 3, **kw)  # type: ignore[arg-type]
    expert = ExpertTeacher(obs, groups, "teacher", 3, **kw)  # type: ignore[arg-type]
    expert.load_state_dict(actor.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(expert(obs), actor(obs))
        other = torch.randn(4, 6, generator=gen)
        offset = torch.randn(4, 3, generator=gen)
        moved = obs.clone().update({"teacher_policy": other, "teacher_offset": offset})
        want = actor(TensorDict({"policy": other}, batch_size=[4])) + offset
        torch.testing.assert_close(expert(moved), want)


def test_distill_a_feedback_teacher_into_a_feedforward_student(
    shared_data: Path, tmp_path: Path
) -> None:
    """``humimic distill --student-base feedforward``: the student's run records the
    ``feedforward`` base (eval and export rebuild it without the LQR), its checkpoint holds
    the teacher's actor weight for weight, and it evaluates and exports like any run. A
    teacher whose LQR was designed for a latency is refused (exit 2, nothing written)."""
    import torch
    import yaml

    motion, _ = _refined(shared_data)
    path = tmp_path / "walk_dyn.npz"
    save_motion(motion, path)

    def train(out: Path, *extra: str) -> None:
        args = ["train", "--motion", str(path), "--out", str(out), "--num-envs", "8",
                "--max-iterations", "1", "--num-steps-per-env", "8", "--dr", "none", "--quiet",
                *extra]  # fmt: skip
        assert main(args) == 0

    teacher = tmp_path / "teacher"
    train(teacher)
    student = tmp_path / "student"
    args = ["distill", "--teacher", str(teacher), "--out", str(student), "--num-envs", "8",
            "--max-iterations", "2", "--student-base", "feedforward", "--quiet"]  # fmt: skip
    assert main(args) == 0
    cfg = yaml.safe_load((student / "config.yaml").read_text())
    assert cfg["settings"]["task"]["action_base"] == "feedforward"
    assert cfg["tracking"]["action_base"] == "feedforward"
    t_blob = torch.load(teacher / "checkpoints" / "model_000001.pt", weights_only=True)
    s_blob = torch.load(student / "checkpoints" / "model_000002.pt", weights_only=True)
    for k, v in t_blob["actor_state_dict"].items():
        torch.testing.assert_close(s_blob["teacher_state_dict"][k], v)
    assert main(["eval", str(student), "--episodes", "2", "--out", str(tmp_path / "e.json")]) == 0
    assert main(["export", str(student), "--out", str(tmp_path / "s.onnx")]) == 0
    delayed = tmp_path / "delayed"
    train(delayed, "--task.feedback-delay", "1")
    refused = tmp_path / "refused"
    bad = ["distill", "--teacher", str(delayed), "--out", str(refused), "--num-envs", "8",
           "--student-base", "feedforward", "--quiet"]  # fmt: skip
    assert main(bad) == 2
    assert not refused.exists()
