"""Robot motion files: kinematics from qpos on the real G1, and the versioned .npz format."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest

from humimic.errors import InputError, MotionDataError
from humimic.motion import SCHEMA_VERSION, Motion, load_motion, motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model

FPS = 50.0
FRAMES = 100
BASE_SPEED = 0.6  # m/s along world x
YAW_RATE = 2.0  # rad/s about world z; the yaw passes pi, so w changes sign
YAW0 = 0.5
BASE_HEIGHT = 0.78

TRACKER_KEYS = (
    "fps",
    "joint_pos",
    "joint_vel",
    "body_pos_w",
    "body_quat_w",
    "body_lin_vel_w",
    "body_ang_vel_w",
    "joint_names",
    "body_names",
    "schema_version",
)


@dataclass(frozen=True)
class Trajectory:
    """A synthetic smooth trajectory with its analytic joint velocities."""

    t: np.ndarray  # (T,)
    qpos: np.ndarray  # (T, 7 + J)
    amp: np.ndarray  # (J,)
    omega: np.ndarray  # (J,)
    joint_vel: np.ndarray  # (T, J), analytic


@pytest.fixture(scope="module")
def g1() -> mujoco.MjModel:
    return nominal_model(get_robot("g1"))


@pytest.fixture(scope="module")
def traj(g1: mujoco.MjModel) -> Trajectory:
    t = np.arange(FRAMES) / FPS
    lo, hi = g1.jnt_range[1:, 0], g1.jnt_range[1:, 1]
    nj = lo.shape[0]
    assert g1.nq == 7 + nj
    centre = 0.5 * (lo + hi)
    amp = np.minimum(0.25 * (hi - lo), 0.5)
    omega = 2.0 * np.pi * (0.5 + 0.05 * np.arange(nj))  # 0.5 .. 1.9 Hz
    phase = 0.3 * np.arange(nj)
    arg = omega[None] * t[:, None] + phase[None]
    joints = centre + amp * np.sin(arg)
    assert np.all(joints > lo) and np.all(joints < hi)
    yaw = YAW0 + YAW_RATE * t
    qpos = np.zeros((FRAMES, g1.nq))
    qpos[:, 0] = 0.3 + BASE_SPEED * t
    qpos[:, 1] = -0.1
    qpos[:, 2] = BASE_HEIGHT
    qpos[:, 3] = np.cos(yaw / 2)
    qpos[:, 6] = np.sin(yaw / 2)
    qpos[:, 7:] = joints
    return Trajectory(t=t, qpos=qpos, amp=amp, omega=omega, joint_vel=amp * omega * np.cos(arg))


@pytest.fixture(scope="module")
def motion(g1: mujoco.MjModel, traj: Trajectory) -> Motion:
    return motion_from_qpos(g1, traj.qpos, FPS, "g1")


# --- Kinematics -------------------------------------------------------------------------------


def test_motion_shapes_and_names(g1: mujoco.MjModel, motion: Motion) -> None:
    nj = g1.njnt - 1
    assert motion.robot == "g1"
    assert motion.fps == FPS
    assert motion.num_frames == FRAMES
    assert motion.body_names[0] == "pelvis"
    assert motion.joint_names == tuple(g1.joint(j).name for j in range(1, g1.njnt))
    assert len(motion.body_names) == g1.nbody - 1  # every body but the world
    nb = len(motion.body_names)
    assert motion.joint_pos.shape == motion.joint_vel.shape == (FRAMES, nj)
    assert motion.body_pos_w.shape == motion.body_lin_vel_w.shape == (FRAMES, nb, 3)
    assert motion.body_ang_vel_w.shape == (FRAMES, nb, 3)
    assert motion.body_quat_w.shape == (FRAMES, nb, 4)


def test_root_pose_is_qpos(motion: Motion, traj: Trajectory) -> None:
    np.testing.assert_allclose(motion.body_pos_w[:, 0], traj.qpos[:, :3], atol=1e-12)
    q = motion.body_quat_w[:, 0]
    dot = np.sum(q * traj.qpos[:, 3:7], axis=-1)
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-12)
    np.testing.assert_array_equal(motion.joint_pos, traj.qpos[:, 7:])
    np.testing.assert_array_equal(motion.qpos, traj.qpos)


def test_body_quats_are_unit_and_sign_continuous(motion: Motion) -> None:
    q = motion.body_quat_w
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) > 0)


def test_joint_vel_matches_analytic_derivative(motion: Motion, traj: Trajectory) -> None:
    h = 1.0 / FPS
    a, w = traj.amp, traj.omega
    # Central differences of a sinusoid: error <= a w (w h)^2 / 6.
    interior_tol = a * w**3 * h**2 / 6.0 * 1.01 + 1e-9
    err = np.abs(motion.joint_vel - traj.joint_vel)
    assert np.all(err[1:-1] <= interior_tol[None]), float(err[1:-1].max())
    # One-sided at the two ends: error <= a w^2 h / 2 + a w^3 h^2 / 6.
    end_tol = a * w**2 * h / 2.0 + a * w**3 * h**2 / 6.0 + 1e-9
    assert np.all(err[[0, -1]] <= end_tol[None])
    # And exactly the central difference it claims to be.
    central = (traj.qpos[2:, 7:] - traj.qpos[:-2, 7:]) / (2.0 * h)
    np.testing.assert_allclose(motion.joint_vel[1:-1], central, atol=1e-9)


def test_pelvis_velocities(motion: Motion) -> None:
    np.testing.assert_allclose(
        motion.body_ang_vel_w[:, 0], np.tile([0.0, 0.0, YAW_RATE], (FRAMES, 1)), atol=1e-9
    )
    np.testing.assert_allclose(
        motion.body_lin_vel_w[:, 0], np.tile([BASE_SPEED, 0.0, 0.0], (FRAMES, 1)), atol=1e-9
    )


def test_body_lin_vel_is_derivative_of_body_pos(motion: Motion) -> None:
    h = 1.0 / FPS
    central = (motion.body_pos_w[2:] - motion.body_pos_w[:-2]) / (2.0 * h)
    np.testing.assert_allclose(motion.body_lin_vel_w[1:-1], central, atol=1e-9)


def test_single_frame_motion_has_zero_velocities(g1: mujoco.MjModel, traj: Trajectory) -> None:
    m = motion_from_qpos(g1, traj.qpos[:1], FPS, "g1")
    assert m.num_frames == 1
    np.testing.assert_array_equal(m.joint_vel, 0.0)
    np.testing.assert_array_equal(m.body_lin_vel_w, 0.0)
    np.testing.assert_array_equal(m.body_ang_vel_w, 0.0)


# --- File format ------------------------------------------------------------------------------


def _assert_same_motion(a: Motion, b: Motion) -> None:
    assert a.robot == b.robot
    assert a.fps == b.fps
    assert a.joint_names == b.joint_names
    assert a.body_names == b.body_names
    for name in (
        "qpos",
        "joint_pos",
        "joint_vel",
        "body_pos_w",
        "body_quat_w",
        "body_lin_vel_w",
        "body_ang_vel_w",
    ):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_save_load_round_trip_exact_without_pickle(motion: Motion, tmp_path: Path) -> None:
    path = tmp_path / "walk.npz"
    assert save_motion(motion, path) == path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.npz"]  # no temp file left
    loaded = load_motion(path)
    _assert_same_motion(motion, loaded)
    assert not loaded.extras
    with np.load(path, allow_pickle=False) as z:
        assert set(TRACKER_KEYS) <= set(z.files)
        arrays = {k: z[k] for k in z.files}  # would raise on a pickled object array
    assert all(a.dtype != object for a in arrays.values())
    assert int(arrays["schema_version"]) == SCHEMA_VERSION
    assert float(arrays["fps"]) == FPS
    assert [str(s) for s in arrays["joint_names"]] == list(motion.joint_names)
    assert [str(s) for s in arrays["body_names"]] == list(motion.body_names)
    np.testing.assert_array_equal(arrays["body_quat_w"], motion.body_quat_w)


def test_save_load_round_trip_extras(motion: Motion, tmp_path: Path) -> None:
    contacts = np.zeros((FRAMES, 2), dtype=bool)
    contacts[10:20, 0] = True
    m = Motion(**{**motion.__dict__, "extras": {"contacts": contacts}})
    path = tmp_path / "with_extras.npz"
    save_motion(m, path)
    loaded = load_motion(path)
    _assert_same_motion(m, loaded)
    assert loaded.extras is not None
    np.testing.assert_array_equal(loaded.extras["contacts"], contacts)


def test_save_motion_requires_npz(motion: Motion, tmp_path: Path) -> None:
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"walk\.npy.*\.npz"):
        save_motion(motion, out / "walk.npy")
    assert not out.exists() or list(out.iterdir()) == []
    assert list(tmp_path.iterdir()) in ([], [out])


@pytest.fixture()
def saved(motion: Motion, tmp_path: Path) -> dict[str, np.ndarray]:
    path = tmp_path / "good.npz"
    save_motion(motion, path)
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    np.savez(path, **arrays)  # type: ignore[arg-type]
    return path


def test_load_motion_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nothere\.npz: no such file"):
        load_motion(tmp_path / "nothere.npz")


def test_load_motion_not_an_npz(tmp_path: Path) -> None:
    path = tmp_path / "garbage.npz"
    path.write_bytes(b"this is not a zip file")
    with pytest.raises(MotionDataError, match=r"garbage\.npz"):
        load_motion(path)


@pytest.mark.parametrize("key", ["body_quat_w", "fps", "joint_names", "schema_version"])
def test_load_motion_missing_key(saved: dict[str, np.ndarray], tmp_path: Path, key: str) -> None:
    del saved[key]
    path = _write(tmp_path / "missing_key.npz", saved)
    with pytest.raises(MotionDataError, match=rf"missing_key\.npz: missing key.*'{key}'"):
        load_motion(path)


def test_load_motion_wrong_schema_version(saved: dict[str, np.ndarray], tmp_path: Path) -> None:
    saved["schema_version"] = np.array(SCHEMA_VERSION + 1)
    path = _write(tmp_path / "future.npz", saved)
    with pytest.raises(MotionDataError, match=rf"future\.npz: schema_version {SCHEMA_VERSION + 1}"):
        load_motion(path)


@pytest.mark.parametrize("key", ["joint_vel", "body_pos_w", "body_quat_w", "qpos"])
def test_load_motion_nan(saved: dict[str, np.ndarray], tmp_path: Path, key: str) -> None:
    arr = saved[key].copy()
    arr.reshape(-1)[7] = np.nan
    saved[key] = arr
    path = _write(tmp_path / "nan.npz", saved)
    with pytest.raises(MotionDataError, match=rf"nan\.npz: {key} contains NaN"):
        load_motion(path)


@pytest.mark.parametrize("fps", [np.nan, 0.0, -50.0])
def test_load_motion_bad_fps(saved: dict[str, np.ndarray], tmp_path: Path, fps: float) -> None:
    saved["fps"] = np.array(fps)
    path = _write(tmp_path / "bad_fps.npz", saved)
    with pytest.raises(MotionDataError, match=r"bad_fps\.npz: fps"):
        load_motion(path)


@pytest.mark.parametrize("key", ["joint_vel", "body_lin_vel_w", "body_ang_vel_w"])
def test_load_motion_mismatched_frames(
    saved: dict[str, np.ndarray], tmp_path: Path, key: str
) -> None:
    saved[key] = saved[key][:-3]
    path = _write(tmp_path / "short.npz", saved)
    with pytest.raises(
        MotionDataError, match=rf"short\.npz: {key} has {FRAMES - 3} frames, qpos has {FRAMES}"
    ):
        load_motion(path)
