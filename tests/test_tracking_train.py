"""``humimic train`` and ``humimic eval``: run folders, crash and resume, NaN, evaluation.

Tiny budgets (8 envs, a few iterations of 8 steps): these tests check the machinery, not what
the policy learns.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from humimic.cli.main import main
from humimic.motion import load_motion


def _train_args(motion: Path, out: Path, iterations: int, *extra: str) -> list[str]:
    return ["train", "--motion", str(motion), "--out", str(out), "--num-envs", "8",
            "--max-iterations", str(iterations), "--num-steps-per-env", "8", "--dr", "none",
            "--checkpoint-every", "2", "--task.action-base", "default", "--quiet",
            *extra]  # fmt: skip


def test_reference_is_resampled_to_the_policy_rate(motion_file: Path) -> None:
    from humimic.tracking.task import load_reference

    src = load_motion(motion_file)
    ref = load_reference(motion_file, "g1", 50.0)
    assert ref.fps == 50.0
    assert (ref.num_frames - 1) / 50.0 == pytest.approx((src.num_frames - 1) / 30.0, abs=0.02)
    # Same pose at the same time (t = 1 s is frame 30 of the source, 50 of the reference).
    np.testing.assert_allclose(ref.qpos[50], src.qpos[30], atol=1e-9)
    assert ref.info is not None and ref.info["resampled_from_fps"] == 30.0


def test_train_writes_a_run_and_refuses_to_overwrite_it(
    motion_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert main(_train_args(motion_file, out, 3)) == 0
    names = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert names == ["model_000002.pt", "model_000003.pt"]
    blob = torch.load(out / "checkpoints" / "model_000003.pt", weights_only=True)
    assert blob["iter"] == 3 and "actor_state_dict" in blob
    rows = (out / "progress.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("iteration,")
    # What each update did, mini-batch by mini-batch: rsl_rl's adaptive schedule computes a
    # KL on every one (NaN here would mean the probe no longer sees it).
    table = [dict(zip(rows[0].split(","), r.split(","), strict=True)) for r in rows[1:]]
    for r in table:
        kl, lr_mean, lr_max = float(r["kl"]), float(r["lr_mean"]), float(r["lr_max"])
        assert kl > 0.0 and 1e-5 <= lr_mean <= lr_max <= 1e-2
        assert lr_max >= float(r["learning_rate"])
    cfg = (out / "config.yaml").read_text()
    assert "settings:" in cfg and "tracking:" in cfg and "ppo:" in cfg
    assert "humimic.tracking.rewards:" in cfg  # Reward functions by import path.
    before = (out / "progress.csv").read_text()
    assert main(_train_args(motion_file, out, 5)) == 2
    assert "--resume" in capsys.readouterr().err
    assert (out / "progress.csv").read_text() == before
    # A resume with other physics is refused, naming the difference.
    args = _train_args(motion_file, out, 5, "--resume")
    args[args.index("--dr") + 1] = "default"
    assert main(args) == 2
    assert "dr" in capsys.readouterr().err


def test_task_and_ppo_settings_are_recorded_and_kept_on_resume(
    motion_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--task.*`` and ``--ppo.*`` change the frozen configs; config.yaml records them, the
    networks have the sizes asked for, a resume without them is refused naming the setting,
    and the commands that rebuild the run's task (eval, export) use them."""
    import yaml

    from humimic.tracking.runs import read_run_settings
    from humimic.tracking.task import task_config

    out = tmp_path / "run"
    tuned = ["--task.action-scale", "0.5", "--task.reward-weights", "body_pos", "2.0",
             "--task.reward-stds", "anchor_pos", "0.3", "--task.feedback-root-cost", "10",
             "--ppo.learning-rate", "3e-4", "--ppo.actor-hidden-dims", "32", "16"]  # fmt: skip
    assert main(_train_args(motion_file, out, 1, *tuned)) == 0
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["schema"] == 2  # RUN_SCHEMA: the layout it was written in.
    assert cfg["settings"]["task"]["action_scale"] == 0.5
    assert cfg["settings"]["task"]["reward_weights"] == {"body_pos": 2.0}
    assert cfg["settings"]["task"]["reward_stds"] == {"anchor_pos": 0.3}
    assert cfg["tracking"]["rewards"]["anchor_pos"]["params"]["std"] == 0.3
    assert cfg["tracking"]["feedback"]["base_position"] == 10.0
    assert cfg["settings"]["ppo"]["learning_rate"] == 3e-4
    assert cfg["tracking"]["action_scale"] == 0.5
    assert cfg["tracking"]["rewards"]["body_pos"]["weight"] == 2.0
    assert cfg["tracking"]["rewards"]["body_ori"]["weight"] == 1.0  # The others as they were.
    assert cfg["ppo"]["algorithm"]["learning_rate"] == 3e-4
    assert cfg["ppo"]["actor"]["hidden_dims"] == [32, 16]
    blob = torch.load(out / "checkpoints" / "model_000001.pt", weights_only=True)
    shapes = [v.shape for k, v in blob["actor_state_dict"].items() if k.endswith("weight")]
    assert [s[0] for s in shapes[:2]] == [32, 16]
    settings = read_run_settings(out)
    assert settings.task.action_scale == 0.5 and settings.ppo.actor_hidden_dims == (32, 16)
    task = task_config("g1", "none", 0, settings=settings.task)
    assert task.action_scale == 0.5 and task.rewards["body_pos"].weight == 2.0
    assert task.rewards["anchor_pos"].params["std"] == 0.3
    assert task.rewards["body_pos"].params["std"] == 0.3  # The others as they were.
    assert task.feedback.base_position == 10.0
    capsys.readouterr()
    assert main(_train_args(motion_file, out, 2, "--resume")) == 2
    err = capsys.readouterr().err
    assert "task.action_scale" in err and "ppo.learning_rate" in err
    assert main(_train_args(motion_file, out, 2, "--resume", *tuned)) == 0
    assert main(["eval", str(out), "--episodes", "2"]) == 0
    assert main(["export", str(out), "--out", str(tmp_path / "p.onnx")]) == 0
    # Bad values are refused before anything is written, naming the flag.
    for bad, named in ((["--task.action-scale", "0"], "--task.action-scale"),
                       (["--task.reward-weights", "nope", "1"], "nope"),
                       (["--task.reward-stds", "action_rate_l2", "1"], "action_rate_l2"),
                       (["--task.reward-stds", "anchor_pos", "0"], "--task.reward-stds"),
                       (["--task.feedback-root-cost", "-1"], "--task.feedback-root-cost"),
                       (["--task.feedback-delay", "-1"], "--task.feedback-delay"),
                       (["--task.feedback-delay", "1", "--task.action-base", "reference"],
                        "--task.feedback-delay"),
                       (["--ppo.gamma", "1.5"], "--ppo.gamma")):  # fmt: skip
        assert main(_train_args(motion_file, tmp_path / "bad", 1, *bad)) == 2
        assert named in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()


