"""One tracking env over a library of clips: one table, episodes that end at their own clip's
end, start frames drawn by each clip's failures (issue 59). Tiny env counts."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from rsl_rl.runners import OnPolicyRunner

from humimic.errors import InputError
from humimic.motion import Motion, motion_from_qpos
from humimic.tracking.command import MotionCommand
from humimic.tracking.config import AdaptiveSampling, g1_tracking
from humimic.tracking.env import TrackingEnv, tracking_model
from humimic.tracking.rsl import PpoConfig, train_cfg


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return tracking_model(g1_tracking("none"))


def _clip(model: mujoco.MjModel, frames: int, joint: str, amplitude: float) -> Motion:
    """The G1 in its home pose swinging one joint: ``frames`` frames at 50 fps."""
    q = np.tile(model.key_qpos[0], (frames, 1))
    adr = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)]
    q[:, adr] += amplitude * np.sin(2 * np.pi * np.arange(frames) / 50.0)
    return motion_from_qpos(model, q, 50.0, "g1")


@pytest.fixture(scope="module")
def clips(model: mujoco.MjModel) -> tuple[Motion, Motion]:
    return (_clip(model, 120, "left_shoulder_pitch_joint", 0.3),
            _clip(model, 45, "right_elbow_joint", 0.4))  # fmt: skip


def _command(clips: tuple[Motion, ...], **adaptive) -> MotionCommand:
    cfg = replace(g1_tracking("none"), action_base="default",
                  adaptive=AdaptiveSampling(**adaptive))  # fmt: skip
    names = list(clips[0].joint_names) if clips else []  # The env's joints: the motion's.
    return MotionCommand(cfg, clips, names, "pelvis", torch.device("cpu"))


def test_a_library_is_one_table_where_every_frame_knows_its_clip(clips) -> None:
    c = _command(clips)
    a, b = clips
    assert c.num_frames == a.num_frames + b.num_frames == 165
    assert c.clip_start.tolist() == [0, 120] and c.clip_length.tolist() == [120, 45]
    assert c.first[[0, 119, 120, 164]].tolist() == [0, 0, 120, 120]
    assert c.last[[0, 119, 120, 164]].tolist() == [119, 119, 164, 164]
    # The packed table is each clip's own, one after the other.
    alone = _command((b,))
    np.testing.assert_array_equal(c.packed[120:].numpy(), alone.packed.numpy())
    np.testing.assert_array_equal(c.start["joint_pos"][120:], alone.start["joint_pos"])
    # Bins: 1 s each, per clip (2.4 s -> 3 bins, 0.9 s -> 1 bin).
    assert c.bin_count == 3 + 1
    # Without adaptive sampling, any frame but a clip's last, uniformly.
    plain = _command(clips, enabled=False)
    frames = plain.sample_frames(20000, torch.Generator().manual_seed(0))
    assert not np.isin(frames.numpy(), [119, 164]).any()
    share_b = float((frames >= 120).float().mean())
    assert share_b == pytest.approx(44 / 163, abs=0.02)


def test_a_clip_that_always_fails_is_started_more_within_bounds(clips) -> None:
    """Episodes fail only in clip B: its bins' weight grows, and clip A keeps the floor every
    bin has (``uniform_ratio`` over the number of bins), so its episodes still start."""
    c = _command(clips, alpha=0.2)
    c.weights.copy_(c._compute_weights())
    frames_b = torch.arange(120, 164)
    for _ in range(50):
        c.fold_failures(frames_b, torch.ones(len(frames_b)))
    w = c.weights
    on_b = float(w[3:].sum())
    assert on_b > 0.9
    floor = c.cfg.adaptive.uniform_ratio / c.bin_count
    np.testing.assert_allclose(w[:3].numpy() * float((c.bin_failed + floor).sum()), floor,
                               rtol=1e-5)  # fmt: skip
    drawn = c.sample_frames(20000, torch.Generator().manual_seed(1))
    in_b = float((drawn >= 120).float().mean())
    assert in_b == pytest.approx(on_b, abs=0.02)
    assert float((drawn < 120).float().mean()) > 0 and int(drawn.max()) <= 163
    assert not np.isin(drawn.numpy(), [119, 164]).any()


def test_failures_are_smoothed_within_their_clip(clips) -> None:
    """The kernel moves a failure's weight to the bins before it (a fall is caused earlier),
    never into the previous clip."""
    c = _command(clips, alpha=1.0)
    c.fold_failures(torch.tensor([120]), torch.ones(1))  # Clip B's first (and only) bin.
    floor = c.cfg.adaptive.uniform_ratio / c.bin_count
    assert float(c.weights[2]) == pytest.approx(float(c.weights[0]), rel=1e-6)
    assert float(c.weights[3]) > 10 * float(c.weights[2])
    total = float((c.bin_failed + floor).sum())
    assert float(c.weights[2]) == pytest.approx(floor / total, rel=1e-5)


def test_an_episode_ends_at_its_own_clips_end(model: mujoco.MjModel, clips) -> None:
    """Started one frame before their clip's last, every env times out after one step at its
    own clip's last frame, never in the next clip."""
    cfg = replace(g1_tracking("none"), action_base="default", start_frame=118)
    env = TrackingEnv(cfg, list(clips), 16, model=model)
    try:
        starts = env.state.frame.clone()
        assert set(starts.tolist()) == {118, 120 + 43}  # Clip B's 45 frames: its 43rd.
        assert (env.state.last_frame == torch.where(starts < 120, 119, 164)).all()
        _, _, dones, extras = env.step(torch.zeros(16, env.num_actions))
        assert dones.all() and extras["time_outs"].all()
    finally:
        env.close()


