"""Hostile input to ``humimic train``, ``eval``, ``export`` and ``distill``: exit code 2 with a
message naming the file or flag, nothing written, no input overwritten.

One tiny run (2 envs, rollouts of 4 steps, 2 iterations) serves every test that needs one;
tests that write into a run folder work on a copy of it.
"""

from __future__ import annotations

import csv
import os
import re
import shutil
import typing
from collections.abc import Iterator
from dataclasses import fields, is_dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro

from humimic.cli.main import main
from humimic.configs.jobs import EvalSettings, ExportSettings, LoopSettings
from humimic.configs.runs import (
    DistillSettings,
    TrainSettings,
)
from humimic.errors import InputError
from humimic.motion import motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model


def _write_motion(path: Path) -> Path:
    """The G1 standing, one arm swinging: 1.5 s at 30 fps."""
    m = nominal_model(get_robot("g1"))
    q = np.tile(m.key_qpos[0], (46, 1))
    adr = m.jnt_qposadr[m.joint("left_shoulder_pitch_joint").id]
    q[:, adr] += 0.3 * np.sin(2 * np.pi * np.arange(46) / 30.0)
    save_motion(motion_from_qpos(m, q, 30.0, "g1"), path)
    return path


def _train_args(motion: Path | str, out: Path | str, iterations: int, *extra: str) -> list[str]:
    return ["train", "--motion", str(motion), "--out", str(out), "--num-envs", "2",
            "--max-iterations", str(iterations), "--num-steps-per-env", "4", "--dr", "none",
            "--checkpoint-every", "1", "--task.action-base", "default", "--quiet",
            *extra]  # fmt: skip


@pytest.fixture(scope="module")
def motion_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_motion(tmp_path_factory.mktemp("motion") / "stand.npz")


@pytest.fixture(scope="module")
def run(motion_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-iteration run with checkpoints after iterations 1 and 2 (never written to)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(_train_args(motion_file, out, 2)) == 0
    return out


def _copy(run: Path, dst: Path) -> Path:
    shutil.copytree(run, dst)
    return dst


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# --- 1. export: one self-contained ONNX file -------------------------------------------------


def test_export_writes_one_self_contained_file_that_runs_anywhere(
    run: Path, tmp_path: Path
) -> None:
    """The weights are inside policy.onnx: a copy of that file alone loads and runs elsewhere,
    and re-exporting leaves no other file in the run folder."""
    import onnx
    from onnx.reference import ReferenceEvaluator

    from humimic.tracking.export import load_policy_runner

    folder = _copy(run, tmp_path / "run")
    before = set(_snapshot(folder))
    assert main(["export", str(folder), "--format", "onnx"]) == 0
    assert main(["export", str(folder), "--format", "onnx"]) == 0  # Re-export: same files.
    assert set(_snapshot(folder)) == before | {"policy.onnx"}

    elsewhere = tmp_path / "robot"
    elsewhere.mkdir()
    shutil.copy(folder / "policy.onnx", elsewhere / "policy.onnx")
    model = onnx.load(str(elsewhere / "policy.onnx"))
    onnx.checker.check_model(model, full_check=True)
    assert model.graph.initializer
    assert all(t.data_location != onnx.TensorProto.EXTERNAL for t in model.graph.initializer)

    runner, env, _ = load_policy_runner(folder, None)
    try:
        policy = runner.get_inference_policy(device="cpu")
        obs = env.get_observations()
        with torch.inference_mode():
            expected = policy(obs).numpy()
    finally:
        env.close()
    (got,) = ReferenceEvaluator(model).run(None, {"obs": obs["policy"].numpy()})
    assert np.asarray(got).shape == expected.shape == (1, 29)
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-4, atol=1e-5)


# --- 2. damaged checkpoints ------------------------------------------------------------------


def _bad_checkpoint(kind: str, run: Path, path: Path) -> Path:
    good = run / "checkpoints" / "model_000002.pt"
    if kind == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif kind == "truncated":
        path.write_bytes(good.read_bytes()[:100_000])
    elif kind == "text":
        path.write_text("iter: 2\nactor_state_dict: weights\n")
    elif kind == "tensor":
        torch.save(torch.zeros(3), path)
    elif kind == "nan":  # A run that diverged: one weight of the actor is NaN.
        blob = torch.load(good, weights_only=True)
        key = next(k for k in blob["actor_state_dict"] if k.endswith("0.weight"))
        blob["actor_state_dict"][key][0, 0] = float("nan")
        torch.save(blob, path)
    else:  # Another shape: the actor's first layer takes one input fewer.
        blob = torch.load(good, weights_only=True)
        key = next(k for k in blob["actor_state_dict"] if k.endswith("0.weight"))
        blob["actor_state_dict"][key] = blob["actor_state_dict"][key][:, :-1].clone()
        torch.save(blob, path)
    return path


