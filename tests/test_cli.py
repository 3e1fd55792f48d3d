"""The ``humimic`` command line: exit codes, messages and no half-written outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import mujoco
import numpy as np
import pytest
import tyro

import humimic.configs
from humimic.cli.main import main
from humimic.configs import RETARGET_CONFIGS, RetargetConfig
from humimic.motion import load_motion

REPORT_KEYS = (
    "frames",
    "fps",
    "frames_per_second",
    "keypoint_error_mm_mean",
    "keypoint_error_mm_p95",
    "foot_skating_mm_per_s",
    "max_ground_penetration_mm",
    "joint_limit_violations",
    "self_collision_frames",
    "mean_joint_jerk",
)


def _files(root: Path) -> set[str]:
    """Every regular file under ``root`` (hidden temp files included), relative."""
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def _trimmed_bvh(src: Path, dst: Path, frames: int) -> Path:
    """Copy the header of ``src`` and its first ``frames`` frames, fixing the Frames: line."""
    lines = src.read_bytes().decode().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("Frames:"))
    assert lines[i + 1].startswith("Frame Time:")
    body = lines[i + 2 :]
    assert len(body) >= frames
    newline = "\r\n" if lines[i].endswith("\r\n") else "\n"
    dst.write_bytes(
        "".join([*lines[:i], f"Frames: {frames}{newline}", lines[i + 1], *body[:frames]]).encode()
    )
    return dst


def _climb_npy(shared_data: Path) -> Path:
    return sorted((shared_data / "holosoma_climb").glob("*/*_joint_positions_*.npy"))[0]


@dataclass(frozen=True)
class Case:
    """A bad-input case: the inputs it makes, the argv, and what stderr must name."""

    argv: list[str]
    expect: list[str]


def _case_truncated_bvh(tmp: Path, data: Path) -> Case:
    lines = (data / "cmu" / "35_01.bvh").read_bytes().splitlines(keepends=True)
    src = tmp / "in" / "truncated.bvh"
    src.write_bytes(b"".join(lines[: int(0.6 * len(lines))]))
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["truncated.bvh", "truncated"],
    )


def _case_bad_number_bvh(tmp: Path, data: Path) -> Case:
    lines = (data / "cmu" / "35_01.bvh").read_bytes().decode().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("Frame Time:"))
    bad = i + 1 + 5  # the sixth frame
    fields = lines[bad].split(" ")
    fields[4] = "1.2.3"
    lines[bad] = " ".join(fields)
    src = tmp / "in" / "badnum.bvh"
    src.write_bytes("".join(lines).encode())
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        [f"badnum.bvh:{bad + 1}", "'1.2.3'"],
    )


def _case_nan_npy(tmp: Path, data: Path) -> Case:
    arr = np.load(_climb_npy(data), allow_pickle=False)[:60].copy()
    arr[17, 5, 1] = np.nan
    src = tmp / "in" / "nan.npy"
    np.save(src, arr)
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["nan.npy", "NaN", "frame 17"],
    )


def _case_zero_frames(tmp: Path, data: Path) -> Case:
    src = tmp / "in" / "empty.npy"
    np.save(src, np.zeros((0, 53, 3), dtype=np.float32))
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["empty.npy", "zero frames"],
    )


def _case_unknown_suffix(tmp: Path, data: Path) -> Case:
    src = tmp / "in" / "walk.txt"
    src.write_text("HIERARCHY\n")
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["walk.txt", "'.txt'", ".bvh"],
    )


def _case_missing_input(tmp: Path, data: Path) -> Case:
    return Case(
        ["retarget", str(tmp / "in" / "ghost.bvh"), "--out", str(tmp / "out" / "m.npz")],
        ["ghost.bvh", "no such file"],
    )


def _case_unwritable_output(tmp: Path, data: Path) -> Case:
    src = _trimmed_bvh(data / "cmu" / "35_01.bvh", tmp / "in" / "walk.bvh", 20)
    (tmp / "out").mkdir()
    (tmp / "out" / "afile").write_text("a regular file\n")
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "afile" / "m.npz")],
        ["afile"],
    )


def _case_out_not_npz(tmp: Path, data: Path) -> Case:
    src = _trimmed_bvh(data / "cmu" / "35_01.bvh", tmp / "in" / "walk.bvh", 20)
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.json")],
        ["m.json", ".npz"],
    )


def _case_unknown_joint_names(tmp: Path, data: Path) -> Case:
    src = _trimmed_bvh(data / "cmu" / "35_01.bvh", tmp / "in" / "walk.bvh", 20)
    src.write_text(src.read_text().replace("LeftUpLeg", "LeftThigh"))
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["skeletons/cmu.yaml", "keypoints.left_hip.human", "'LeftUpLeg'", "LeftThigh"],
    )


def _case_capture_dropout(tmp: Path, data: Path) -> Case:
    arr = np.load(_climb_npy(data), allow_pickle=False)[:300].copy()
    arr[140:160] = 0.0  # A dropout: every joint at the origin.
    src = tmp / "in" / "dropout.npy"
    np.save(src, arr)
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["dropout.npy", "t = 1.1"],
    )


def _case_corrupt_npz(tmp: Path, data: Path) -> Case:
    src = tmp / "in" / "broken.npz"
    src.write_bytes(b"PK\x03\x04" + b"\x00" * 40)
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz")],
        ["broken.npz", "not a readable"],
    )


def _case_bad_ik_setting(tmp: Path, data: Path) -> Case:
    src = _trimmed_bvh(data / "cmu" / "35_01.bvh", tmp / "in" / "walk.bvh", 20)
    return Case(
        ["retarget", str(src), "--out", str(tmp / "out" / "m.npz"), "--ik.max-step", "0"],
        ["ik.max_step", "positive"],
    )


def _case_same_output_name(tmp: Path, data: Path) -> Case:
    for sub in ("a", "b"):
        (tmp / "in" / sub).mkdir()
        _trimmed_bvh(data / "cmu" / "35_01.bvh", tmp / "in" / sub / "walk.bvh", 20)
    return Case(
        ["retarget", str(tmp / "in" / "a" / "walk.bvh"), str(tmp / "in" / "b" / "walk.bvh"),
         "--out", str(tmp / "out")],
        ["walk.bvh", "both be written as walk.npz"],
    )  # fmt: skip


CASES: dict[str, Callable[[Path, Path], Case]] = {
    "capture_dropout": _case_capture_dropout,
    "corrupt_npz": _case_corrupt_npz,
    "bad_ik_setting": _case_bad_ik_setting,
    "same_output_name": _case_same_output_name,
    "unknown_joint_names": _case_unknown_joint_names,
    "truncated_bvh": _case_truncated_bvh,
    "bad_number_bvh": _case_bad_number_bvh,
    "nan_npy": _case_nan_npy,
    "zero_frames_npy": _case_zero_frames,
    "unknown_suffix": _case_unknown_suffix,
    "missing_input": _case_missing_input,
    "unwritable_output": _case_unwritable_output,
    "out_not_npz": _case_out_not_npz,
}


def _make_case(name: str, tmp_path: Path, shared_data: Path) -> tuple[Case, set[str]]:
    (tmp_path / "in").mkdir()
    case = CASES[name](tmp_path, shared_data)
    return case, _files(tmp_path)


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_exits_2_with_message_and_no_output(
    name: str, tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    case, before = _make_case(name, tmp_path, shared_data)
    code = main(case.argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("humimic: error: ")
    assert "Traceback" not in err
    for part in case.expect:
        assert part in err, f"{part!r} not in {err!r}"
    # No output and no temporary file anywhere: only the inputs the test made.
    assert _files(tmp_path) == before
    out = tmp_path / "out"
    assert not out.exists() or all(p.is_dir() or p.name == "afile" for p in out.rglob("*"))


def _humimic_command() -> list[str]:
    script = Path(sys.executable).with_name("humimic")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "humimic.cli.main"]


@pytest.mark.parametrize("name", ["nan_npy", "unwritable_output"])
def test_console_script_exit_code_and_no_traceback(
    name: str, tmp_path: Path, shared_data: Path
) -> None:
    case, before = _make_case(name, tmp_path, shared_data)
    proc = subprocess.run(
        [*_humimic_command(), *case.argv], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    for part in case.expect:
        assert part in proc.stderr
    assert _files(tmp_path) == before


# --- Success -----------------------------------------------------------------------------------


def test_retarget_cmu_walk_writes_motion_and_report(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", tmp_path / "walk40.bvh", 40)
    out = tmp_path / "out"
    argv = ["retarget", str(src), "--out", str(out / "walk.npz")]
    code = main([*argv, "--report", str(out / "walk.json"), "--quiet"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "Traceback" not in captured.err
    assert _files(out) == {"walk.npz", "walk.json"}  # no temp files left
    report = json.loads((out / "walk.json").read_text())
    missing = [k for k in REPORT_KEYS if k not in report]
    assert not missing, missing
    assert report["fps"] == 50.0
    # 40 source frames at 120 fps, the T-pose frame 0 skipped: 39 frames = 0.3167 s -> 16 at 50.
    assert report["frames"] == 16
    assert report["start_frame"] == 1
    assert np.isfinite(report["keypoint_error_mm_mean"])
    assert report["keypoint_error_mm_p95"] >= report["keypoint_error_mm_mean"] >= 0.0
    motion = load_motion(out / "walk.npz")
    assert motion.robot == "g1"
    assert motion.num_frames == report["frames"]
    assert motion.fps == 50.0
    assert "walk.npz" in captured.out


def test_robots_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["robots", "list"]) == 0
    out = capsys.readouterr().out
    names = [line.split()[0] for line in out.splitlines() if line.strip()]
    assert {"g1", "t1"} <= set(names)


def test_robots_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "X.xml"
    assert main(["robots", "export", "g1", "--out", str(out)]) == 0
    assert "X.xml" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["X.xml", "X_assets"]
    model = mujoco.MjModel.from_xml_path(str(out))
    assert model.nu == 29


@pytest.mark.parametrize(
    ("argv", "out"),
    [
        (["robots", "export", "nope"], "X.xml"),
        (["retarget", "walk.bvh", "--robot", "nope"], "m.npz"),
    ],
    ids=["robots export", "retarget"],
)
def test_unknown_robot_is_a_parse_error(
    argv: list[str], out: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Robot names are the registry's choices: another is refused before anything runs
    (exit 2), and the message lists the registered robots."""
    with pytest.raises(SystemExit) as info:
        main([*argv, "--out", str(tmp_path / out)])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and "g1" in err and "t1" in err
    assert list(tmp_path.iterdir()) == []