def test_a_library_of_clips_of_two_layouts_is_refused(model: mujoco.MjModel, clips) -> None:
    a, b = clips
    other = replace(b, joint_names=tuple(reversed(b.joint_names)), source="b.npz")
    with pytest.raises(InputError, match=r"b\.npz: its joints or bodies differ"):
        _command((a, other))
    with pytest.raises(InputError, match="no clip"):
        _command(())


def test_ppo_trains_two_iterations_on_a_library(
    model: mujoco.MjModel, clips, tmp_path: Path
) -> None:
    cfg = replace(g1_tracking("default"), action_base="default")
    env = TrackingEnv(cfg, list(clips), 4, model=model)
    ppo = PpoConfig(actor_hidden_dims=(32, 32), critic_hidden_dims=(32, 32),
                    num_steps_per_env=4, num_mini_batches=2, num_learning_epochs=1)  # fmt: skip
    try:
        runner = OnPolicyRunner(env, train_cfg(ppo), log_dir=str(tmp_path), device="cpu")
        runner.learn(num_learning_iterations=2, init_at_random_ep_len=True)
        assert sorted(p.name for p in tmp_path.glob("model_*.pt")) == ["model_0.pt", "model_1.pt"]
        assert (env.state.frame <= env.state.last_frame).all()
    finally:
        env.close()


def _train(motion: Path, out: Path, iterations: int, *extra: str) -> list[str]:
    return ["train", "--motion", str(motion), "--out", str(out), "--num-envs", "8",
            "--max-iterations", str(iterations), "--num-steps-per-env", "8", "--dr", "none",
            "--checkpoint-every", "2", "--task.action-base", "default", "--quiet",
            *extra]  # fmt: skip


