"""MuJoCo's renderer on an evaluation MCAP: the filmstrip and the video of a rollout beside its
reference (issue 59), and a clear error where no OpenGL context can be made."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from PIL import Image

from humimic.errors import InputError
from humimic.motion import motion_from_qpos
from humimic.robots import get_robot, nominal_model
from humimic.tracking.evaluate import _Trace, write_eval_mcap
from humimic.viewer.film import HEIGHT, WIDTH, render_eval_film


def _eval_mcap(path: Path, raise_arm: float) -> Path:
    """Ten frames of the G1 standing; the "rollout" the same with the left shoulder pitched
    by ``raise_arm`` [rad]."""
    model = nominal_model(get_robot("g1"))
    q = np.tile(model.key_qpos[0], (10, 1))
    motion = motion_from_qpos(model, q, 50.0, "g1")
    adr = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT,
                                              "left_shoulder_pitch_joint")]  # fmt: skip
    rolled = q.copy()
    rolled[:, adr] -= raise_arm
    trace = _Trace(qpos=list(rolled), qvel=[np.zeros(model.nv)] * 10,
                   targets=[np.zeros(model.nu)] * 10, reward=[0.0] * 10)  # fmt: skip
    write_eval_mcap(path, motion, tuple(motion.joint_names), 0.02, trace, trace, {})
    return path


def _halves(img: Image.Image) -> tuple[np.ndarray, np.ndarray]:
    """The rollout's and the reference's views of a video frame, without their captions."""
    a = np.asarray(img.convert("RGB"), dtype=float)
    return a[22:, :WIDTH], a[22:, WIDTH:]


def test_the_rollout_is_rendered_beside_its_reference(tmp_path: Path) -> None:
    same = _eval_mcap(tmp_path / "same.mcap", 0.0)
    png, gif = tmp_path / "film.png", tmp_path / "film.gif"
    render_eval_film(same, png, gif)
    strip = Image.open(png)
    assert strip.size == (6 * WIDTH, 2 * (HEIGHT + 22))  # Six key frames, two rows.
    video = Image.open(gif)
    frames = getattr(video, "n_frames", 1)
    assert frames == 2 and video.size == (2 * WIDTH, HEIGHT + 22)  # 10 fps of 50.
    rollout, reference = _halves(video)
    assert np.abs(rollout - reference).mean() < 1.0  # The same pose: the same picture.
    assert rollout.std() > 10.0  # Not a blank image: a robot on a floor.
    raised = _eval_mcap(tmp_path / "raised.mcap", 1.2)
    render_eval_film(raised, png, gif)
    rollout, reference = _halves(Image.open(gif))
    assert np.abs(rollout - reference).mean() > 1.0  # The raised arm shows.


def test_no_opengl_context_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mcap = _eval_mcap(tmp_path / "e.mcap", 0.0)
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    with pytest.raises(InputError, match=r"rendering .*e\.mcap failed: .*MUJOCO_GL"):
        render_eval_film(mcap, tmp_path / "f.png", None)
    assert not (tmp_path / "f.png").exists()