def test_run_records_the_feedback_it_trains_with_and_older_runs_read_as_trained() -> None:
    """A run records the LQR root cost its task resolves to, so a later change of the default
    does not change what eval rebuilds; a config.yaml written before the setting existed reads
    as the root cost and anchor reward of then (10; std 0.3, weight 0.5): the upgrade of a
    schema-1 config.yaml (no ``schema`` key), the one place older run folders are read."""
    from dataclasses import asdict

    from humimic.configs.runs import TrainSettings
    from humimic.tracking.config import tracking_task
    from humimic.tracking.runs import (
        RUN_SCHEMA,
        _settings_from,
        resolved_settings,
        upgrade_run_config,
    )
    from humimic.tracking.task import task_config

    def read_v1(settings: dict) -> TrainSettings:
        config = upgrade_run_config({"settings": settings}, Path("run/config.yaml"))
        assert config["schema"] == RUN_SCHEMA
        return _settings_from(config["settings"])

    r = resolved_settings(TrainSettings(motion=Path("m.npz"), out=Path("run")))
    assert r.task.feedback_root_cost == tracking_task("g1").feedback.base_position
    old = asdict(r)
    del old["task"]["feedback_root_cost"], old["task"]["reward_stds"]
    old["task"]["reward_weights"] = {"body_pos": 2.0}
    read = read_v1(old).task
    assert read.feedback_root_cost == 10.0
    task = task_config("g1", "none", 0, settings=read)
    assert task.feedback.base_position == 10.0
    assert task.rewards["anchor_pos"].params["std"] == 0.3
    assert task.rewards["anchor_pos"].weight == 0.5 and task.rewards["body_pos"].weight == 2.0
    # The LQR's design delay: recorded as resolved, and none for a run recorded before it.
    assert r.task.feedback_delay == 0
    s = TrainSettings(motion=Path("m.npz"), out=Path("run"))
    two = resolved_settings(replace(s, task=replace(s.task, feedback_delay=2)))
    assert task_config("g1", "none", 0, settings=two.task).feedback_delay == 2
    assert _settings_from(asdict(two)).task.feedback_delay == 2
    before = asdict(two)
    del before["task"]["feedback_delay"]
    assert read_v1(before).task.feedback_delay == 0