def test_train_on_a_library_folder_resumes_and_refuses_bad_libraries(
    model: mujoco.MjModel, clips, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from humimic.cli.main import main
    from humimic.motion import save_motion

    lib = tmp_path / "lib"
    lib.mkdir()
    save_motion(clips[0], lib / "a.npz")
    save_motion(clips[1], lib / "b.npz")
    run = tmp_path / "run"
    assert main(_train(lib, run, 2)) == 0
    assert "motion_sha256" in (run / "config.yaml").read_text()
    assert main(_train(lib, run, 3, "--resume")) == 0
    # One policy evaluated on each clip of its library: the per-clip figures are those of an
    # evaluation on that clip alone, the library's the mean over its clips.
    one, every = tmp_path / "one.json", tmp_path / "every.json"
    assert main(["eval", str(run), "--motion", str(lib / "b.npz"), "--episodes", "2",
                 "--out", str(one)]) == 0  # fmt: skip
    assert main(["eval", str(run), "--episodes", "2", "--out", str(every)]) == 0
    printed = capsys.readouterr().out
    assert "a.npz (120 frames)" in printed and "mean over the 2 clips" in printed
    alone, lib_eval = json.loads(one.read_text()), json.loads(every.read_text())
    assert list(lib_eval["clips"]) == ["a.npz", "b.npz"]
    assert lib_eval["clips"]["b.npz"]["policy"] == alone["policy"]
    clip_rows = [c["policy"] for c in lib_eval["clips"].values()]
    mean = np.mean([c["mpjpe_global_mm"] for c in clip_rows])
    assert lib_eval["policy"]["mpjpe_global_mm"] == pytest.approx(mean)
    assert lib_eval["policy"]["episodes"] == 4
    pelvis = np.mean([c["per_body_mm"]["pelvis"] for c in clip_rows])
    assert lib_eval["policy"]["per_body_mm"]["pelvis"] == pytest.approx(pelvis)
    # The field's protocols: a row per clip (the clip's alone), the totals over the library.
    for name in ("beyondmimic", "phc"):
        proto = lib_eval["protocols"][name]
        assert list(proto["per_clip"]) == ["a.npz", "b.npz"] and proto["clips"] == 2
        assert proto["per_clip"]["b.npz"] == alone["protocols"][name]["per_clip"]["b.npz"]
    bm = lib_eval["protocols"]["beyondmimic"]
    assert bm["failed_clips"] == sum(r["failed"] for r in bm["per_clip"].values())
    assert (tmp_path / "every_a.mcap").is_file() and (tmp_path / "every_b.mcap").is_file()
    # A library with a clip the run cannot take: exit 2, and no clip's file is written.
    mixed_eval = tmp_path / "mixed_eval"
    mixed_eval.mkdir()
    save_motion(clips[0], mixed_eval / "a.npz")
    save_motion(replace(clips[1], robot="t1"), mixed_eval / "b.npz")
    bad_out = tmp_path / "bad_eval.json"
    assert main(["eval", str(run), "--motion", str(mixed_eval), "--episodes", "2",
                 "--out", str(bad_out)]) == 2  # fmt: skip
    assert "b.npz: the motion is for robot 't1'" in capsys.readouterr().err
    assert not list(tmp_path.glob("bad_eval*"))
    # A clip changed since: the run's library is not the one it began on.
    save_motion(_clip(model, 30, "left_knee_joint", 0.2), lib / "b.npz")
    assert main(_train(lib, run, 4, "--resume")) == 2
    assert "has changed" in capsys.readouterr().err
    # Bad libraries exit 2 naming what is wrong, and leave no run behind.
    (tmp_path / "empty").mkdir()
    listed = tmp_path / "clips.yaml"
    listed.write_text("- lib/a.npz\n- lib/missing.npz\n")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    save_motion(clips[0], mixed / "a.npz")
    save_motion(replace(clips[1], robot="t1"), mixed / "b.npz")
    for motion, message in ((tmp_path / "empty", "holds no .npz"),
                            (listed, "lists " + str(tmp_path / "lib" / "missing.npz")),
                            (mixed, "b.npz: the motion is for robot 't1', not 'g1'")):  # fmt: skip
        assert main(_train(motion, tmp_path / "bad", 1)) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()


def test_a_library_is_refined_once_in_workers_and_a_clip_that_cannot_be_is_left_out(
    model: mujoco.MjModel, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The default (feedback) base needs refined clips: train refines the library's clips on
    worker processes into the run, reports and leaves out a clip that cannot be refined (two
    frames: refining needs three), and a resume refines nothing again."""
    from humimic.cli.main import main
    from humimic.motion import load_motion, save_motion
    from humimic.tracking.actions import has_stored_controls

    lib = tmp_path / "lib"
    lib.mkdir()
    save_motion(_clip(model, 16, "left_shoulder_pitch_joint", 0.3), lib / "a.npz")
    save_motion(_clip(model, 10, "right_elbow_joint", 0.4), lib / "b.npz")
    save_motion(_clip(model, 2, "left_knee_joint", 0.1), lib / "c.npz")
    run = tmp_path / "run"

    def train(motion: Path, iterations: int, *extra: str) -> list[str]:
        args = _train(motion, run, iterations, *extra)
        del args[args.index("--task.action-base") : args.index("--task.action-base") + 2]
        return args

    assert main(train(lib, 1)) == 0
    out = capsys.readouterr().out
    assert "left out of the run: c (refining failed:" in out and "at least 3" in out
    listing = run / "reference" / "library.yaml"
    assert listing.read_text() == "- a.npz\n- b.npz\n"
    refined = load_motion(run / "reference" / "a.npz")
    assert has_stored_controls(refined) and refined.fps == 50.0
    assert "motion: reference/library.yaml" in (run / "config.yaml").read_text()
    stamp = (run / "reference" / "a.npz").stat().st_mtime_ns
    assert main(train(lib, 2, "--resume")) == 0  # Refines nothing again.
    assert (run / "reference" / "a.npz").stat().st_mtime_ns == stamp
    assert main(["eval", str(run), "--episodes", "1"]) == 0
    assert "mean over the 2 clips" in capsys.readouterr().out
    # A clip changed since: refused before any refining.
    save_motion(_clip(model, 12, "right_elbow_joint", 0.2), lib / "b.npz")
    assert main(train(lib, 3, "--resume")) == 2
    assert "not trained on a refinement of" in capsys.readouterr().err
    # No clip that can be refined: exit 2, no run left behind.
    only = tmp_path / "only"
    only.mkdir()
    save_motion(_clip(model, 2, "left_knee_joint", 0.1), only / "c.npz")
    run = tmp_path / "bad"
    assert main(train(only, 1)) == 2
    assert "no clip of the library could be refined" in capsys.readouterr().err
    assert not run.exists()


def test_clip_weights_of_a_yaml_library(clips, tmp_path: Path) -> None:
    """``- {file: b.npz, weight: 3}``: every frame of b three times as likely to start an
    episode (uniform and adaptive sampling); a library without weights hashes as before."""
    from humimic.motion import save_motion
    from humimic.tracking.runs import motion_sha256
    from humimic.tracking.task import library_entries, load_references

    folder = tmp_path / "lib"
    folder.mkdir()
    save_motion(clips[0], folder / "a.npz")
    save_motion(clips[1], folder / "b.npz")
    weighted, plain = tmp_path / "w.yaml", tmp_path / "p.yaml"
    weighted.write_text("- lib/a.npz\n- {file: lib/b.npz, weight: 3}\n")
    plain.write_text("- lib/a.npz\n- lib/b.npz\n")
    assert library_entries(weighted) == [(folder / "a.npz", 1.0), (folder / "b.npz", 3.0)]
    assert motion_sha256(plain) == motion_sha256(folder) != motion_sha256(weighted)
    refs = tuple(load_references(weighted, "g1", 50.0))
    uniform = _command(refs, enabled=False)
    frames = uniform.sample_frames(40000, torch.Generator().manual_seed(2))
    # 119 startable frames of a at weight 1, 44 of b at weight 3.
    assert float((frames >= 120).float().mean()) == pytest.approx(3 * 44 / (119 + 3 * 44),
                                                                   abs=0.01)  # fmt: skip
    adaptive = _command(refs)
    adaptive.weights.copy_(adaptive._compute_weights())
    # No failure yet: a's three bins and b's one weigh alike but for the weight.
    assert float(adaptive.weights[3]) == pytest.approx(3 / (3 + 3), rel=1e-5)
    for bad in ("- {file: lib/a.npz, weight: -1}\n", "- {file: lib/a.npz, weight: x}\n",
                "- {name: lib/a.npz}\n", "- {file: lib/a.npz, weight: .nan}\n"):  # fmt: skip
        weighted.write_text(bad)
        with pytest.raises(InputError, match=str(weighted.name)):
            library_entries(weighted)