# --- Configs and parsing -----------------------------------------------------------------------


def _config_factories() -> dict[str, Callable[[], RetargetConfig]]:
    factories: dict[str, Callable[[], RetargetConfig]] = {
        f"registry:{k}": f for k, f in RETARGET_CONFIGS.items()
    }
    for name in humimic.configs.__all__:
        obj = getattr(humimic.configs, name)
        if name.startswith("retarget_") and callable(obj):
            factories[f"configs:{name}"] = cast(Callable[[], RetargetConfig], obj)
    return factories


def test_config_factories_are_found() -> None:
    names = set(_config_factories())
    assert {"configs:retarget_default", "configs:retarget_fast"} <= names
    assert {f"registry:{k}" for k in RETARGET_CONFIGS} <= names


@pytest.mark.parametrize("name", sorted(_config_factories()))
def test_every_registered_default_parses(name: str) -> None:
    factory = _config_factories()[name]
    default = factory()
    assert isinstance(default, RetargetConfig)
    assert tyro.cli(RetargetConfig, default=default, args=[]) == default


def test_config_override_from_command_line() -> None:
    cfg = tyro.cli(
        RetargetConfig, default=humimic.configs.retarget_fast(), args=["--stage2-iters", "7"]
    )
    assert cfg.stage2_iters == 7
    assert cfg.first_frame_iters == humimic.configs.retarget_fast().first_frame_iters


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["retarget"],
        ["demo"],
        ["robots"],
        ["robots", "list"],
        ["robots", "export"],
        ["fetch"],
    ],
    ids=lambda a: " ".join(a) or "top",
)
def test_help_exits_0(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([*argv, "--help"])
    assert info.value.code == 0
    assert "usage" in capsys.readouterr().out.lower()


def test_parse_error_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["retarget", "clip.bvh"])  # --out is required
    assert info.value.code == 2
    assert "--out" in capsys.readouterr().err