def test_run_config_schema_is_recorded_and_a_newer_one_refused(tmp_path: Path) -> None:
    """config.yaml records its schema; one from a newer humimic, or a schema that is not a
    whole number, is refused naming the file (not read as if it were this one's); a current
    one is read as written (no schema-1 defaults over its fields)."""
    from dataclasses import asdict

    from humimic.configs.runs import TrainSettings
    from humimic.errors import InputError
    from humimic.tracking.runs import RUN_SCHEMA, upgrade_run_config

    where = tmp_path / "config.yaml"
    for bad, match in ((RUN_SCHEMA + 1, "newer humimic"), ("2", "whole number"), (True, "whole")):
        with pytest.raises(InputError, match=match) as e:
            upgrade_run_config({"schema": bad, "settings": {}}, where)
        assert str(where) in str(e.value)
    settings = asdict(TrainSettings(motion=Path("m.npz"), out=Path("run")))
    settings["task"]["action_base"] = None
    kept = upgrade_run_config({"schema": RUN_SCHEMA, "settings": settings}, where)
    assert kept["settings"]["task"]["action_base"] is None  # Schema 2: not filled in.
    old = upgrade_run_config(
        {"settings": asdict(TrainSettings(motion=Path("m.npz"), out=Path("r")))}, where
    )
    assert old["settings"]["task"]["action_base"] == "default"


@pytest.mark.parametrize(
    ("variant", "actor_dim"),
    [("robust", 160), ("asymmetric", 160 + 5 * 160), ("teacher", None)],
)
def test_each_variant_trains(
    motion_file: Path, tmp_path: Path, variant: str, actor_dim: int | None
) -> None:
    """Each variant trains, records itself, and gives its actor the variant's observations;
    a teacher (which reads simulator parameters) is not exported."""
    out = tmp_path / variant
    assert main(_train_args(motion_file, out, 1, "--variant", variant)) == 0
    cfg = (out / "config.yaml").read_text()
    assert f"variant: {variant}" in cfg
    blob = torch.load(out / "checkpoints" / "model_000001.pt", weights_only=True)
    first = next(v for k, v in blob["actor_state_dict"].items() if k.endswith("0.weight"))
    critic_first = next(v for k, v in blob["critic_state_dict"].items() if k.endswith("0.weight"))
    if variant == "teacher":
        assert first.shape[1] > 160  # policy + physics parameters e
        assert main(["export", str(out), "--out", str(tmp_path / "t.onnx")]) == 2
        assert not (tmp_path / "t.onnx").exists()
    else:
        assert first.shape[1] == actor_dim
    # Only the robust critic is limited to deployable observations.
    assert (critic_first.shape[1] == 160) == (variant == "robust")


def test_fine_tune_from_a_run_on_a_physics_file(motion_file: Path, tmp_path: Path) -> None:
    """``--init-from`` starts from another run's weights (its observation statistics carry
    on); ``--physics`` is recorded; networks that do not fit are refused, nothing written."""
    base = tmp_path / "base"
    assert main(_train_args(motion_file, base, 2)) == 0
    tuned = tmp_path / "tuned"
    args = _train_args(motion_file, tuned, 1, "--init-from", str(base), "--physics", "backpack",
                       "--ppo.learning-rate", "3e-05", "--ppo.schedule", "fixed")  # fmt: skip
    assert main(args) == 0
    assert "physics: backpack" in (tuned / "config.yaml").read_text()
    # The run's learning rate, not the one in the checkpoint's optimizer state.
    with (tuned / "progress.csv").open() as f:
        assert float(next(csv.DictReader(f))["lr_mean"]) == pytest.approx(3e-5)

    def count(run: Path, it: int) -> float:
        blob = torch.load(run / "checkpoints" / f"model_{it:06d}.pt", weights_only=True)
        return float(next(v for k, v in blob["actor_state_dict"].items() if k.endswith("count")))

    fresh = tmp_path / "fresh"
    assert main(_train_args(motion_file, fresh, 1)) == 0
    assert count(tuned, 1) == pytest.approx(count(base, 2) + count(fresh, 1))
    bad = tmp_path / "bad"
    assert main(_train_args(motion_file, bad, 1, "--init-from", str(tuned), "--variant",
                            "teacher")) == 2  # fmt: skip
    assert not bad.exists()


