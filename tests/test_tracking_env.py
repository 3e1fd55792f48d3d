"""Tests of the motion-tracking environment (humimic.tracking). Fast: tiny env counts."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from rsl_rl.env import VecEnv
from rsl_rl.runners import OnPolicyRunner

from humimic import transforms as tf
from humimic.errors import HumimicError, InputError
from humimic.motion import Motion, motion_from_qpos
from humimic.sim import randomization as dr_mod
from humimic.sim.backend import MujocoCpuBackend
from humimic.sim.randomization import dr_default, load_dr_profile
from humimic.tracking import rewards as rew
from humimic.tracking import terminations as term
from humimic.tracking.config import (
    TRACKING_TASKS,
    AdaptiveSampling,
    default_rewards,
    g1_tracking,
    tracking_task,
)
from humimic.tracking.env import TrackingEnv, tracking_backend, tracking_model
from humimic.tracking.math import quat_from_euler_xyz
from humimic.tracking.rsl import PpoConfig, train_cfg
from humimic.tracking.state import TrackingState


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return tracking_model(g1_tracking("none"))


@pytest.fixture(scope="module")
def motion(model: mujoco.MjModel) -> Motion:
    """The G1 standing in its home pose, arms swinging gently: 1.5 s at 50 fps."""
    fps, T = 50.0, 75
    q = np.tile(model.key_qpos[0], (T, 1))
    t = np.arange(T) / fps
    for name in ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint"):
        adr = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]
        q[:, adr] += 0.3 * np.sin(2 * np.pi * t)
    return motion_from_qpos(model, q, fps, "g1")


def make_env(
    model: mujoco.MjModel, motion: Motion, n: int = 4, dr: str = "default", **kw
) -> TrackingEnv:
    cfg = replace(g1_tracking(dr), **{"action_base": "default", **kw})  # A kinematic clip.
    return TrackingEnv(cfg, motion, n, model=model)


# ------------------------------------------------------------------------- VecEnv contract


@pytest.mark.parametrize("robot", sorted(TRACKING_TASKS))
def test_every_registered_task_steps_without_nan(robot: str) -> None:
    """Each registered task builds its model and env, resets, and takes steps under DR with
    strong random actions: every observation group and reward stays finite."""
    cfg = replace(tracking_task(robot, "default"), action_base="default")
    task_model = tracking_model(cfg)
    T = 50
    home = task_model.key_qpos[0] if task_model.nkey else task_model.qpos0  # OP3: no keys.
    q = np.tile(home, (T, 1))
    q[:, 7:] += 0.2 * np.sin(2 * np.pi * np.arange(T)[:, None] / T)
    env = TrackingEnv(cfg, motion_from_qpos(task_model, q, 50.0, robot), 4, model=task_model)
    try:
        gen = torch.Generator().manual_seed(0)
        for _ in range(3):
            obs, rewards, _, extras = env.step(torch.randn(4, env.num_actions, generator=gen))
            for group in ("policy", "critic", "proprio_history", "physics"):
                assert torch.isfinite(obs[group]).all(), group
            assert torch.isfinite(rewards).all()
            assert all(torch.isfinite(v).all() for v in extras["log"].values())
    finally:
        env.close()


def test_vec_env_contract(model: mujoco.MjModel, motion: Motion) -> None:
    env = make_env(model, motion, n=4, episode_length_s=0.2)  # 10 policy steps
    assert isinstance(env, VecEnv)
    assert env.num_actions == 29 and isinstance(env.max_episode_length, int)
    assert env.episode_length_buf.dtype == torch.long
    obs = env.get_observations()
    assert set(obs.keys()) == {"policy", "critic", "proprio_history", "physics", "base_lin_vel"}
    for v in obs.values():
        assert v.dtype == torch.float32 and v.ndim == 2 and v.shape[0] == 4
    assert obs["proprio_history"].shape[1] == 5 * obs["policy"].shape[1]
    torch.testing.assert_close(obs["physics"], env.physics_params)
    gen = torch.Generator().manual_seed(0)
    saw_done = False
    with torch.inference_mode():
        for _ in range(12):
            obs, rewards, dones, extras = env.step(0.3 * torch.randn(4, 29, generator=gen))
            assert rewards.shape == (4,) and rewards.dtype == torch.float32
            assert dones.shape == (4,) and dones.dtype == torch.bool
            time_outs = extras["time_outs"]
            assert time_outs.dtype == torch.bool and not bool((time_outs & ~dones).any())
            for key, value in extras["log"].items():
                assert "/" not in key and value.ndim == 0
            for key in ("policy", "critic", "proprio_history"):
                v = obs[key]
                assert v.dtype == torch.float32 and torch.isfinite(v).all()
            if dones.any():
                saw_done = True
                # Done envs were reset: a fresh episode, history filled with the new observation.
                assert (env.episode_length_buf[dones] == 0).all()
                hist = obs["proprio_history"][dones].view(-1, 5, obs["policy"].shape[1])
                assert torch.equal(hist[:, 0], hist[:, -1])
    assert saw_done


def test_episode_length_buf_replaced_by_runner(model: mujoco.MjModel, motion: Motion) -> None:
    env = make_env(model, motion, n=2, dr="none", episode_length_s=1.0)
    # What OnPolicyRunner.learn(init_at_random_ep_len=True) does: the attribute is replaced.
    env.episode_length_buf = torch.tensor([env.max_episode_length - 1, 0])
    env.state.frame.zero_()
    with torch.inference_mode():
        _, _, dones, extras = env.step(torch.zeros(2, 29))
    assert bool(extras["time_outs"][0]) and bool(dones[0])
    assert int(env.episode_length_buf[0]) == 0 and int(env.episode_length_buf[1]) == 1


def test_displaced_anchor_terminates(model: mujoco.MjModel, motion: Motion) -> None:
    env = make_env(model, motion, n=2, dr="none")
    r = env.backend.read()
    qpos, qvel = r.qpos.copy(), r.qvel.copy()
    qpos[0, 2] += 0.6  # Lift env 0 well above its reference.
    env.backend.reset_to(np.arange(2), qpos, qvel)
    with torch.inference_mode():
        _, _, dones, extras = env.step(torch.zeros(2, 29))
    assert bool(dones[0]) and not bool(extras["time_outs"][0])
    assert float(extras["log"]["term_anchor_height"]) == 0.5
    assert not bool(dones[1])


# ----------------------------------------------------------------- rewards on a fake state


@dataclass
class FakeEnv:
    """The least an MDP term reads: a state and the episode counters."""

    state: TrackingState
    episode_length_buf: torch.Tensor
    max_episode_length: int = 100


def fake_env(n: int = 3) -> FakeEnv:
    state = TrackingState.zeros(
        num_envs=n,
        body_names=("pelvis", "torso", "hand"),
        anchor_body="torso",
        root_body="pelvis",
        num_joints=2,
        num_contact_bodies=2,
        num_feet=2,
        num_frames=10,
    )
    pos = torch.tensor([[0.0, 0.0, 0.8], [0.0, 0.0, 1.1], [0.3, 0.2, 1.0]])
    state.body_pos_w[:] = pos
    state.ref_body_pos_w[:] = pos
    state.update_relative()
    return FakeEnv(state=state, episode_length_buf=torch.zeros(n, dtype=torch.long))


def test_perfect_tracking_gives_weight_sum() -> None:
    env = fake_env()
    terms = default_rewards()
    total = sum(tc.weight * tc.func(env, **tc.params) for tc in terms.values())
    expected = sum(tc.weight for tc in terms.values() if tc.weight > 0)
    assert torch.allclose(torch.as_tensor(total), torch.full((3,), expected))


def test_known_errors_give_exp() -> None:
    env = fake_env()
    s = env.state
    s.body_pos_w[:, 1, 2] += 0.2  # Anchor 0.2 m too high (all envs).
    got = rew.anchor_pos_error_exp(env, std=0.3)
    assert torch.allclose(got, torch.full((3,), math.exp(-0.04 / 0.09)))
    # Rotate the hand by 0.5 rad about z: mean squared angle over the 3 bodies is 0.25 / 3.
    s.body_quat_w[:, 2] = quat_from_euler_xyz(
        torch.tensor(0.0), torch.tensor(0.0), torch.tensor(0.5)
    )
    s.update_relative()
    got = rew.body_ori_error_exp(env, std=0.4)
    assert torch.allclose(got, torch.full((3,), math.exp(-(0.25 / 3) / 0.16)), atol=1e-6)
    got = rew.body_ori_error_exp(env, std=0.4, body_names=("hand",))
    assert torch.allclose(got, torch.full((3,), math.exp(-0.25 / 0.16)), atol=1e-6)
    s.body_lin_vel_w[:, 0, 0] = 1.0  # One of three bodies 1 m/s off.
    got = rew.body_lin_vel_error_exp(env, std=1.0)
    assert torch.allclose(got, torch.full((3,), math.exp(-1.0 / 3)))
    s.action[:] = torch.tensor([0.3, -0.4])
    assert torch.allclose(rew.action_rate_l2(env), torch.full((3,), 0.25))
    s.soft_joint_limits[:] = torch.tensor([[-1.0, 1.0], [-1.0, 1.0]])
    s.joint_pos[:] = torch.tensor([1.5, -1.2])
    assert torch.allclose(rew.joint_pos_limits(env), torch.full((3,), 0.7))
    s.contact_found[1] = torch.tensor([2.0, 1.0])
    assert rew.undesired_contacts(env).tolist() == [0.0, 2.0, 0.0]


def test_body_position_reward_ignores_heading_and_horizontal_offset() -> None:
    env = fake_env()
    s = env.state
    # The robot stands 1 m to the side, turned 90 degrees: relative tracking is still perfect.
    yaw = quat_from_euler_xyz(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(math.pi / 2))
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    anchor = s.ref_body_pos_w[0, 1]
    s.body_pos_w[:] = (s.ref_body_pos_w - anchor) @ rot.T + anchor + torch.tensor([1.0, 0.0, 0.0])
    s.body_quat_w[:] = yaw
    s.update_relative()
    assert torch.allclose(rew.body_pos_error_exp(env, std=0.3), torch.ones(3), atol=1e-6)
    assert torch.allclose(rew.body_ori_error_exp(env, std=0.4), torch.ones(3), atol=1e-6)
    assert (rew.anchor_pos_error_exp(env, std=0.3) < 1e-4).all()


def test_terminations_on_fake_state() -> None:
    env = fake_env()
    s = env.state
    assert not term.anchor_height_error(env, threshold=0.25).any()
    s.body_pos_w[0, 1, 2] += 0.3
    s.body_pos_w[1, 1, 2] += 0.1
    assert term.anchor_height_error(env, threshold=0.25).tolist() == [True, False, False]
    s.body_quat_w[2, 1] = quat_from_euler_xyz(
        torch.tensor(1.5), torch.tensor(0.0), torch.tensor(0.0)
    )
    assert term.anchor_ori_error(env, threshold=0.8).tolist() == [False, False, True]
    s.update_relative()
    s.body_pos_w[1, 2, 2] -= 0.4
    assert term.ee_height_error(env, threshold=0.25, body_names=("hand",)).tolist() == [
        False,
        True,
        False,
    ]
    env.episode_length_buf[:] = torch.tensor([100, 5, 5])
    s.frame[:] = torch.tensor([0, 9, 3])
    assert term.time_out(env).tolist() == [True, True, False]


# ---------------------------------------------------------------- domain randomization


def test_dr_none_is_nominal_and_noise_free(model: mujoco.MjModel, motion: Motion) -> None:
    env = make_env(model, motion, n=3, dr="none")
    assert torch.equal(env.physics_params, torch.zeros_like(env.physics_params))
    assert isinstance(env.backend, MujocoCpuBackend)
    assert np.array_equal(env.backend.model_of(2).body_mass, model.body_mass)
    with torch.inference_mode():
        obs, *_ = env.step(torch.zeros(3, 29))
    p = obs["policy"]
    assert torch.equal(p, obs["critic"][:, : p.shape[1]])  # No observation noise.
    assert torch.equal(env.physics_params, torch.zeros_like(env.physics_params))


def test_dr_default_varies_within_ranges(model: mujoco.MjModel, motion: Motion) -> None:
    env = make_env(model, motion, n=4, dr="default")
    dr = dr_default()
    be = env.backend
    assert isinstance(be, MujocoCpuBackend)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    frictions = [be.model_of(i).geom_friction[floor, 0] for i in range(4)]
    assert len(set(frictions)) == 4 and all(
        dr.friction[0] <= f <= dr.friction[1] for f in frictions
    )
    ratio = np.stack([be.model_of(i).body_mass[1:] / model.body_mass[1:] for i in range(4)])
    assert ratio.min() >= dr.mass_scale[0] - 1e-9 and ratio.max() <= dr.mass_scale[1] + 1e-9
    assert ratio.std() > 0.01
    kp = np.stack(
        [be.model_of(i).actuator_gainprm[:, 0] / model.actuator_gainprm[:, 0] for i in range(4)]
    )
    assert kp.min() >= dr.kp_scale[0] - 1e-9 and kp.max() <= dr.kp_scale[1] + 1e-9
    e = env.physics_params
    assert e.abs().max() <= 1.0 and e.std(dim=0).max() > 0.1
    with torch.inference_mode():
        obs, *_ = env.step(torch.zeros(4, 29))
    p = obs["policy"]
    assert not torch.equal(p, obs["critic"][:, : p.shape[1]])  # Noisy policy observations.
    assert torch.equal(obs["critic"][:, p.shape[1] : p.shape[1] + e.shape[1]], e)


def test_com_mass_scale_loads_the_anchor_body_alone(model: mujoco.MjModel, motion: Motion) -> None:
    """``com_mass_scale`` (a payload on the torso) multiplies the anchor body's mass on top of
    ``mass_scale``; the other bodies keep theirs; ``e`` spans the product of both ranges."""
    dr = replace(dr_mod.dr_none(), mass_scale=(0.95, 1.05), com_mass_scale=(1.4, 1.6))
    cfg = replace(g1_tracking(dr), action_base="default")
    env = TrackingEnv(cfg, motion, 6, model=model)
    be = env.backend
    assert isinstance(be, MujocoCpuBackend)
    torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, cfg.anchor_body)
    ratio = np.stack([be.model_of(i).body_mass / model.body_mass.clip(1e-12) for i in range(6)])
    assert ratio[:, torso].min() >= 1.4 * 0.95 - 1e-9 and ratio[:, torso].max() <= 1.6 * 1.05
    others = np.delete(ratio[:, 1:], torso - 1, axis=1)
    others = others[:, model.body_mass[1:][np.arange(model.nbody - 1) != torso - 1] > 0]
    assert others.min() >= 0.95 - 1e-9 and others.max() <= 1.05 + 1e-9
    e = env.physics_params
    assert e.abs().max() <= 1.0 + 1e-6 and e.std(dim=0).max() > 0.1
    with pytest.raises(ValueError, match="com_column"):
        dr_mod.sample(dr, 2, num_bodies=5, num_joints=3, rng=np.random.default_rng(0))


def test_sample_pool_serves_fresh_rows_with_their_normalization() -> None:
    dr = dr_default()
    pool = dr_mod.SamplePool(dr, num_bodies=5, num_joints=3, rng=np.random.default_rng(0), block=4)
    rows = [pool.take(k) for k in (3, 1, 2, 6)]  # The third and the fourth start new blocks.
    friction = np.concatenate([smp.physics.friction for smp, _ in rows])
    assert len(friction) == 12 and len(np.unique(friction)) == 12
    for smp, e in rows:
        assert e.shape == (len(smp.physics.friction), dr_mod.param_dim(5, 3))
        np.testing.assert_allclose(e, dr_mod.normalize(dr, smp))
        assert smp.physics.mass_scale.shape == (len(e), 5) and smp.joint_offset.shape == (len(e), 3)


def test_param_layout_names_each_quantity_of_e() -> None:
    """Each block of the layout holds its quantity, normalized by hand here: linear for
    friction, CoM, joint offsets and delay, logarithmic for the scales."""
    dr = replace(dr_default(), com_mass_scale=(1.0, 1.0))
    smp = dr_mod.sample(dr, 7, num_bodies=5, num_joints=3, rng=np.random.default_rng(1))
    e = dr_mod.normalize(dr, smp)
    lay = dr_mod.param_layout(5, 3)
    assert sum(sl.stop - sl.start for sl in lay.values()) == e.shape[1] == dr_mod.param_dim(5, 3)

    def lin(x: np.ndarray, r: tuple[float, float]) -> np.ndarray:
        return (x - r[0]) / (r[1] - r[0]) * 2.0 - 1.0

    def log(x: np.ndarray, r: tuple[float, float]) -> np.ndarray:
        return lin(np.log(x), (math.log(r[0]), math.log(r[1])))

    p = smp.physics
    np.testing.assert_allclose(e[:, lay["friction"]], lin(p.friction, dr.friction)[:, None])
    np.testing.assert_allclose(e[:, lay["mass_scale"]], log(p.mass_scale, dr.mass_scale))
    com = np.stack([lin(p.com_offset[:, k], dr.com_offset[k]) for k in range(3)], -1)
    np.testing.assert_allclose(e[:, lay["com_offset"]], com)
    np.testing.assert_allclose(e[:, lay["kp_scale"]], log(p.kp_scale, dr.kp_scale))
    np.testing.assert_allclose(e[:, lay["kd_scale"]], log(p.kd_scale, dr.kd_scale))
    np.testing.assert_allclose(
        e[:, lay["armature_scale"]], log(p.armature_scale, dr.armature_scale)
    )
    np.testing.assert_allclose(e[:, lay["joint_offset"]], lin(smp.joint_offset, dr.joint_offset))
    delay = lin(smp.action_delay.astype(float), dr.action_delay)[:, None]
    np.testing.assert_allclose(e[:, lay["action_delay"]], delay)


def test_wide_profile_contains_default_and_widens_the_robot_axes() -> None:
    wide, default = dr_mod.dr_profile("wide"), dr_default()
    wide.validate("wide")

    def ranges(dr: dr_mod.DomainRandomization) -> dict[str, tuple[float, float]]:
        out = {f.name: getattr(dr, f.name) for f in fields(dr)}
        for name in ("com_offset", "push_lin_vel", "push_ang_vel"):
            out.update({f"{name}.{a}": r for a, r in zip("xyz", out.pop(name), strict=True)})
        return {k: v for k, v in out.items() if isinstance(v, tuple)}

    w, d = ranges(wide), ranges(default)
    assert w.keys() == d.keys()
    for k in d:  # Every range of `default` lies inside `wide`'s ...
        assert w[k][0] <= d[k][0] and w[k][1] >= d[k][1], k
    widened = {k for k in d if w[k] != d[k]}  # ... and only the robot's axes grow.
    assert widened == {"friction", "com_mass_scale", "action_delay", "com_offset.x"}
    assert wide.obs_noise == default.obs_noise and wide.push_interval_s == default.push_interval_s


def test_yaml_profile(tmp_path: Path) -> None:
    good = tmp_path / "dr.yaml"
    good.write_text(
        "base: default\nfriction: [0.5, 0.9]\naction_delay: [0, 2]\nobs_noise: {joint_vel: 1.0}\n"
    )
    dr = load_dr_profile(good)
    assert dr.friction == (0.5, 0.9) and dr.action_delay == (0, 2)
    assert dr.obs_noise is not None and dr.obs_noise.joint_vel == 1.0
    assert dr.com_offset == dr_default().com_offset
    bad = tmp_path / "bad.yaml"
    bad.write_text("friction: [0.5, 0.9]\nfrcition_typo: [1, 2]\n")
    with pytest.raises(InputError, match="frcition_typo"):
        load_dr_profile(bad)
    bad.write_text("obs_noise: {joint_velocity: 1.0}\n")
    with pytest.raises(InputError, match="joint_velocity"):
        load_dr_profile(bad)
    bad.write_text("mass_scale: [1.2, 0.8]\n")
    with pytest.raises(InputError, match="mass_scale"):
        load_dr_profile(bad)


# ---------------------------------------------------------------- sampling and backends


def test_adaptive_sampling_favours_failing_bins(model: mujoco.MjModel, motion: Motion) -> None:
    cfg = replace(g1_tracking("none"), adaptive=AdaptiveSampling(alpha=0.5), action_base="default")
    env = TrackingEnv(cfg, motion, 2, model=model)
    before = env.sampling_weights.clone()
    assert torch.allclose(before, torch.full_like(before, 1 / len(before)))
    env.state.frame[:] = 55  # Bin 1 of the 1.5 s clip (bins of 1 s).
    env._terminated[:] = True
    env._time_outs[:] = False
    env._update_failure_stats()
    after = env.sampling_weights
    assert after[1] > after[0] and after[1] > 1.2 * before[1]


def test_failed_draws_replay_a_share_of_resets_from_a_ring() -> None:
    rng = np.random.default_rng(0)
    fresh = (np.arange(10.0), np.arange(10)[:, None] * np.ones((1, 3)))
    idle = dr_mod.FailedDraws(0.5, 4, np.random.default_rng(1))
    assert idle.mix(fresh) is fresh  # Nothing failed yet: the fresh draws, untouched.
    ring = dr_mod.FailedDraws(1.0, 4, np.random.default_rng(1))
    ring.record((np.array([100.0, 101, 102]), np.full((3, 3), 7.0)))
    ring.record((np.array([103.0, 104]), np.full((2, 3), 8.0)))  # 100 is pushed out.
    assert len(ring) == 4
    mixed = ring.mix(fresh)
    assert set(mixed[0]) <= {101.0, 102, 103, 104} and len(set(mixed[0])) > 1
    assert np.array_equal(mixed[1][:, 0], np.where(mixed[0] <= 102, 7.0, 8.0))  # Whole rows.
    assert np.array_equal(fresh[0], np.arange(10.0))  # The input is not changed.
    half = dr_mod.FailedDraws(0.3, 4, rng)
    half.record((np.array([-1.0]), np.zeros((1, 3))))
    share = np.mean([np.mean(half.mix(fresh)[0] == -1.0) for _ in range(400)])
    assert abs(share - 0.3) < 0.03


def test_a_failed_episodes_physics_comes_back_at_its_reset(
    model: mujoco.MjModel, motion: Motion
) -> None:
    """With the replay on, the draw of an episode that fails is kept and a reset takes it
    again (the share is 1 here: every reset replays); without it, a reset draws anew."""

    def fail_env_0(env: TrackingEnv) -> tuple[torch.Tensor, torch.Tensor]:
        before = env.physics_params.clone()
        r = env.backend.read()
        qpos, qvel = r.qpos.copy(), r.qvel.copy()
        qpos[0, 2] += 0.6  # Lift env 0 well above its reference: it fails this step.
        env.backend.reset_to(np.arange(2), qpos, qvel)
        with torch.inference_mode():
            _, _, dones, extras = env.step(torch.zeros(2, 29))
        assert bool(dones[0]) and not bool(extras["time_outs"][0]) and not bool(dones[1])
        return before, env.physics_params.clone()

    fresh = make_env(model, motion, n=2, dr="default")
    before, after = fail_env_0(fresh)
    assert not torch.equal(after[0], before[0]) and torch.equal(after[1], before[1])

    env = make_env(model, motion, n=2, dr="default", adaptive=AdaptiveSampling(dr_replay=0.5))
    assert env.events.replay is not None and len(env.events.replay) == 0
    env.events.replay.share = 1.0
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    be = env.backend
    assert isinstance(be, MujocoCpuBackend)
    friction = be.model_of(0).geom_friction[floor, 0]
    before, after = fail_env_0(env)
    assert len(env.events.replay) == 1
    assert torch.equal(after, before)  # Env 0 has its failed draw again; env 1 kept its own.
    assert be.model_of(0).geom_friction[floor, 0] == friction
    with pytest.raises(InputError, match="dr_replay"):
        replace(g1_tracking("default"), adaptive=AdaptiveSampling(dr_replay=1.0)).validate()


def test_reset_state_is_the_noisy_reference(model: mujoco.MjModel, motion: Motion) -> None:
    """The reset states built from block-drawn noise (rotation matrices, quaternion product as
    a matrix) against the quaternion formulas of reference state initialization."""
    env = make_env(model, motion, n=2)
    frames = np.array([3, 40, 70])
    u, rot, left = env.events.draw_reset_noise(3)
    env.events.reset_noise = dr_mod.Blocks(lambda n: (u, rot, left), block=3)
    qpos, qvel = env.events.reset_state(frames)
    ref_quat = motion.qpos[frames, 3:7] / np.linalg.norm(motion.qpos[frames, 3:7], axis=1)[:, None]
    root_quat = tf.quat_mul(tf.quat_from_euler_xyz(u[:, 3:6]), ref_quat)
    np.testing.assert_allclose(qpos[:, 3:7], root_quat, atol=1e-12)
    np.testing.assert_allclose(qpos[:, :3], motion.qpos[frames, :3] + u[:, :3], atol=1e-12)
    root = motion.body_names.index("pelvis")
    ang_vel_b = tf.quat_apply_inverse(root_quat, motion.body_ang_vel_w[frames, root] + u[:, 9:12])
    np.testing.assert_allclose(qvel[:, 3:6], ang_vel_b, atol=1e-9)
    np.testing.assert_allclose(qvel[:, :3], motion.body_lin_vel_w[frames, root] + u[:, 6:9])
    env.close()


def test_compiled_env_matches_eager(
    model: mujoco.MjModel, motion: Motion, monkeypatch: pytest.MonkeyPatch
) -> None:
    """torch.compile'd env math gives the eager env's observations, rewards and dones step by
    step (DR, noise, resets, a replaced episode counter), with one compiled graph each."""
    import torch._dynamo

    monkeypatch.setattr(torch._dynamo.config, "error_on_recompile", True)
    envs = [make_env(model, motion, n=6, torch_compile=c) for c in (False, True)]
    gen = torch.Generator().manual_seed(0)
    resets = 0
    for k in range(20):
        if k == 5:
            for env in envs:  # As OnPolicyRunner.learn(init_at_random_ep_len=True) does.
                env.episode_length_buf = torch.arange(6) * 20
        a = 0.5 * torch.randn(6, 29, generator=gen)
        with torch.inference_mode():
            (o1, r1, d1, x1), (o2, r2, d2, x2) = (env.step(a) for env in envs)
        assert torch.equal(d1, d2) and torch.equal(x1["time_outs"], x2["time_outs"])
        torch.testing.assert_close(r2, r1, atol=1e-5, rtol=1e-5)
        for group in ("policy", "critic", "proprio_history", "physics"):
            torch.testing.assert_close(o2[group], o1[group], atol=1e-4, rtol=1e-4)
        for key, value in x1["log"].items():
            torch.testing.assert_close(x2["log"][key], value, atol=1e-5, rtol=1e-5)
        resets += int(d1.sum())
    assert resets > 0
    for env in envs:
        env.close()


def test_compile_failure_is_reported(
    model: mujoco.MjModel, motion: Motion, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no C++ compiler found\ndetails")

    monkeypatch.setattr(torch, "compile", broken)
    with pytest.raises(HumimicError, match=r"no C\+\+ compiler found\); on the CPU it needs"):
        make_env(model, motion, n=2, torch_compile=True)


def test_rollout_and_threads_agree(model: mujoco.MjModel) -> None:
    cfg = g1_tracking("none")
    a = tracking_backend(replace(cfg, step_method="rollout"), 2, model=model)
    b = tracking_backend(replace(cfg, step_method="threads"), 2, model=model)
    q = np.tile(model.key_qpos[0], (2, 1))
    q[1, 2] += 0.05
    for be in (a, b):
        be.reset_to(np.arange(2), q, np.zeros((2, model.nv)))
        be.set_ctrl(q[:, 7:] + 0.1)
        be.step(4)
    ra, rb = a.read(), b.read()
    assert np.allclose(ra.qpos, rb.qpos, atol=1e-6)
    assert np.allclose(ra.body_pos_w, rb.body_pos_w, atol=1e-6)
    assert not np.allclose(ra.qpos, q)
    a.close()
    b.close()


# ------------------------------------------------------------------------------- PPO


def test_train_cfg_is_a_fresh_copy() -> None:
    a = train_cfg(PpoConfig())
    a["algorithm"]["learning_rate"] = 5.0
    a["obs_groups"]["actor"].append("critic")
    b = train_cfg(PpoConfig())
    assert b["algorithm"]["learning_rate"] == 1e-3 and b["obs_groups"]["actor"] == ["policy"]


def test_ppo_two_iterations(model: mujoco.MjModel, motion: Motion, tmp_path: Path) -> None:
    env = make_env(model, motion, n=4, dr="default")
    cfg = PpoConfig(
        actor_hidden_dims=(32, 32),
        critic_hidden_dims=(32, 32),
        num_steps_per_env=4,
        num_mini_batches=2,
        num_learning_epochs=1,
    )
    runner = OnPolicyRunner(env, train_cfg(cfg), log_dir=str(tmp_path), device="cpu")
    runner.learn(num_learning_iterations=2, init_at_random_ep_len=True)
    checkpoints = sorted(tmp_path.glob("model_*.pt"))
    assert [c.name for c in checkpoints] == ["model_0.pt", "model_1.pt"]
    saved = torch.load(checkpoints[-1], weights_only=True)
    assert saved["iter"] == 1
    env.close()


def test_batched_set_const_equals_mujocos(model: mujoco.MjModel) -> None:
    """The warp backend's constants of randomized models (``InertiaConstants``, batched
    tensor math) against ``mj_setConst`` on each model, with wide DR ranges."""
    import copy

    from humimic.sim.params import ModelLayout
    from humimic.sim.setconst import InertiaConstants

    cfg = g1_tracking("default")
    wide = replace(cfg.dr, mass_scale=(0.5, 2.0), armature_scale=(0.3, 3.0),
                   com_offset=((-0.1, 0.1), (-0.1, 0.1), (-0.1, 0.1)))  # fmt: skip
    lay = ModelLayout.of(model, cfg.body_names, com_body=cfg.anchor_body,
                         contact_body_names=cfg.undesired_contact_bodies,
                         foot_body_names=("left_ankle_roll_link", "right_ankle_roll_link"))  # fmt: skip
    n = 5
    smp = dr_mod.sample(wide, n, num_bodies=len(lay.robot_bodies), num_joints=model.nu,
                        rng=np.random.default_rng(3))  # fmt: skip
    fields = lay.fields(smp.physics)
    out = InertiaConstants(model)(
        *(
            torch.as_tensor(fields[f])
            for f in ("body_mass", "body_inertia", "body_ipos", "dof_armature")
        )
    )
    m, d = copy.copy(model), mujoco.MjData(model)
    for k in range(n):
        for name, v in fields.items():
            getattr(m, name)[:] = v[k]
        mujoco.mj_setConst(m, d)
        for name, v in out.items():
            np.testing.assert_allclose(v[k].numpy(), getattr(m, name), rtol=1e-9, atol=1e-12,
                                       err_msg=name)  # fmt: skip
    # The fields do differ between the models (the test is not of one model five times).
    assert np.ptp(out["dof_invweight0"].numpy()[:, 10]) > 1e-3


# ---------------------------------------------------------------------------- action bases


@pytest.mark.parametrize("base", ["default", "reference"])
def test_action_base_sets_the_pd_targets(model: mujoco.MjModel, motion: Motion, base: str) -> None:
    """PD target = base(frame) + scale * action: the default pose, or the reference's next
    frame (``reference``), whatever frame each env is at; a base-relative action of the
    targets (``action_for_targets``) gives them back."""
    env = make_env(model, motion, n=3, dr="none", action_base=base)
    try:
        env.state.frame[:] = torch.tensor([0, 10, 73])
        gen = torch.Generator().manual_seed(3)
        a = torch.randn(3, env.num_actions, generator=gen)
        frames = env.state.frame.clone()
        expected_base = (
            env.default_joint_pos.expand(3, -1)
            if base == "default"
            else env.reference_joint_pos[(frames + 1).clamp(max=env.num_frames - 1)]
        )
        np.testing.assert_allclose(
            env.action_for_targets(expected_base + 0.1).numpy(),
            (0.1 / env.action_scale).expand(3, -1).numpy(),
            rtol=1e-5,
        )
        env.step(a)
        np.testing.assert_allclose(
            env.joint_targets.numpy(), (expected_base + env.action_scale * a).numpy(), atol=1e-6
        )
        # The frames differ, so the reference base differs between envs (the default not).
        spread = float((env.joint_targets - env.action_scale * a).std(dim=0).max())
        assert (spread > 1e-3) == (base == "reference")
    finally:
        env.close()


def test_feedforward_base_needs_stored_controls(model: mujoco.MjModel, motion: Motion) -> None:
    with pytest.raises(InputError, match=r"feedforward.*humimic refine"):
        make_env(model, motion, n=2, dr="none", action_base="feedforward")
    with pytest.raises(InputError, match="action_base"):
        make_env(model, motion, n=2, dr="none", action_base="residual")


def test_actor_output_gain_starts_the_policy_at_its_base(
    model: mujoco.MjModel, motion: Motion
) -> None:
    """A zero gain makes the initial actor's mean output zero (the action base itself) for any
    observation; gain 1 leaves PyTorch's initialization alone."""
    from humimic.tracking.rsl import make_runner, scale_actor_output

    env = make_env(model, motion, n=4, dr="default")
    try:
        cfg = PpoConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_steps_per_env=2)
        runner = make_runner(env, train_cfg(cfg), log_dir=None, device="cpu")
        obs = env.get_observations()
        policy = runner.get_inference_policy(device="cpu")
        before = policy(obs).clone()
        scale_actor_output(runner, 1.0)
        assert torch.equal(policy(obs), before) and float(before.abs().max()) > 1e-3
        scale_actor_output(runner, 0.0)
        assert float(policy(obs).abs().max()) == 0.0
    finally:
        env.close()


