"""Parity of the MuJoCo Warp backend with the CPU backend, on the CPU (mujoco_warp's CPU device).

Slow: the first run compiles MJWarp's kernels for the CPU (about a minute on 2 cores; warp
caches them in ``~/.cache/warp``). Run with ``bash scripts/test.sh -m slow tests/test_warp_backend.py``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from humimic.errors import HumimicError, InputError
from humimic.motion import Motion, motion_from_qpos
from humimic.sim import randomization as dr_mod
from humimic.sim.backend import MujocoCpuBackend
from humimic.sim.setup import WarpOptions
from humimic.sim.warp_backend import MujocoWarpBackend, capacity, warp_available
from humimic.tracking.config import g1_tracking
from humimic.tracking.env import TrackingEnv, tracking_backend, tracking_model

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not warp_available(), reason="needs mujoco_warp (humimic[gpu])"),
]

N = 3
DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    ),
]


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return tracking_model(g1_tracking("default"))


def _backends(
    model: mujoco.MjModel, device: str = "cpu", method: str = "threads", **kw
) -> tuple[MujocoCpuBackend, MujocoWarpBackend]:
    cfg = g1_tracking("default")
    names = {
        "body_names": cfg.body_names,
        "contact_body_names": cfg.undesired_contact_bodies,
        "foot_body_names": ("left_ankle_roll_link", "right_ankle_roll_link"),
        "com_body": cfg.anchor_body,
        "per_env_models": True,
    }
    # The thread pool keeps each env's MjData, so the solver's warm start carries over between
    # env steps as it does in MJWarp (rollout restarts it at every call).
    cpu = MujocoCpuBackend(model, N, method=method, nthread=1, **names)  # type: ignore[arg-type]
    gpu = MujocoWarpBackend(model, N, device=device, **names, **kw)
    return cpu, gpu


def _start(model: mujoco.MjModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Home pose with the joints perturbed, dropped from 2 cm, moving a little."""
    qpos = np.tile(model.key_qpos[0], (N, 1))
    qpos[:, 2] += 0.02
    qpos[:, 7:] += rng.uniform(-0.1, 0.1, size=(N, model.nu))
    qvel = rng.uniform(-0.2, 0.2, size=(N, model.nv))
    return qpos, qvel


def _close(a, b, what: str, atol: float, rtol: float = 0.0) -> None:
    a, b = np.asarray(a), np.asarray(b)
    print(f"{what}: max abs diff {np.max(np.abs(a - b)):.3g}")
    err = np.abs(a - b) - rtol * np.abs(b)
    assert np.all(err <= atol), f"{what}: off by up to {np.max(np.abs(a - b)):.3g}"


def _same_readout(cpu, gpu, atol_pos: float, atol_vel: float, atol_force: float) -> None:
    rc, rg = cpu.read(), gpu.read()
    _close(rg.qpos, rc.qpos, "qpos", atol_pos)
    _close(rg.qvel, rc.qvel, "qvel", atol_vel)
    _close(rg.body_pos_w, rc.body_pos_w, "body positions", atol_pos)
    # Quaternions up to sign.
    dots = np.abs(np.sum(rg.body_quat_w * rc.body_quat_w, axis=-1))
    assert np.all(dots > 1 - atol_pos), f"body orientations: min |dot| {dots.min():.6f}"
    _close(rg.body_lin_vel_w, rc.body_lin_vel_w, "body linear velocities", atol_vel)
    _close(rg.body_ang_vel_w, rc.body_ang_vel_w, "body angular velocities", atol_vel)
    np.testing.assert_array_equal(rg.contact_found, rc.contact_found)
    _close(rg.foot_force, rc.foot_force, "foot forces", atol_force, rtol=0.02)


@pytest.mark.parametrize("device", DEVICES)
def test_steps_from_the_same_states_agree_with_the_cpu_backend(
    model: mujoco.MjModel, device: str
) -> None:
    """Reset, randomized physics, a push and 8 env steps: both backends read the same."""
    rng = np.random.default_rng(0)
    cpu, gpu = _backends(model, device)
    pool = dr_mod.sample(
        g1_tracking("default").dr, N, num_bodies=cpu.num_bodies_total, num_joints=cpu.nu, rng=rng
    )
    params = pool.physics
    for be in (cpu, gpu):
        be.set_params(np.array([1, 2]), params.select(slice(1, 3)))
        be.set_params(np.array([0]), be.nominal_params(1))
    qpos, qvel = _start(model, rng)
    for be in (cpu, gpu):
        be.reset_to(np.arange(N), qpos, qvel)
    _same_readout(cpu, gpu, 1e-5, 1e-4, 1e-2)  # Kinematics only: float32 round-off.

    ctrl = qpos[:, 7:] + rng.uniform(-0.05, 0.05, size=(N, model.nu))
    for k in range(8):
        for be in (cpu, gpu):
            be.set_ctrl(ctrl)
            be.step(4)
        if k == 3:
            dq = np.zeros((2, model.nv))
            dq[:, :3] = [[0.3, -0.2, 0.0], [-0.1, 0.4, 0.1]]
            for be in (cpu, gpu):
                be.push(np.array([0, 2]), dq)
    # 32 physics steps, the feet landing on the floor: float32 against float64 and another
    # implementation of the solver (measured: 4e-7 m, 1e-5 m/s, 6e-3 N).
    _same_readout(cpu, gpu, 1e-4, 1e-3, 0.5)
    # The physics differ by env (DR): the same control moves them apart.
    r = gpu.read()
    assert np.abs(r.qpos[1] - r.qpos[2]).max() > 1e-3