def test_teacher_distills_into_a_student(
    motion_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A teacher checkpoint loads into rsl_rl's distillation runner (its actor becomes the
    teacher, weight for weight), the student's imitation loss falls, and the student run
    evaluates and exports like any run."""
    teacher = tmp_path / "teacher"
    assert main(_train_args(motion_file, teacher, 2, "--variant", "teacher")) == 0
    student = tmp_path / "student"
    args = ["distill", "--teacher", str(teacher), "--out", str(student), "--num-envs", "8",
            "--max-iterations", "12", "--checkpoint-every", "6", "--quiet"]  # fmt: skip
    assert main(args) == 0
    t_blob = torch.load(teacher / "checkpoints" / "model_000002.pt", weights_only=True)
    s_blob = torch.load(student / "checkpoints" / "model_000012.pt", weights_only=True)
    for k, v in t_blob["actor_state_dict"].items():
        torch.testing.assert_close(s_blob["teacher_state_dict"][k], v)
    first = next(v for k, v in s_blob["student_state_dict"].items() if k.endswith("0.weight"))
    assert first.shape[1] == 160 + 5 * 160  # policy + proprio_history: no physics parameters
    losses = [float(r.split(",")[header.index("loss_behavior")])
              for header in [(student / "progress.csv").read_text().splitlines()[0].split(",")]
              for r in (student / "progress.csv").read_text().splitlines()[1:]]  # fmt: skip
    assert len(losses) == 12
    assert np.mean(losses[-3:]) < 0.6 * np.mean(losses[:3])
    assert main(args) == 2  # The folder holds a run: --resume or another --out.
    assert main(["eval", str(student), "--episodes", "2"]) == 0
    assert main(["export", str(student), "--out", str(tmp_path / "s.onnx")]) == 0
    assert main(["distill", "--teacher", str(student), "--out", str(tmp_path / "x")]) == 2
    # PPO goes on from the student: its actor (the variant whose actor observes its groups),
    # the noise at --ppo.init-std, a fresh critic that trains alone first.
    tuned, bad = tmp_path / "tuned", tmp_path / "bad"

    def from_student(out: Path, variant: str, base: str = "default") -> list[str]:
        args = _train_args(motion_file, out, 1, "--init-from", str(student), "--variant",
                           variant, "--ppo.critic-warmup-iterations", "1", "--ppo.init-std",
                           "0.2")  # fmt: skip
        args[args.index("--task.action-base") + 1] = base
        return args

    assert main(from_student(tuned, "asymmetric")) == 0
    actor = torch.load(tuned / "checkpoints" / "model_000001.pt", weights_only=True)
    actor = actor["actor_state_dict"]
    for k, v in s_blob["student_state_dict"].items():
        if k.startswith("mlp."):
            torch.testing.assert_close(actor[k], v)
    torch.testing.assert_close(actor["distribution.std_param"], torch.full((29,), 0.2))
    # Another variant's actor, or another action base: refused, nothing written.
    capsys.readouterr()
    assert main(from_student(bad, "beyondmimic")) == 2
    assert "--variant asymmetric" in capsys.readouterr().err
    assert main(from_student(bad, "asymmetric", "reference")) == 2
    assert "'default' action base" in capsys.readouterr().err
    assert not bad.exists()
    # A checkpoint of another variant does not fit the teacher's actor: refused, nothing written.
    robust = tmp_path / "robust"
    assert main(_train_args(motion_file, robust, 1, "--variant", "robust")) == 0
    bad = ["distill", "--teacher", str(teacher), "--out", str(tmp_path / "bad"), "--num-envs",
           "8", "--teacher-checkpoint", str(robust / "checkpoints" / "model_000001.pt")]  # fmt: skip
    assert main(bad) == 2
    assert not (tmp_path / "bad" / "config.yaml").exists()
    # A student around stored targets the teacher's kinematic motion does not have: refused.
    moved = ["distill", "--teacher", str(teacher), "--out", str(tmp_path / "ff"), "--num-envs",
             "8", "--student-base", "feedforward", "--quiet"]  # fmt: skip
    assert main(moved) == 2
    assert not (tmp_path / "ff").exists()
    gru = tmp_path / "gru"
    gru_args = ["distill", "--teacher", str(teacher), "--out", str(gru), "--student", "gru",
                "--num-envs", "8", "--max-iterations", "2", "--quiet"]  # fmt: skip
    assert main(gru_args) == 0
    assert main(["eval", str(gru), "--episodes", "2"]) == 0
    # The recurrent student exports with its GRU state as input and output; fed back step by
    # step, ONNX and torch agree.
    from onnx.reference import ReferenceEvaluator

    from humimic.tracking.export import load_policy_runner

    path = tmp_path / "g.onnx"
    assert main(["export", str(gru), "--out", str(path)]) == 0
    runner, env, _ = load_policy_runner(gru, None)
    try:
        policy = runner.get_inference_policy(device="cpu")
        obs = env.get_observations()
        seq = [obs["policy"] + 0.2 * k for k in range(3)]
        with torch.inference_mode():
            expected = [policy(obs.clone().update({"policy": x})).numpy() for x in seq]
    finally:
        env.close()
    onnx_policy = ReferenceEvaluator(str(path))
    h = np.zeros((1, 1, 256), dtype=np.float32)
    for x, want in zip(seq, expected, strict=True):
        got, h = onnx_policy.run(None, {"obs": x.numpy(), "h_in": h})
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-5)
    assert not np.allclose(expected[0], expected[2])  # The state and the inputs matter.


def test_bad_input_exits_2(motion_file: Path, tmp_path: Path) -> None:
    assert main(_train_args(tmp_path / "missing.npz", tmp_path / "a", 1)) == 2
    assert main(_train_args(motion_file, tmp_path / "b", 0)) == 2
    args = _train_args(motion_file, tmp_path / "c", 1)
    args[args.index("--dr") + 1] = "nonsense"
    assert main(args) == 2
    assert not (tmp_path / "a").exists() and not (tmp_path / "c" / "config.yaml").exists()
    assert main(["eval", str(tmp_path / "nothing")]) == 2
    warm = [*_train_args(motion_file, tmp_path / "d", 1), "--ppo.critic-warmup-iterations", "-1"]
    assert main(warm) == 2 and not (tmp_path / "d").exists()


def test_failed_compile_exits_1_and_leaves_no_run_folder(
    motion_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(torch, "compile", broken)
    out = tmp_path / "run"
    assert main([*_train_args(motion_file, out, 1), "--compile"]) == 1
    assert not out.exists()


def test_kill_9_then_resume_loses_nothing_beyond_the_last_checkpoint(
    motion_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "humimic.cli.main",
           *_train_args(motion_file, out, 400)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            ckpts = list((out / "checkpoints").glob("model_*.pt")) if out.exists() else []
            if len(ckpts) >= 2:
                break
            time.sleep(0.2)
        else:
            pytest.fail("no checkpoint within 120 s")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = max(int(p.stem.split("_")[1]) for p in (out / "checkpoints").glob("model_*.pt"))
    # A damaged newer file (a write cut short elsewhere) is skipped, not trusted.
    (out / "checkpoints" / f"model_{done + 1:06d}.pt").write_bytes(b"PK\x03\x04 cut short")
    assert main([*_train_args(motion_file, out, done + 2), "--resume"]) == 0
    rows = [line.split(",")[0] for line in (out / "progress.csv").read_text().splitlines()[1:]]
    iterations = [int(r) for r in rows]
    assert iterations[-2:] == [done + 1, done + 2]  # Continued right after the checkpoint.
    blob = torch.load(out / "checkpoints" / f"model_{done + 2:06d}.pt", weights_only=True)
    assert blob["iter"] == done + 2


def test_nan_stops_training_with_a_clear_error(
    motion_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    import humimic.tracking.train as train_mod
    from humimic.configs.runs import TaskSettings
    from humimic.tracking.config import TermConfig

    calls = {"n": 0}

    def poisoned(env, **_) -> torch.Tensor:
        calls["n"] += 1
        value = torch.zeros(env.num_envs, device=env.device)
        return value + (float("nan") if calls["n"] > 20 else 0.0)

    original = train_mod.task_config

    def task_config(robot: str, dr: str, seed: int, physics: str | None = None,
                    settings: TaskSettings | None = None):  # fmt: skip
        cfg = original(robot, dr, seed, physics, settings)
        rewards = {**cfg.rewards, "poison": TermConfig(func=poisoned, weight=1.0)}
        return replace(cfg, rewards=rewards)

    monkeypatch.setattr(train_mod, "task_config", task_config)
    out = tmp_path / "run"
    assert main(_train_args(motion_file, out, 10)) == 1
    err = capsys.readouterr().err
    assert "diverged" in err and "NaN" in err
    ckpts = sorted((out / "checkpoints").glob("model_*.pt"))
    for p in ckpts:  # Whatever was saved before the NaN loads.
        torch.load(p, weights_only=True)


def test_eval_reports_policy_and_open_loop(motion_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(_train_args(motion_file, out, 2)) == 0
    result_path = tmp_path / "eval.json"
    assert main(["eval", str(out), "--episodes", "3", "--out", str(result_path)]) == 0
    r = json.loads(result_path.read_text())
    assert r["iterations"] == 2 and r["dr"] == "none"
    for name in ("policy", "open_loop"):
        m = r[name]
        assert m["episodes"] == 3 and 0.0 <= m["success_rate"] <= 1.0
        assert 0 < m["mpjpe_global_mm"] < 2000 and 0 < m["mpjpe_root_mm"] < 2000
        assert m["joint_error_rad"] >= 0 and m["mean_steps"] >= 1
        assert set(m["per_body_mm"]) >= {"pelvis", "torso_link"}
    png = tmp_path / "eval_failures.png"
    assert r["failures_png"] == str(png) and png.read_bytes()[:4] == b"\x89PNG"
    for name in ("policy", "open_loop"):
        m = r[name]
        assert len(m["fail_steps"]) == round((1 - m["success_rate"]) * m["episodes"])
        assert all(0 <= k < r["frames"] for k in m["fail_steps"])
    # The open loop replays the reference exactly in its first step: the first joint error
    # is small, so the clip's reference and the env agree on joint order.
    assert r["open_loop"]["joint_error_rad"] < 0.5

    # Per episode, beside the metrics: the DR draw it ran under and whether it failed.
    from humimic.configs.jobs import EvalSettings
    from humimic.tracking.evaluate import run_evaluation

    ev = run_evaluation(EvalSettings(run=out, episodes=6, dr="default"), open_loop=False,
                        traces=6)  # fmt: skip
    e, failed = ev.episodes["physics_e"], ev.episodes["failed"]
    # Where each failed episode fell: the steps it lived, as its own trace counts them.
    lived = sorted(len(tr.qpos) - 1 for tr, f in zip(ev.policy_traces, failed, strict=True) if f)
    assert ev.results["policy"]["fail_steps"] == lived
    assert e.shape[0] == 6 and failed.shape == (6,) and failed.dtype == bool
    assert e.shape[1] == ev.param_layout["action_delay"].stop
    assert 1.0 - failed.mean() == pytest.approx(ev.results["policy"]["success_rate"])
    friction = e[:, ev.param_layout["friction"]]
    assert np.abs(friction).max() <= 1.0 and friction.std() > 0.05  # Six different floors.
    # Each episode recorded, from the first frame exactly or (--start-noise) about it.
    for noise in (False, True):
        ev = run_evaluation(EvalSettings(run=out, episodes=3, start_noise=noise),
                            open_loop=False, traces=3)  # fmt: skip
        firsts = np.stack([t.qpos[0] for t in ev.policy_traces])
        assert [t.env for t in ev.policy_traces] == [0, 1, 2]
        assert (np.ptp(firsts, axis=0).max() > 1e-3) == noise
        assert ev.results["start_noise"] == noise

    # The protocols' play (nominal, no noise, no failure terminations) is the policy's first
    # episode, step by step until that one ends: checked by MuJoCo's forward kinematics of
    # the recorded qpos, not the env's state. The env's body read-outs are sensors, which
    # mj_step evaluates before its last integration: they lag the qpos by one physics step
    # (5 ms of 20), so the check interpolates that far back between control steps.
    import mujoco

    from humimic.tracking.config import g1_tracking
    from humimic.tracking.env import tracking_model
    from humimic.tracking.protocols import judge

    ev = run_evaluation(EvalSettings(run=out, episodes=1), open_loop=False)
    play, qpos = ev.protocol_play, np.stack(ev.policy.qpos)
    # Frames 1 to the one before the last (the last ends the episode, as in the metrics).
    assert play is not None and play.steps == r["frames"] - 2 >= len(qpos) - 1
    cfg = g1_tracking("none")
    model = tracking_model(cfg)
    data = mujoco.MjData(model)
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in cfg.body_names]
    anchor = ids[cfg.body_names.index(cfg.anchor_body)]
    fk, quat = [], []
    for k in range(len(qpos)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        fk.append(data.xpos[ids].copy())
        quat.append(data.xquat[anchor].copy())
    fk, quat = np.array(fk), np.array(quat)
    lagged = fk[1:] - (fk[1:] - fk[:-1]) / cfg.decimation
    n = len(qpos) - 1
    np.testing.assert_allclose(play.body_pos[:n], lagged, atol=5e-4)
    assert np.abs(play.body_pos[:n] - fk[1:]).max() > 1e-3  # The lag is real.
    tilt = np.abs(np.einsum("ki,ki->k", play.anchor_quat[:n], quat[1:]))
    assert tilt.min() > 1 - 1e-4  # The same anchor orientation to within a small angle.
    clip = Path(r["motion"]).name
    assert r["protocols"]["phc"]["per_clip"] == {clip: judge(play)["phc"]}
    assert r["protocols"]["beyondmimic"]["clips"] == 1

    # The first episode, beside the JSON, with the reference: what `humimic view` plays.
    from humimic.formats.mcap import qpos_from_log, read_mcap
    from humimic.pipeline.files import load_rollout, read_any_motion

    mcap = tmp_path / "eval.mcap"
    assert r["mcap"] == str(mcap)
    ref = read_any_motion(mcap)
    assert ref.fps == 50.0 and ref.joint_names[0] == "left_hip_pitch_joint"
    log = read_mcap(mcap)
    times, qpos = qpos_from_log(log, ref.joint_names)
    # No reset noise, nominal physics: all episodes are the same, and the first state is the
    # reference's first frame (joints clamped into the soft limits: the straight knees move).
    assert len(times) == round(r["policy"]["mean_steps"]) + 1
    np.testing.assert_allclose(qpos[0, :7], ref.qpos[0, :7], atol=1e-6)
    assert np.abs(qpos[0, 7:] - ref.qpos[0, 7:]).max() < 0.07
    assert np.all(np.diff(times) == 20_000_000)
    assert len(log.topic("/open_loop/qpos")) == round(r["open_loop"]["mean_steps"]) + 1
    assert len(log.topic("/joint_commands")) == len(times)
    assert json.loads(log.meta("eval")["results"])["policy"] == r["policy"]
    shown = load_rollout(None, mcap, ref)  # The viewer finds the rollout in the same file.
    assert shown is not None and shown.shape == ref.qpos.shape
    np.testing.assert_allclose(shown[: len(qpos)], qpos, atol=1e-12)

    # The same policy on an unseen robot (a shipped physics file): a different rollout.
    worn = tmp_path / "worn.json"
    args = ["eval", str(out), "--episodes", "3", "--out", str(worn), "--physics", "worn_knees"]
    assert main(args) == 0
    w = json.loads(worn.read_text())
    assert w["physics"]["name"] == "worn_knees" and w["physics"]["effects"]
    assert w["policy"]["joint_error_rad"] != r["policy"]["joint_error_rad"]
    assert main([*args[:-1], "no_such_robot.yaml"]) == 2


def test_mujoco_model_of_the_reference_matches_the_env(motion_file: Path) -> None:
    """The trainer's motion uses the same joint names as the env's model."""
    from humimic.tracking.env import tracking_model
    from humimic.tracking.task import load_reference, task_config

    task = task_config("g1", "none", 0)
    model = tracking_model(task)
    ref = load_reference(motion_file, "g1", 50.0)
    env_joints = [model.joint(j).name for j in range(model.njnt)
                  if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]  # fmt: skip
    assert list(ref.joint_names) == env_joints
    assert os.path.getsize(motion_file) > 0


def test_export_onnx_matches_the_torch_policy(motion_file: Path, tmp_path: Path) -> None:
    from onnx.reference import ReferenceEvaluator

    from humimic.tracking.export import load_policy_runner

    out = tmp_path / "run"
    assert main(_train_args(motion_file, out, 2)) == 0
    path = tmp_path / "policy.onnx"
    assert main(["export", str(out), "--out", str(path)]) == 0
    runner, env, _ = load_policy_runner(out, None)
    try:
        policy = runner.get_inference_policy(device="cpu")
        obs = env.get_observations()
        batch = obs["policy"].repeat(5, 1) + 0.1 * torch.randn(5, obs["policy"].shape[1])
        with torch.inference_mode():
            expected = policy(obs.expand(5).clone().update({"policy": batch})).numpy()
    finally:
        env.close()
    (out,) = ReferenceEvaluator(str(path)).run(None, {"obs": batch.numpy()})
    got = np.asarray(out)
    assert got.shape == expected.shape == (5, 29)
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-4, atol=1e-5)
    assert main(["export", str(out), "--out", str(tmp_path / "policy.txt")]) == 2


def test_two_processes_train_one_policy_and_stay_in_sync(motion_file: Path, tmp_path: Path) -> None:
    """``torchrun --nproc-per-node 2 humimic train`` on the CPU (gloo): every iteration the
    ranks' policies are compared (``rank_param_spread``, the largest difference of any
    parameter from rank 0's); rank 0 alone writes the run."""
    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone",
           "--nproc-per-node", "2", "-m", "humimic.cli.main",
           *_train_args(motion_file, out, 3)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = (out / "progress.csv").read_text().splitlines()
    header, rows = lines[0].split(","), [line.split(",") for line in lines[1:]]
    assert [int(r[0]) for r in rows] == [1, 2, 3]  # One row per iteration: rank 0's.
    spread = [float(r[header.index("rank_param_spread")]) for r in rows]
    assert spread == [0.0, 0.0, 0.0]
    # Both ranks' experience counts: 2 ranks x 8 envs x 8 steps per iteration.
    assert [int(r[header.index("env_steps")]) for r in rows] == [128, 256, 384]
    ckpts = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert ckpts == ["model_000002.pt", "model_000003.pt"]
    # The policy moved away from its initialization (the updates were not all zero).
    a = torch.load(out / "checkpoints" / "model_000002.pt", weights_only=True)
    b = torch.load(out / "checkpoints" / "model_000003.pt", weights_only=True)
    key = next(k for k in b["actor_state_dict"] if k.endswith("weight"))
    assert not torch.equal(a["actor_state_dict"][key], b["actor_state_dict"][key])