def test_critic_warmup_trains_the_critic_alone_then_both(
    model: mujoco.MjModel, motion: Motion
) -> None:
    """During the warmup iterations PPO's update leaves every actor parameter (its noise
    included) and the learning rate as they were and changes the critic; after them both
    learn."""
    from humimic.tracking.rsl import make_runner

    env = make_env(model, motion, n=4, dr="default")
    try:
        cfg = PpoConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_steps_per_env=4,
                        critic_warmup_iterations=2)  # fmt: skip
        runner = make_runner(env, train_cfg(cfg), log_dir=None, device="cpu")
        runner.logger.log = lambda **kw: None

        def snapshot(m: torch.nn.Module) -> list[torch.Tensor]:
            return [p.detach().clone() for p in m.parameters()]

        actor, critic = snapshot(runner.alg.actor), snapshot(runner.alg.critic)
        runner.learn(2)
        assert all(
            torch.equal(a, b) for a, b in zip(actor, snapshot(runner.alg.actor), strict=True)
        )
        assert not all(
            torch.equal(a, b) for a, b in zip(critic, snapshot(runner.alg.critic), strict=True)
        )
        assert runner.alg.learning_rate == cfg.learning_rate
        assert all(p.requires_grad for p in runner.alg.actor.parameters())
        runner.current_learning_iteration = 2  # As a resume from those 2 iterations sets it.
        runner.learn(1)  # The third iteration: past the warmup.
        assert not all(
            torch.equal(a, b) for a, b in zip(actor, snapshot(runner.alg.actor), strict=True)
        )
    finally:
        env.close()