@pytest.mark.parametrize("device", DEVICES)
def test_the_env_reads_the_same_through_either_backend(model: mujoco.MjModel, device: str) -> None:
    """The whole tracking env (DR, resets, observations, rewards) on both backends."""
    fps, T = 50.0, 60
    q = np.tile(model.key_qpos[0], (T, 1))
    adr = model.jnt_qposadr[model.joint("left_shoulder_pitch_joint").id]
    q[:, adr] += 0.3 * np.sin(2 * np.pi * np.arange(T) / fps)
    motion: Motion = motion_from_qpos(model, q, fps, "g1")
    # Domain randomization, reset noise and resets as drawn by numpy (the same on both
    # devices); no torch random numbers, whose streams differ between CPU and CUDA: a fixed
    # start frame, no observation noise, no pushes.
    base = g1_tracking("default")
    cfg = replace(base, start_frame=0, dr=replace(base.dr, obs_noise=None, push_interval_s=None),
                  action_base="default")  # fmt: skip
    envs = [
        TrackingEnv(replace(cfg, step_method="threads", num_threads=1), motion, N, model=model),
        TrackingEnv(replace(cfg, backend="warp"), motion, N, model=model, device=device),
    ]
    assert isinstance(envs[1].backend, MujocoWarpBackend)
    assert envs[1]._tensor_io  # The env and the backend share the device: no host copies.
    actions = torch.zeros(N, envs[0].num_actions)
    for _ in range(5):
        outs = [env.step(actions.to(env.device)) for env in envs]
        (oc, rc, dc, _), (og, rg, dg, _) = [
            (o.to("cpu"), r.cpu(), d.cpu(), x) for o, r, d, x in outs
        ]
        torch.testing.assert_close(dg, dc)
        torch.testing.assert_close(og["policy"], oc["policy"], atol=1e-3, rtol=0)
        torch.testing.assert_close(og["critic"], oc["critic"], atol=1e-3, rtol=1e-3)
        torch.testing.assert_close(rg, rc, atol=1e-4, rtol=0)


@pytest.mark.parametrize("device", DEVICES)
def test_open_loop_rollouts_agree_with_the_cpu_backends(model: mujoco.MjModel, device: str) -> None:
    """``rollout`` (the dynamics retargeter's call): the same states and sensors after each
    physics step as the CPU backend's, from given states and warm starts, and the envs' own
    states untouched."""
    rng = np.random.default_rng(2)
    cpu, gpu = _backends(model, device, method="rollout")
    qpos, qvel = _start(model, rng)
    for be in (cpu, gpu):
        be.reset_to(np.arange(N), qpos, qvel)
    start = np.stack([cpu.env_state(i) for i in range(N)])
    np.testing.assert_allclose(np.stack([gpu.env_state(i) for i in range(N)]), start, atol=1e-6)
    nstep = 24
    controls = qpos[:, None, 7:] + rng.uniform(-0.05, 0.05, size=(N, nstep, model.nu))
    warm = np.zeros((N, model.nv))
    own = gpu.read().qpos.copy()
    sc, nc = cpu.rollout(start, controls, warm)
    sg, ng = gpu.rollout(start, controls, warm)
    assert sg.shape == sc.shape and ng.shape == nc.shape
    _close(sg, sc, "rollout states", 1e-3)
    _close(ng, nc, "rollout sensors", 1e-2, rtol=0.02)
    np.testing.assert_array_equal(gpu.read().qpos, own)
    with pytest.raises(InputError, match="rollout"):
        gpu.rollout(start[:1], controls, warm)


def test_running_out_of_constraint_rows_is_an_error_not_dropped_contacts(
    model: mujoco.MjModel,
) -> None:
    cpu, gpu = _backends(model, njmax=8)
    cpu.close()
    qpos, qvel = _start(model, np.random.default_rng(1))
    gpu.reset_to(np.arange(N), qpos, qvel)
    gpu.step(2)
    with pytest.raises(HumimicError, match="njmax"):
        gpu.check_overflow()


def test_default_capacity_bounds_the_floor_contacts(model: mujoco.MjModel) -> None:
    ncon, rows = capacity(model)
    # 24 boxes and 4 cylinders (4 contacts each), 8 spheres (1); 4 rows each; 29 limits.
    assert (ncon, rows) == (120, 4 * 120 + 29)


def test_bad_settings_are_refused(model: mujoco.MjModel) -> None:
    cfg = g1_tracking("none")
    with pytest.raises(InputError, match="device"):
        tracking_backend(replace(cfg, backend="warp"), 1, model=model, device="mps")
    with pytest.raises(InputError, match="njmax"):
        tracking_backend(replace(cfg, backend="warp", warp=WarpOptions(njmax=0)), 1, model=model)


def test_dynamics_retargeting_samples_on_the_warp_backend(shared_data: Path) -> None:
    """``humimic refine --backend warp``: the sampled rollouts run in MJWarp; the result's
    stored states are MuJoCo's replay of its controls, and it beats the raw reference."""
    from humimic.configs import DynamicsConfig, RetargetConfig
    from humimic.datasets import load_clip
    from humimic.retarget import Retargeter
    from humimic.retarget.dynamics import check_replay, refine

    clip = load_clip(shared_data / "cmu" / "35_01.bvh").slice(1, 49)  # 0.4 s
    walk = Retargeter("g1", "cmu", RetargetConfig(fps=50.0)).run(clip).motion
    cfg = DynamicsConfig(samples=16, iterations=2, horizon_s=0.2)
    motion, report = refine(walk, cfg, robustness=0, backend="warp", device="cpu")
    r = check_replay(motion)
    assert r["max_qpos_error"] <= 1e-12 and r["max_qvel_error"] <= 1e-12
    kin, dyn = report["kinematic_replay"], report["dynamics_replay"]
    assert not dyn["fell"]
    assert dyn["mpjpe_mm"] < kin["mpjpe_mm"], report