@pytest.mark.parametrize("kind", ["random", "truncated", "text", "tensor", "shape", "nan"])
def test_damaged_checkpoint_exits_2_naming_it(
    kind: str, run: Path, motion_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = _bad_checkpoint(kind, run, tmp_path / f"{kind}.pt")
    out = tmp_path / "out"
    calls = {
        "eval": ["eval", str(run), "--episodes", "1", "--checkpoint", str(bad), "--out",
                 str(out / "eval.json")],
        "export": ["export", str(run), "--checkpoint", str(bad), "--out", str(out / "p.onnx")],
        "distill": ["distill", "--teacher", str(run), "--teacher-checkpoint", str(bad),
                    "--out", str(out / "student"), "--num-envs", "2", "--max-iterations", "1",
                    "--quiet"],
        "train": _train_args(motion_file, out / "tuned", 1, "--init-from", str(bad)),
    }  # fmt: skip
    for name, args in calls.items():
        assert main(args) == 2, name
        err = capsys.readouterr().err
        assert err.startswith("humimic: error: --") and str(bad) in err, (name, err)
        assert len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err
        assert not out.exists() or not any(out.rglob("*")), name


def test_resume_refuses_a_newest_checkpoint_that_does_not_fit(
    run: Path, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _copy(run, tmp_path / "run")
    newest = folder / "checkpoints" / "model_000002.pt"
    _bad_checkpoint("shape", run, newest)
    before = (folder / "progress.csv").read_text()
    assert main(_train_args(motion_file, folder, 3, "--resume")) == 2
    err = capsys.readouterr().err
    assert "model_000002.pt" in err and "do not fit" in err
    assert (folder / "progress.csv").read_text() == before
    assert sorted(p.name for p in (folder / "checkpoints").iterdir()) == [
        "model_000001.pt",
        "model_000002.pt",
    ]


@pytest.mark.parametrize("kind", ["nan", "folder", "fifo"])
def test_a_newest_checkpoint_that_does_not_load_is_named_not_passed_over(
    kind: str, run: Path, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """eval and export read the run's newest checkpoint: one with NaN weights, a folder or a
    FIFO in its place is refused by name (an older one was taken in silence), and nothing is
    written. ``train --resume`` passes over a damaged or NaN one, saying so on stderr, but not
    a folder or FIFO (no crash leaves one)."""
    folder = _copy(run, tmp_path / "run")
    newest = folder / "checkpoints" / "model_000003.pt"
    if kind == "nan":
        _bad_checkpoint("nan", run, newest)
    elif kind == "folder":
        newest.mkdir()
    else:
        os.mkfifo(newest)
    before = _snapshot(folder)
    calls = [["eval", str(folder), "--episodes", "1", "--out", str(tmp_path / "eval.json")],
             ["export", str(folder), "--out", str(tmp_path / "p.onnx")]]  # fmt: skip
    if kind != "nan":
        calls.append(_train_args(motion_file, folder, 4, "--resume"))
    why = {"nan": "NaN", "folder": "a folder", "fifo": "not a regular file"}[kind]
    for args in calls:
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert "model_000003.pt" in err and why in err and len(err.strip().splitlines()) == 1
    assert _snapshot(folder) == before
    assert not (tmp_path / "eval.json").exists() and not (tmp_path / "p.onnx").exists()
    if kind == "nan":
        assert main(_train_args(motion_file, folder, 3, "--resume")) == 0
        err = capsys.readouterr().err
        assert "warning: skipping" in err and "model_000003.pt" in err and why in err, err


def test_a_run_folder_being_written_is_refused_to_a_second_writer(
    run: Path, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two trainings on one --out, started 2 s apart, both ran and mixed their files. While a
    process holds the folder (here: this test, through the same kernel lock a training
    takes), train --resume and distill into it are refused; once it lets go, resuming works
    (a killed run's lock goes with it: test_kill_9_then_resume_loses_nothing...)."""
    from humimic.tracking.runs import run_folder_lock

    folder = _copy(run, tmp_path / "run")
    before = _snapshot(folder)
    with run_folder_lock(folder, has_run=True):
        assert main(_train_args(motion_file, folder, 3, "--resume")) == 2
        err = capsys.readouterr().err
        assert "another humimic process is writing" in err and str(folder) in err, err
        distill = ["distill", "--teacher", str(run), "--out", str(folder), "--resume",
                   "--num-envs", "2", "--max-iterations", "3", "--quiet"]  # fmt: skip
        assert main(distill) == 2
        assert "another humimic process is writing" in capsys.readouterr().err
        assert _snapshot(folder) == before
    assert main(_train_args(motion_file, folder, 3, "--resume")) == 0


def test_a_run_started_meanwhile_in_the_same_folder_is_refused(
    run: Path, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The lock is taken after the settings are checked: a run written into the folder in
    between (by a process that has ended) is found under the lock, not overwritten."""
    from humimic.tracking.runs import run_folder_lock

    folder = _copy(run, tmp_path / "run")
    meanwhile = "another run was started in this folder meanwhile"
    with pytest.raises(InputError, match=meanwhile), run_folder_lock(folder, has_run=False):
        pass


@pytest.mark.parametrize("case", ["resume-missing", "resume-no-run", "new-nonempty"])
def test_train_needs_a_run_to_resume_and_an_empty_folder_to_start(
    case: str, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--resume on a missing folder started a new run; a new run went into a folder of other
    files."""
    out = tmp_path / "out"
    if case != "resume-missing":
        out.mkdir()
        (out / "notes.txt").write_text("mine\n")
    extra = () if case == "new-nonempty" else ("--resume",)
    assert main(_train_args(motion_file, out, 1, *extra)) == 2
    err = capsys.readouterr().err
    want = {"resume-missing": "no such folder", "resume-no-run": "holds no run",
            "new-nonempty": "not empty"}[case]  # fmt: skip
    assert want in err and str(out) in err and err.count("\n") == 1, err
    assert (
        (not out.exists())
        if case == "resume-missing"
        else [p.name for p in out.iterdir()] == ["notes.txt"]
    )


def test_a_physics_file_with_an_effect_that_adds_joints_is_refused_by_name(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Backlash adds a play joint: eval said "the actuators must drive the joints after the
    free joint, in qpos order", naming neither the file nor the effect."""
    physics = tmp_path / "worn.yaml"
    physics.write_text("effects:\n  - backlash:left_knee_joint=0.02\n")
    out = tmp_path / "eval.json"
    assert main(["eval", str(run), "--episodes", "1", "--physics", str(physics),
                 "--out", str(out)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert str(physics) in err and "backlash" in err and "adds joints" in err, err
    assert err.count("\n") == 1 and not out.exists()


def test_a_copied_run_reads_its_own_reference_and_notices_it_changed(
    tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """config.yaml stored the run's reference (its own reference.npz) by absolute path: a
    copied run read the original's, ``eval --out COPY/reference.npz`` overwrote the copy's
    with JSON, and a changed or deleted reference in the copy went unnoticed."""
    import yaml

    from humimic.tracking.runs import read_run_settings

    first = tmp_path / "first"
    first.mkdir()
    shutil.copy(motion_file, first / "reference.npz")  # A run's own (refined) reference.
    assert main(_train_args(first / "reference.npz", first, 1)) == 0
    config = yaml.safe_load((first / "config.yaml").read_text())
    assert config["settings"]["motion"] == "reference.npz" and config["motion_in_run"] is True
    copy = _copy(first, tmp_path / "copy")
    shutil.rmtree(first)  # The copy stands alone.
    assert read_run_settings(copy).motion == (copy / "reference.npz").resolve()
    assert main(["eval", str(copy), "--episodes", "1", "--out", str(tmp_path / "e.json")]) == 0

    before = (copy / "reference.npz").read_bytes()
    assert main(["eval", str(copy), "--episodes", "1", "--out", str(copy / "reference.npz")]) == 2
    assert "would overwrite the run's reference.npz" in capsys.readouterr().err
    assert (copy / "reference.npz").read_bytes() == before

    # Another motion (of the same robot and length) in the reference's place.
    m = nominal_model(get_robot("g1"))
    q = np.tile(m.key_qpos[0], (46, 1))
    save_motion(motion_from_qpos(m, q, 30.0, "g1"), copy / "reference.npz")
    out = tmp_path / "changed.json"
    for args in (["eval", str(copy), "--episodes", "1", "--out", str(out)],
                 _train_args(copy / "reference.npz", copy, 2, "--resume")):  # fmt: skip
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "reference.npz has changed since the run recorded it" in err, err
    assert not out.exists() and not (copy / "checkpoints" / "model_000002.pt").exists()
    (copy / "reference.npz").unlink()
    assert main(["eval", str(copy), "--episodes", "1", "--out", str(out)]) == 2
    assert "reference.npz is missing" in capsys.readouterr().err


# --- 3. nonsensical settings -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "flag"),
    [
        (["--device", "bogus"], "--device"),
        (["--device", "mps"], "--device"),
        (["--num-steps-per-env", "0"], "--num-steps-per-env"),
        (["--num-envs", "0"], "--num-envs"),
        (["--max-iterations", "-1"], "--max-iterations"),
        (["--checkpoint-every", "0"], "--checkpoint-every"),
        (["--max-minutes", "0"], "--max-minutes"),
        (["--max-minutes", "nan"], "--max-minutes"),
        (["--seed", "-1"], "--seed"),
        (["--num-envs", "1", "--num-steps-per-env", "2"], "--num-envs 1 x --num-steps-per-env 2"),
    ],
)
def test_train_refuses_nonsensical_settings(
    extra: list[str], flag: str, motion_file: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    out = tmp_path / "run"
    args = _train_args(motion_file, out, 1)
    for name, value in zip(extra[::2], extra[1::2], strict=True):  # Replace or add the flag.
        if name in args:
            args[args.index(name) + 1] = value
        else:
            args += [name, value]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"humimic: error: {flag}"), err
    assert not out.exists()


@pytest.mark.parametrize(
    ("command", "extra", "flag"),
    [
        ("eval", ["--episodes", "0"], "--episodes"),
        ("eval", ["--episodes", "2", "--num-envs", "1"], "--num-envs"),
        ("eval", ["--device", "bogus"], "--device"),
        ("eval", ["--seed", "-1"], "--seed"),
        ("distill", ["--num-envs", "0"], "--num-envs"),
        ("distill", ["--max-iterations", "0"], "--max-iterations"),
        ("distill", ["--device", "cuda:x"], "--device"),
        ("distill", ["--max-minutes", "-1"], "--max-minutes"),
        ("loop", ["--episodes", "0"], "--episodes"),
        ("loop", ["--iterations", "0"], "--iterations"),
        ("loop", ["--sysid-duration", "1"], "--sysid-duration"),
        ("loop", ["--sysid-duration", "inf"], "--sysid-duration"),
        ("loop", ["--device", "nonsense"], "--device"),
        ("loop", ["--max-minutes", "0"], "--max-minutes"),
    ],
)
def test_eval_distill_loop_refuse_nonsensical_settings(
    command: str, extra: list[str], flag: str, run: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    out = tmp_path / "out"
    args = {
        "eval": ["eval", str(run), "--out", str(out / "eval.json")],
        "distill": ["distill", "--teacher", str(run), "--out", str(out), "--quiet"],
        "loop": ["loop", "--run", str(run), "--real", "backpack", "--out", str(out), "--quiet"],
    }[command]
    assert main([*args, *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"humimic: error: {flag}"), err
    assert not out.exists()


def test_cuda_device_is_checked_before_any_work(
    motion_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """Without CUDA, ``--device cuda`` is refused; with one GPU, ``cuda:3`` is."""
    out = tmp_path / "run"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(_train_args(motion_file, out, 1, "--device", "cuda")) == 2
    assert "--device cuda: CUDA is not available" in capsys.readouterr().err
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert main(_train_args(motion_file, out, 1, "--device", "cuda:3")) == 2
    assert "--device cuda:3: this machine has 1 CUDA device" in capsys.readouterr().err
    assert not out.exists()


# --- 4. paths recorded absolute --------------------------------------------------------------


def test_run_records_absolute_paths_and_works_from_any_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run started with relative paths evaluates from another folder, resumes with the
    motion's absolute path, and an older run folder's relative paths are still found."""
    from humimic.tracking.runs import read_run_settings

    project = tmp_path / "project"
    (project / "data").mkdir(parents=True)
    motion = _write_motion(project / "data" / "stand.npz")
    monkeypatch.chdir(project)
    assert main(_train_args("data/stand.npz", "runs/a", 1)) == 0
    run = project / "runs" / "a"
    assert read_run_settings(run).motion == motion.resolve()
    assert f"motion: {motion.resolve()}" in (run / "config.yaml").read_text()

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["eval", str(run), "--episodes", "1"]) == 0
    # The same motion by its absolute path is no "other motion".
    assert main(_train_args(motion, run, 2, "--resume")) == 0
    assert (run / "checkpoints" / "model_000002.pt").is_file()
    # Another motion is.
    other = _write_motion(elsewhere / "stand.npz")
    assert main(_train_args(other, run, 3, "--resume")) == 2
    assert "--resume: motion differs" in capsys.readouterr().err

    # An older run folder recorded the paths as typed: found from where the run was started.
    cfg = run / "config.yaml"
    text = cfg.read_text()
    cfg.write_text(
        text.replace(f"motion: {motion.resolve()}", "motion: data/stand.npz").replace(
            f"out: {run.resolve()}", "out: runs/a"
        )
    )
    assert "motion: data/stand.npz" in cfg.read_text()
    assert read_run_settings(run).motion == motion.resolve()
    # A motion that is gone is named.
    motion.rename(project / "data" / "moved.npz")
    out = elsewhere / "e.json"
    assert main(["eval", str(run), "--episodes", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "the run's motion" in err and "stand.npz" in err and "--motion" in err
    assert not out.exists()


# --- 5. progress.csv after a crash and --resume ----------------------------------------------


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_resume_after_a_crash_keeps_progress_csv_one_row_per_iteration(
    run: Path, tmp_path: Path, motion_file: Path
) -> None:
    """A crash after iteration 2's row but before its checkpoint, with a row cut short: the
    resumed run redoes iteration 2, keeps one row per iteration, and its ``seconds`` go on."""
    folder = _copy(run, tmp_path / "run")
    (folder / "checkpoints" / "model_000002.pt").unlink()  # The crash came before it.
    rows = _rows(folder / "progress.csv")
    assert [r["iteration"] for r in rows] == ["1", "2"]
    with open(folder / "progress.csv", "a") as f:
        f.write("3,24,99")  # A row cut short by kill -9.
    kept_seconds = float(rows[0]["seconds"])

    assert main(_train_args(motion_file, folder, 3, "--resume")) == 0
    rows = _rows(folder / "progress.csv")
    assert [r["iteration"] for r in rows] == ["1", "2", "3"]
    header = (folder / "progress.csv").read_text().splitlines()[0].split(",")
    assert all(len(r) == len(header) and None not in r for r in rows)  # Columns line up.
    seconds = [float(r["seconds"]) for r in rows]
    assert seconds[0] == kept_seconds
    assert seconds[0] < seconds[1] < seconds[2]
    assert [int(r["env_steps"]) for r in rows] == [8, 16, 24]


def test_trim_progress_drops_rows_past_the_checkpoint(tmp_path: Path) -> None:
    from humimic.tracking.runs import trim_progress

    path = tmp_path / "progress.csv"
    path.write_text("iteration,seconds,x\n1,2.5,a\n2,5.0,b\n3,7.5,c\n4,10.0,d\n5,1")
    assert trim_progress(path, 2) == (5.0, ["iteration", "seconds", "x"])
    assert path.read_text() == "iteration,seconds,x\n1,2.5,a\n2,5.0,b\n"
    assert trim_progress(path, 2) == (5.0, ["iteration", "seconds", "x"])  # Nothing to drop.
    assert trim_progress(path, 0) == (0.0, None)  # No checkpoint: no row is kept.
    assert not path.exists()
    path.write_text("iteration,sec")  # A header cut short.
    assert trim_progress(path, 3) == (0.0, None) and not path.exists()
    # A last row cut short is removed from the file even when every full row is kept:
    # otherwise the resumed run's next row would be glued onto it.
    path.write_text("iteration,seconds\n1,0.5\n2,1.0\n3,1.")
    assert trim_progress(path, 5) == (1.0, ["iteration", "seconds"])
    assert path.read_text() == "iteration,seconds\n1,0.5\n2,1.0\n"


# --- 6. outputs that would overwrite an input ------------------------------------------------


def test_outputs_that_would_overwrite_an_input_are_refused(
    run: Path, tmp_path: Path, motion_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _copy(run, tmp_path / "run")
    before = _snapshot(folder)
    motion_bytes = motion_file.read_bytes()
    cases = [
        (["eval", str(folder), "--out", str(folder / "config.yaml")], "--out", "config.yaml"),
        (["eval", str(folder), "--out", str(folder / "progress.csv")], "--out", "progress.csv"),
        (["eval", str(folder), "--out", str(motion_file)], "--out", "the motion"),
        (["eval", str(folder), "--out", str(tmp_path / "e.json"), "--mcap",
          str(tmp_path / "m.mcap"), "--motion", str(tmp_path / "m.mcap")], "--mcap", "motion"),
        # --out x.mcap: its default MCAP would be the same file.
        (["eval", str(folder), "--out", str(tmp_path / "x.mcap")], "--mcap", "--out"),
        (["distill", "--teacher", str(folder), "--out", str(folder), "--resume"], "--out",
         "teacher"),
    ]  # fmt: skip
    for args, flag, what in cases:
        assert main([*args, "--episodes", "1"] if args[0] == "eval" else args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith(f"humimic: error: {flag}") and what in err, err
    assert _snapshot(folder) == before
    assert motion_file.read_bytes() == motion_bytes
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "e.json").exists()

    # A new run must not write its checkpoints over the one it starts from.
    fresh = tmp_path / "fresh"
    (fresh / "checkpoints").mkdir(parents=True)
    init = fresh / "checkpoints" / "model_000001.pt"
    shutil.copy(folder / "checkpoints" / "model_000001.pt", init)
    init_bytes = init.read_bytes()
    assert main(_train_args(motion_file, fresh, 1, "--init-from", str(init))) == 2
    assert "--init-from" in capsys.readouterr().err
    assert init.read_bytes() == init_bytes
    assert sorted(p.name for p in fresh.rglob("*")) == ["checkpoints", "model_000001.pt"]


# --- 7. help texts ---------------------------------------------------------------------------


def _help_entries(text: str) -> dict[str, str]:
    """tyro's help (rich boxes on a terminal, plain text otherwise), per option: its first
    line's leading words (flags and metavar) -> its help text. An option's line starts at most
    two columns in; its help's further lines are indented to the help column."""
    entries: dict[str, str] = {}
    key = None
    for line in text.splitlines():
        inner = line.replace("│", " ").rstrip()
        body = inner.lstrip()
        if not body:
            key = None
        elif len(inner) - len(body) <= 2:  # A new option: flags, 2+ spaces, help.
            key, _, rest = body.partition("  ")
            entries[key] = rest.strip()
        elif key is not None:
            entries[key] += " " + body
    return entries


_SUPPRESS = typing.get_args(tyro.conf.Suppress[int])[1]


def _flags(cls: type, prefix: str = "--") -> Iterator[tuple[str, str]]:
    """(field name, flag) of every field of a settings class the command line shows: nested
    configs' fields under their prefix (``--ppo.learning-rate``), suppressed ones left out."""
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in fields(cls):
        hint = hints[f.name]
        if _SUPPRESS in getattr(hint, "__metadata__", ()):
            continue
        flag = prefix + f.name.replace("_", "-")
        if is_dataclass(hint) and isinstance(hint, type):
            yield from _flags(hint, flag + ".")
        else:
            yield f.name, flag


@pytest.mark.parametrize(
    ("command", "cls"),
    [("train", TrainSettings), ("eval", EvalSettings), ("export", ExportSettings),
     ("distill", DistillSettings), ("loop", LoopSettings)],
)  # fmt: skip
def test_every_tracking_subcommand_and_flag_has_help(
    command: str, cls: type, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    # Wide, so that an option's help fits its line where its flags are short; under 130
    # columns, so that tyro does not set the option groups side by side.
    monkeypatch.setenv("COLUMNS", "129")
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "What ``humimic" not in text
    description = text.split("\n\n")[1].strip()
    assert len(description.split()) >= 5 and not description.startswith("╭"), description
    entries = _help_entries(text)
    for name, flag in _flags(cls):
        keys = [k for k in entries if k.split()[0].rstrip(",") == flag]
        if not keys and name == "run" and command in ("eval", "export"):
            keys = [k for k in entries if k.split()[0] == "PATH"]  # Positional.
        assert len(keys) == 1, (flag, sorted(entries))
        help_text = re.sub(r"\((default|required|fixed)[^)]*\)", "", entries[keys[0]])
        assert re.search(r"[A-Za-z]{3}", help_text), (flag, entries[keys[0]])


def test_top_level_help_describes_the_tracking_commands(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "250")
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "What ``humimic" not in text
    for command in ("train", "distill", "eval", "export", "loop"):
        line = next(ln for ln in text.splitlines() if f"• {command} " in ln)
        assert len(line.split(f"• {command} ", 1)[1].strip(" │").split()) >= 4, line