def test_base_lin_vel_group_is_the_roots_velocity_in_its_frame(
    model: mujoco.MjModel, motion: Motion
) -> None:
    """``base_lin_vel`` (what the ``mlp-velocity`` student reads) is the root frame's world
    linear velocity rotated into that frame, exact without DR; with DR ``default`` it is noisy within mjlab's half-width
    of 0.5 m/s."""
    env = make_env(model, motion, n=4, dr="none")
    try:
        obs = env.get_observations()
        for _ in range(5):
            obs, *_ = env.step(0.3 * torch.ones(4, env.num_actions))
        r, k = env.backend.read(), env.state.root_index
        # The root frame's sensors (velocity and orientation, world frame), rotated here.
        want = tf.quat_apply_inverse(r.body_quat_w[:, k], r.body_lin_vel_w[:, k])
        assert np.abs(want).max() > 0.1  # It moves.
        np.testing.assert_allclose(obs["base_lin_vel"].numpy(), want, atol=1e-5)
        # The free joint's own velocity agrees up to the sensors' one physics step of lag
        # (MuJoCo evaluates sensors before it integrates).
        joint = np.stack([tf.quat_apply_inverse(q[3:7], v[:3])
                          for q, v in zip(r.qpos, r.qvel, strict=True)])  # fmt: skip
        np.testing.assert_allclose(obs["base_lin_vel"].numpy(), joint, atol=0.05)
    finally:
        env.close()
    noisy = make_env(model, motion, n=64, dr="default")
    try:
        obs = noisy.get_observations()
        start = noisy._policy_dim + noisy._params_dim
        diff = obs["base_lin_vel"] - obs["critic"][:, start : start + 3]
        assert 0.3 < float(diff.abs().max()) <= 0.5 + 1e-6
    finally:
        noisy.close()


def test_observation_layout_from_the_terms() -> None:
    """The group widths and the policy's noise half-widths come from the terms; checked here
    against the layout written out by hand (the order docs/tracking.md gives)."""
    from humimic.sim.randomization import ObservationNoise
    from humimic.tracking import observations as ob

    dims = ob.ObsDims(joints=5, bodies=4, feet=2, params=7)
    assert ob.group_size(ob.POLICY_TERMS, dims) == 2 * 5 + 3 + 6 + 3 + 3 + 3 * 5
    assert ob.group_size(ob.CRITIC_EXTRA_TERMS, dims) == 7 + 3 + 9 * 4 + 2
    assert ob.offset(ob.CRITIC_EXTRA_TERMS, "base_lin_vel", dims) == 7
    n = ObservationNoise(anchor_pos=1.0, anchor_ori=2.0, projected_gravity=3.0,
                         base_ang_vel=4.0, joint_pos=5.0, joint_vel=6.0)  # fmt: skip
    want = [0.0] * 10 + [1.0] * 3 + [2.0] * 6 + [3.0] * 3 + [4.0] * 3 + [5.0] * 5 + [6.0] * 5
    scale = ob.noise_scale(ob.POLICY_TERMS, n, dims)
    assert scale is not None
    np.testing.assert_array_equal(scale.numpy(), np.array(want + [0.0] * 5, dtype=np.float32))
    assert ob.noise_scale(ob.POLICY_TERMS, None, dims) is None
