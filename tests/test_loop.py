"""``humimic loop`` end to end on a tiny budget, and the rule that no training step reads the
"real" robot's physics file."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.motion import motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model


@pytest.fixture(scope="module")
def base_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-iteration policy on the G1 standing with one arm swinging (1.5 s)."""
    folder = tmp_path_factory.mktemp("loop")
    m = nominal_model(get_robot("g1"))
    q = np.tile(m.key_qpos[0], (46, 1))
    q[:, m.jnt_qposadr[m.joint("left_shoulder_pitch_joint").id]] += 0.3 * np.sin(
        2 * np.pi * np.arange(46) / 30.0
    )
    save_motion(motion_from_qpos(m, q, 30.0, "g1"), folder / "stand.npz")
    run = folder / "base"
    args = ["train", "--motion", str(folder / "stand.npz"), "--out", str(run), "--num-envs", "8",
            "--max-iterations", "2", "--num-steps-per-env", "8", "--dr", "none",
            "--task.action-base", "default", "--quiet"]  # fmt: skip
    assert main(args) == 0
    return run


def test_loop_end_to_end_never_trains_on_the_real_physics(
    base_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = tmp_path / "real.yaml"
    real.write_text("floor_friction: 0.5\neffects:\n  - gain_mismatch:left_knee_joint=0.7\n")
    hidden = tmp_path / "elsewhere.yaml"
    stages: list[str] = []

    def hide_real(name: str, fn):
        def wrapped(*args, **kwargs):
            stages.append(name)
            real.rename(hidden)  # Any read of the real file now fails.
            try:
                return fn(*args, **kwargs)
            finally:
                hidden.rename(real)

        return wrapped

    import humimic.real2sim.report as report_mod
    import humimic.tracking.train as train_mod

    monkeypatch.setattr(train_mod, "train", hide_real("train", train_mod.train))
    monkeypatch.setattr(report_mod, "run_diagnosis",
                        hide_real("sysid", report_mod.run_diagnosis))  # fmt: skip
    out = tmp_path / "loop"
    args = ["loop", "--run", str(base_run), "--real", str(real), "--out", str(out),
            "--episodes", "1", "--iterations", "1", "--learning-rate", "5e-05",
            "--sysid-duration", "5", "--control", "--quiet"]  # fmt: skip
    assert main(args) == 0
    assert stages == ["sysid", "train", "train"]  # Fine-tuning in the corrected and nominal models.

    r = json.loads((out / "loop.json").read_text())
    for name in ("before", "after", "after_nominal"):
        assert 0.0 <= r[name]["policy"]["success_rate"] <= 1.0
        assert r[name]["policy"]["mpjpe_global_mm"] > 0
    # Sysid read the policy's deployment: whole episodes of the 1.5 s clip, about 5 s of them.
    dep = r["deployment_log"]
    assert r["sysid"]["log"] == "deployment" and dep["log"] == str(out / "deployment.mcap")
    assert dep["episodes"] == 4 and 0 <= dep["falls"] <= 4 and 0.0 < dep["seconds"] <= 6.0
    sysid = json.loads((out / "sysid" / "report.json").read_text())
    assert sysid["base"] == "floating"
    # The claims that leave their joints far above the noise floor are named in the loop's too.
    partial = [e for e in sysid["effects"] if e["confidence"] >= 0.5 and e["partial"]]
    assert len(r["sysid"]["partial"]) == len(partial)
    assert "humimic loop" in (out / "loop.md").read_text()

    from humimic.real2sim.robotlog import read_robot_log
    from humimic.sim.physics import load_physics
    from humimic.tracking.runs import read_run_settings

    load_physics(out / "corrected.yaml")  # What sysid claimed, as a physics file.
    tuned = read_run_settings(out / "finetune")
    assert tuned.physics == str(out / "corrected.yaml") and tuned.init_from == base_run
    assert read_run_settings(out / "finetune_nominal").physics is None
    assert tuned.num_envs == 8  # Without --num-envs: as many as the run trained with.
    # Both arms at the loop's learning rate, fixed (the run trained at 1e-3, adaptive).
    for arm in ("finetune", "finetune_nominal"):
        ppo = read_run_settings(out / arm).ppo
        assert (ppo.learning_rate, ppo.schedule) == (5e-05, "fixed")
        with (out / arm / "progress.csv").open() as f:
            assert float(next(csv.DictReader(f))["lr_mean"]) == pytest.approx(5e-05)
    names = tuple(nominal_model(get_robot("g1")).joint(j).name for j in range(1, 30))
    log = read_robot_log(out / "before" / "robot_log.mcap", names)
    assert log.base == "floating" and len(log.t) == r["before"]["policy"]["mean_steps"] + 1
    # A deployment log with the IMU and mocap a robot on the floor reports, which the
    # predictions read (the base's state rebuilt from them, not from the simulator).
    assert log.imu is not None and log.imu.site == "imu_in_pelvis" and log.mocap is not None
    # Standing the first 0.4 s: on average about gravity's reaction, up (the pelvis upright).
    assert log.imu.acc_b is not None
    up = float(np.mean(log.imu.acc_b[:20, 2]))
    assert 9.3 < up < 10.3 and np.all(np.abs(np.mean(log.imu.acc_b[:20, :2], axis=0)) < 1.0)
    assert main(["sysid", "residual", str(out / "before" / "robot_log.mcap"), "--horizon",
                 "0.1", "--report", str(tmp_path / "res.json")]) == 0  # fmt: skip
    res = json.loads((tmp_path / "res.json").read_text())
    assert res["base"] == "floating" and res["error_nominal"]["kstep_rmse_rad"] > 0
    assert json.loads((out / "before" / "eval.json").read_text())["physics"]["name"] == "real"


def test_bad_input_exits_2_and_writes_nothing(base_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "loop"
    args = ["loop", "--run", str(base_run), "--out", str(out), "--quiet"]
    assert main([*args, "--real", str(tmp_path / "missing.yaml")]) == 2
    bad = tmp_path / "bad.yaml"
    bad.write_text("floor_friction: slippery\n")
    assert main([*args, "--real", str(bad)]) == 2
    assert main([*args, "--real", "worn_knees", "--iterations", "0"]) == 2
    assert main([*args, "--real", "worn_knees", "--learning-rate", "0"]) == 2
    assert not out.exists()


def test_a_loop_that_fails_after_deploying_leaves_nothing_behind(
    base_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """The diagnosis refusing the deployment log (as a too short one is) came after the
    deployment had written before/ and deployment.mcap, which stayed; now a failed loop
    removes what it wrote, in a folder it made or in the empty one it was given."""
    import humimic.real2sim.report as report_mod
    from humimic.errors import InputError

    def refuse(log: Path, *args, **kwargs):
        assert log.is_file()  # The deployment log was written.
        raise InputError(f"{log}: too short for --horizon 0.5 s windows")

    monkeypatch.setattr(report_mod, "run_diagnosis", refuse)
    given = tmp_path / "given"
    given.mkdir()
    for out in (tmp_path / "made", given):
        args = ["loop", "--run", str(base_run), "--real", "worn_knees", "--out", str(out),
                "--episodes", "1", "--iterations", "1", "--sysid-duration", "5", "--quiet"]  # fmt: skip
        assert main(args) == 2
        assert "too short" in capsys.readouterr().err
        assert not (tmp_path / "made").exists() and list(given.iterdir()) == []


def test_loop_checks_the_policy_and_its_output_before_deploying(
    base_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A NaN checkpoint ended the loop in a traceback after an empty before/ was made; an
    --out inside the run folder wrote into the input."""
    import shutil

    import torch

    run = shutil.copytree(base_run, tmp_path / "run")
    newest = sorted((run / "checkpoints").glob("model_*.pt"))[-1]
    blob = torch.load(newest, weights_only=True)
    key = next(k for k in blob["actor_state_dict"] if k.endswith("0.weight"))
    blob["actor_state_dict"][key][0, 0] = float("nan")
    torch.save(blob, newest)
    files = sorted(p for p in run.rglob("*"))
    out = tmp_path / "loop"
    base = ["loop", "--real", "worn_knees", "--episodes", "1", "--iterations", "1", "--quiet"]
    assert main([*base, "--run", str(run), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert newest.name in err and "NaN" in err and err.count("\n") == 1, err
    assert main([*base, "--run", str(base_run), "--out", str(base_run / "loop")]) == 2
    assert "inside the run folder" in capsys.readouterr().err
    assert not out.exists() and not (base_run / "loop").exists()
    assert sorted(p for p in run.rglob("*")) == files


def test_a_gantry_session_records_the_real_robot(tmp_path: Path) -> None:
    """``--sysid-log gantry``: the real robot's effects and floor, hanging in a gantry, as
    ``humimic sysid simulate`` would log them with those effects injected."""
    from humimic.configs.jobs import LoopSettings
    from humimic.pipeline.loop import gantry_session
    from humimic.real2sim import LogSettings, read_robot_log, simulate_log
    from humimic.sim.effects import parse_injection

    real = tmp_path / "real.yaml"
    real.write_text("effects:\n  - gain_mismatch:left_knee_joint=0.7\n")
    s = LoopSettings(run=tmp_path, real=str(real), out=tmp_path / "o", sysid_log="gantry",
                     sysid_duration=5.0, seed=3)  # fmt: skip
    path = gantry_session(s, "g1", tmp_path / "gantry.mcap")
    names = tuple(nominal_model(get_robot("g1")).joint(j).name for j in range(1, 30))
    log = read_robot_log(path, names)
    same = simulate_log(get_robot("g1"), [parse_injection("gain_mismatch:left_knee_joint=0.7")],
                        LogSettings(duration=5.0, seed=3))  # fmt: skip
    plain = simulate_log(get_robot("g1"), [], LogSettings(duration=5.0, seed=3))
    assert log.base == "fixed"
    np.testing.assert_allclose(log.q, same.q, atol=1e-9)
    knee = names.index("left_knee_joint")
    assert np.abs(log.q[:, knee] - plain.q[:, knee]).max() > 1e-3  # The weak knee shows.
