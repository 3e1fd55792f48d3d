"""Viewer: the scene it draws equals MuJoCo FK; the human lines up; the server serves."""

from __future__ import annotations

import urllib.request
from functools import cache
from pathlib import Path

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from humimic.configs import retarget_default
from humimic.datasets import HumanClip, load_clip
from humimic.motion import Motion
from humimic.retarget import Retargeter
from humimic.robots import get_robot, nominal_model
from humimic.viewer import Viewer, align_human, pose_track, skeleton_segments, visual_meshes
from humimic.viewer.browser import free_port


@cache
def _walk(shared: Path) -> tuple[Motion, HumanClip]:
    """The first second of the CMU walk, retargeted; and the whole clip as read."""
    clip = load_clip(shared / "cmu" / "35_01.bvh")
    out = Retargeter("g1", "cmu", retarget_default()).run(clip.slice(1, 121))
    return out.motion, clip


def test_visual_meshes_are_the_robots_visual_geoms() -> None:
    model = nominal_model(get_robot("g1"))
    meshes = visual_meshes(model)
    assert len(meshes) == 35  # Menagerie's G1: one visual mesh per link and the head/logo.
    assert all(model.geom_group[m.geom] == 2 and len(m.faces) > 10 for m in meshes)
    assert {m.body for m in meshes} >= {"pelvis", "torso_link", "left_ankle_roll_link"}


def test_scene_poses_equal_mujoco_forward_kinematics(shared_data: Path) -> None:
    motion, _ = _walk(shared_data)
    model = nominal_model(get_robot("g1"))
    geoms = [m.geom for m in visual_meshes(model)]
    track = pose_track(model, motion.qpos, geoms)
    data = mujoco.MjData(model)
    for t in (0, 17, motion.num_frames - 1):
        data.qpos[:] = motion.qpos[t]
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(track.geom_pos[t], data.geom_xpos[geoms], atol=1e-12)
        rot = Rotation.from_quat(track.geom_quat[t], scalar_first=True).as_matrix()
        np.testing.assert_allclose(rot, data.geom_xmat[geoms].reshape(-1, 3, 3), atol=1e-9)
        # ...and the bodies are those of the motion file.
        np.testing.assert_allclose(
            track.body_pos[t, : len(motion.body_names)], motion.body_pos_w[t]
        )


def test_human_is_aligned_with_the_robot(shared_data: Path) -> None:
    motion, clip = _walk(shared_data)
    human = align_human(motion, clip)
    assert human.shape[0] == motion.num_frames
    hips = clip.index("Hips")
    left, right = clip.index("LeftUpLeg"), clip.index("RightUpLeg")
    np.testing.assert_allclose(human[0, hips, :2], 0.0, atol=1e-9)  # Above the origin.
    lr = human[0, left] - human[0, right]
    assert lr[1] > 0.1 and abs(lr[0]) < 0.05  # Left is +y: facing +x like the robot.
    # The human walks where the robot walks (scaled by the leg ratio).
    scale = motion.info["human_scale"]  # type: ignore[index]
    np.testing.assert_allclose(human[-1, hips, :2] * scale, motion.body_pos_w[-1, 0, :2], atol=0.08)
    feet = human[:, [clip.index("LeftToeBase"), clip.index("RightToeBase")], 2]
    assert 0.0 <= np.percentile(feet.min(axis=1), 5) < 0.06  # Standing on our floor.


def test_skeleton_segments() -> None:
    pos = np.arange(2 * 3 * 3, dtype=float).reshape(2, 3, 3)
    segs = skeleton_segments(pos, (-1, 0, 1))
    assert segs.shape == (2, 2, 2, 3)
    np.testing.assert_array_equal(segs[1, 1], [pos[1, 1], pos[1, 2]])


def test_viewer_serves_and_steps(shared_data: Path) -> None:
    motion, clip = _walk(shared_data)
    viewer = Viewer(
        motion,
        nominal_model(get_robot("g1")),
        human=clip,
        port=free_port(),
    )
    viewer.start(frame=3)
    try:
        assert viewer.frame == 3
        with urllib.request.urlopen(viewer.url, timeout=10) as r:
            assert r.status == 200
        viewer.set_frame(40)
        assert int(viewer._slider.value) == 40
        text = viewer.metrics_text(40)
        assert "Frame 40" in text and "Key-point error" in text and "foot contact" in text
        viewer.set_frame(10)
        viewer._playing.value = True
        viewer.step(0.5)  # Half a second at 50 fps: 25 frames on.
        assert viewer.frame == 35
        viewer.step(0.5)  # Past the end (50 frames): loops.
        assert viewer.frame == 10
        viewer.set_frame(10_000)  # Clamped.
        assert viewer.frame == motion.num_frames - 1
    finally:
        viewer.stop()


@pytest.mark.parametrize("bad", ["nope.obj", "empty_dir"])
def test_scene_errors(tmp_path: Path, bad: str) -> None:
    from humimic.errors import InputError
    from humimic.viewer import load_scene_meshes

    if bad == "empty_dir":
        (tmp_path / bad).mkdir()
    with pytest.raises(InputError, match=bad):
        load_scene_meshes(tmp_path / bad)


def test_moving_scene_objects_follow_the_motions_scene_poses(
    shared_data: Path, tmp_path: Path
) -> None:
    import dataclasses

    from humimic.viewer import load_scene_meshes

    motion, _ = _walk(shared_data)
    T = motion.num_frames
    (tmp_path / "s.yaml").write_text(
        "schema_version: 1\nobjects:\n  - {name: crate, box: [0.3, 0.3, 0.3], pos: [1, 0, 0.15]}\n"
    )
    poses = np.zeros((T, 1, 7))
    poses[:, 0, 0] = np.linspace(0.0, 1.0, T)  # Slides along x, in the robot's frame.
    poses[:, 0, 3] = 1.0
    extras = {**(motion.extras or {}), "scene_poses": poses,
              "metric_scene_penetration": np.full(T, 0.002)}  # fmt: skip
    motion = dataclasses.replace(motion, extras=extras)
    scene = load_scene_meshes(tmp_path / "s.yaml")
    assert scene[0].local_vertices is not None
    viewer = Viewer(motion, nominal_model(get_robot("g1")), scene=scene, port=free_port())
    viewer.start(frame=0)
    try:
        viewer.set_frame(T - 1)
        np.testing.assert_allclose(viewer._scene_handles[0].position, [1.0, 0.0, 0.0])
        assert "Scene penetration: 2.0 mm" in viewer.metrics_text(T - 1)
    finally:
        viewer.stop()