def test_preset_is_the_base_of_ik_flags(tmp_path: Path, shared_data: Path) -> None:
    """--ik.* flags set on top of --preset, even to the value of the default preset."""
    src = _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", tmp_path / "walk.bvh", 40)
    out = tmp_path / "m.npz"
    argv = ["retarget", str(src), "--out", str(out), "--quiet", "--preset", "fast"]
    assert main([*argv, "--report", str(tmp_path / "fast.json")]) == 0
    fast = json.loads((tmp_path / "fast.json").read_text())
    assert main([*argv, "--report", str(tmp_path / "f4.json"), "--ik.stage2-iters", "4"]) == 0
    f4 = json.loads((tmp_path / "f4.json").read_text())
    # fast allows 1 + 1 QPs per frame after the first; with stage2_iters 4 it may use more.
    assert f4["qp_iterations_per_frame"] > fast["qp_iterations_per_frame"]


def test_report_is_strict_json(tmp_path: Path, shared_data: Path) -> None:
    """A clip with no foot contact has no 'in contact' height: null, never NaN."""
    arr = np.load(_climb_npy(shared_data), allow_pickle=False)[:40].copy()
    arr[:, :, 2] += np.linspace(0.0, 0.3, 40)[:, None]  # Rising: the feet never rest.
    arr[:, :, 0] += np.linspace(0.0, 1.2, 40)[:, None]  # ...and they move.
    src = tmp_path / "flying.npy"
    np.save(src, arr)
    report = tmp_path / "r.json"
    assert main(["retarget", str(src), "--out", str(tmp_path / "m.npz"), "--report",
                 str(report), "--quiet"]) == 0  # fmt: skip
    text = report.read_text()
    assert "NaN" not in text
    assert json.loads(text)["median_lowest_foot_in_contact_mm"] is None