def test_update_probe_records_every_step_and_restores_the_methods() -> None:
    """The probe sees the rate of each optimizer step and the KL of each mini-batch, and
    leaves the optimizer and the actor as they were."""
    from types import SimpleNamespace

    from humimic.tracking.rsl import UpdateProbe

    w = torch.nn.Parameter(torch.zeros(2))
    opt = torch.optim.SGD([w], lr=1e-3)
    calls = []

    class Actor:
        def get_kl_divergence(self, old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
            calls.append(1)
            return (new - old) ** 2

    alg = SimpleNamespace(optimizer=opt, actor=Actor())
    with UpdateProbe(alg) as probe:
        for lr, d in ((1e-3, 0.1), (4e-3, 0.2), (2e-3, 0.3)):
            opt.param_groups[0]["lr"] = lr
            alg.actor.get_kl_divergence(torch.zeros(3), torch.full((3,), d))
            w.grad = torch.ones(2)
            opt.step()
    s = probe.summary()
    assert s["lr_mean"] == pytest.approx(7e-3 / 3) and s["lr_max"] == 4e-3
    assert s["kl"] == pytest.approx(0.09) and len(calls) == 3
    assert w.detach().tolist() == pytest.approx([-7e-3, -7e-3])
    assert "step" not in vars(opt) and "get_kl_divergence" not in vars(alg.actor)
    empty = UpdateProbe(SimpleNamespace(optimizer=opt)).summary()
    assert all(np.isnan(v) for v in empty.values())
