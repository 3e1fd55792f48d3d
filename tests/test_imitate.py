"""``humimic imitate``: the whole job on a real clip at a tiny budget, and its refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from humimic.cli.main import main


def _short_bvh(src: Path, dst: Path, frames: int) -> Path:
    """The first ``frames`` frames of a BVH file (its hierarchy unchanged)."""
    text = src.read_text().splitlines()
    m = next(i for i, line in enumerate(text) if line.strip() == "MOTION")
    body = text[m + 3 : m + 3 + frames]
    dst.write_text("\n".join([*text[: m + 1], f"Frames: {frames}", text[m + 2], *body]) + "\n")
    return dst


def test_imitate_end_to_end_on_a_tiny_budget(shared_data: Path, tmp_path: Path) -> None:
    """0.6 s of the CMU walk: retargeted, refined (the recipe's feedback base needs it),
    trained for a few seconds, evaluated on the four physics, exported, reported."""
    clip = _short_bvh(shared_data / "cmu" / "35_01.bvh", tmp_path / "walk.bvh", 74)
    out = tmp_path / "job"
    argv = ["imitate", str(clip), "--out", str(out), "--minutes", "0.15", "--episodes", "2",
            "--num-envs", "8", "--no-screenshot", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    for name in ("motion.npz", "motion.json", "run/reference.npz", "run/config.yaml",
                 "policy.onnx", "learning_curve.png", "body_error.png", "report.md",
                 "eval_dr_default.mcap", *(f"eval_{p}.json" for p in
                                           ("nominal", "dr_default", "backpack", "worn_knees"))):  # fmt: skip
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert report["train"]["iterations"] >= 1
    assert set(report["eval"]) == {"nominal", "dr_default", "backpack", "worn_knees"}
    worn = json.loads((out / "eval_worn_knees.json").read_text())
    assert worn["physics"]["name"] == "worn_knees" and worn["policy"]["episodes"] == 2
    md = (out / "report.md").read_text()
    assert "| dr_default | policy |" in md and "learning_curve.png" in md
    assert "Rollout pictures: not asked for" in md
    # The field's protocols once, on the nominal robot, in the report.
    proto = report["eval"]["nominal"]["protocols"]
    assert proto["beyondmimic"]["clips"] == 1 and "protocols" not in report["eval"]["dr_default"]
    assert "BeyondMimic's protocol (" in md and "PHC's protocol (" in md
    # Resuming with the kinematic motion reuses the run's refinement instead of refining again.
    ref = out / "run" / "reference.npz"
    stamp = ref.stat().st_mtime_ns
    done = report["train"]["iterations"]
    resume = ["train", "--motion", str(out / "motion.npz"), "--out", str(out / "run"),
              "--resume", "--num-envs", "8", "--max-iterations", str(done + 1), "--quiet"]  # fmt: skip
    assert main(resume) == 0
    assert ref.stat().st_mtime_ns == stamp
    rows = (out / "run" / "progress.csv").read_text().splitlines()
    assert rows[-1].startswith(f"{done + 1},")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--minutes", "0"], "--minutes 0.0: must be a positive number"),
        (["--episodes", "0"], "--episodes 0: must be at least 1"),
        (["--device", "bogus"], "--device 'bogus'"),
    ],
)
def test_imitate_refuses_bad_settings_before_writing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    clip = tmp_path / "c.bvh"
    clip.write_text("HIERARCHY\n")
    out = tmp_path / "job"
    assert main(["imitate", str(clip), "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_imitate_refuses_bad_clips_and_used_folders(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "job"
    assert main(["imitate", str(tmp_path / "missing.bvh"), "--out", str(out)]) == 2
    assert "missing.bvh: no such clip file" in capsys.readouterr().err
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")  # Truncated.
    assert main(["imitate", str(bad), "--out", str(out)]) == 2
    assert "bad.bvh" in capsys.readouterr().err
    assert not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    clip = _short_bvh(shared_data / "cmu" / "35_01.bvh", tmp_path / "walk.bvh", 30)
    assert main(["imitate", str(clip), "--out", str(out)]) == 2
    assert "must be a new or empty folder" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


def test_imitate_a_folder_trains_one_policy_for_its_clips(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder of two short CMU clips and a truncated one: the two are retargeted, refined
    and tracked by one policy, evaluated clip by clip; the bad one is reported and left
    out."""
    clips = tmp_path / "clips"
    clips.mkdir()
    _short_bvh(shared_data / "cmu" / "35_01.bvh", clips / "walk.bvh", 62)
    _short_bvh(shared_data / "cmu" / "09_01.bvh", clips / "run.bvh", 50)
    (clips / "cut.bvh").write_text("HIERARCHY\nROOT Hips\n{\n")
    out = tmp_path / "job"
    argv = ["imitate", str(clips), "--out", str(out), "--minutes", "0.1", "--episodes", "2",
            "--num-envs", "8", "--no-screenshot", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    assert "left out of the job: cut (retargeting failed:" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "motions").glob("*.npz")) == ["run.npz", "walk.npz"]
    assert (out / "run" / "reference" / "library.yaml").read_text() == "- run.npz\n- walk.npz\n"
    report = json.loads((out / "report.json").read_text())
    assert set(report["retarget"]["clips"]) == {"run", "walk"}
    assert set(report["retarget"]["failed"]) == {"cut"} and report["train"]["left_out"] == []
    for label in ("nominal", "dr_default", "backpack", "worn_knees"):
        assert list(report["eval"][label]["clips"]) == ["run.npz", "walk.npz"]
    proto = report["eval"]["nominal"]["protocols"]
    assert proto["phc"]["clips"] == 2 and "protocols" not in report["eval"]["backpack"]
    md = (out / "report.md").read_text()
    assert "| walk.npz |" in md and "| run.npz |" in md and "failures_dr_default.png" in md
    for name in ("policy.onnx", "learning_curve.png", "body_error.png", "failures_dr_default.png"):
        assert (out / name).is_file(), name
    # Folders it cannot take: clips in a subfolder, robot motions beside human clips.
    (clips / "sub").mkdir()
    _short_bvh(shared_data / "cmu" / "35_01.bvh", clips / "sub" / "w.bvh", 20)
    assert main([*argv[:3], str(tmp_path / "job2"), *argv[4:]]) == 2
    assert "sub/w.bvh is in a subfolder" in capsys.readouterr().err
    assert not (tmp_path / "job2").exists()