def test_folder_outputs_keep_relative_names(tmp_path: Path, shared_data: Path) -> None:
    root = tmp_path / "clips"
    (root / "a").mkdir(parents=True)
    (root / "b").mkdir()
    _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", root / "a" / "walk.bvh", 20)
    _trimmed_bvh(shared_data / "cmu" / "35_01.bvh", root / "b" / "walk.bvh", 20)
    out = tmp_path / "out"  # Outside the input folder (inside it is refused).
    for _ in range(2):
        assert main(["retarget", str(root), "--out", str(out), "--quiet"]) == 0
    assert (out / "a" / "walk.npz").is_file() and (out / "b" / "walk.npz").is_file()
    assert (out / "a" / "walk.json").is_file()
    mode = (out / "a" / "walk.npz").stat().st_mode & 0o777
    assert mode & 0o044, f"outputs must be readable by others (umask permitting): {oct(mode)}"


def test_a_closed_output_pipe_ends_quietly() -> None:
    """``humimic ... --help | head -1``: the reader has closed the pipe; humimic stops
    without a traceback, with the shell's SIGPIPE code."""
    import os

    read, write = os.pipe()
    os.close(read)  # Closed before humimic writes: every write to stdout fails.
    try:
        proc = subprocess.run([*_humimic_command(), "refine", "--help"], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=60)  # fmt: skip
    finally:
        os.close(write)
    assert proc.returncode == 141, proc.stderr
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr
