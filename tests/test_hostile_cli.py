"""A hostile user's pass over the ``humimic`` commands: each bad input exits with code 2 and one
line naming the file or flag, writes nothing, and never replaces an input or a device.

Most settings are checked before any input is read, so these tests give a missing input: a
check that is not there lets the command go on and fail on that file instead.
"""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.errors import OutputPathError
from humimic.formats.mcap import McapWriter
from humimic.io import atomic_write_text, check_writable
from humimic.motion import motion_from_qpos, save_motion
from humimic.robots import get_robot, nominal_model


def _files(root: Path) -> set[str]:
    """Every file and folder under ``root`` (hidden temporary files included), relative."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str], *expect: str) -> str:
    """Run ``humimic argv``: exit code 2, one line on stderr naming each of ``expect``."""
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("humimic: error: ") and err.count("\n") == 1, err
    for part in expect:
        assert part in err, f"{part!r} not in {err!r}"
    return err


def _stand(path: Path, fps: float = 50.0, frames: int = 6) -> Path:
    """The G1 standing still, as a motion file."""
    m = nominal_model(get_robot("g1"))
    q = np.tile(m.key_qpos[0], (frames, 1))
    save_motion(motion_from_qpos(m, q, fps, "g1"), path)
    return path


# --- Outputs that are not regular files -------------------------------------------------------


def test_an_output_that_is_a_device_or_pipe_is_refused_not_replaced(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Writes rename a new file over the path: for /dev/null (or a pipe) that replaced the
    device with a regular file. A FIFO stands in for the device."""
    fifo = tmp_path / "report.json"
    os.mkfifo(fifo)
    with pytest.raises(OutputPathError, match="not a regular file"):
        check_writable(fifo)
    with pytest.raises(OutputPathError, match="not a regular file"):
        atomic_write_text(fifo, "{}\n")
    out = tmp_path / "out"
    bvh = shared_data / "cmu" / "35_01.bvh"
    argv = ["retarget", str(bvh), "--out", str(out / "m.npz"), "--report", str(fifo)]
    _refused(argv, capsys, str(fifo), "not a regular file")
    assert stat.S_ISFIFO(fifo.lstat().st_mode)  # Still the pipe.
    assert _files(tmp_path) == {"report.json"}


# --- Numbers out of range ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--dyn.samples", "99999999999999999999"], "dyn.samples"),
        (["--dyn.horizon-s", "1e308"], "--dyn.horizon-s 1e+308"),
        (["--dyn.horizon-s", "1000"], "dyn.horizon_s"),
        (["--dyn.noise", "1e308"], "dyn.noise"),
        (["--dyn.ensemble", "99999999999999999999"], "dyn.ensemble"),
        (["--dyn.seed", "-1"], "dyn.seed"),
        (["--robustness", "99999999999999999999"], "--robustness"),
        (["--backend", "warp", "--device", "bogus"], "--device"),
    ],
)
def test_refine_refuses_settings_that_crashed_or_never_ended(
    flags: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """These gave tracebacks (an array too large, an infinite horizon, NaN costs, a negative
    seed, a bad torch device) or ran for hours; now each is refused naming its flag."""
    argv = ["refine", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "r.npz"), *flags]
    _refused(argv, capsys, named)
    assert _files(tmp_path) == set()


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--ik.damping", "1e308"], "ik.damping"),
        (["--ik.smooth-weight", "1e20"], "--ik.smooth-weight 1e+20"),
        (["--ik.scale", "1e308"], "ik.scale"),
        (["--ik.contact-min-frames", "-1"], "ik.contact_min_frames"),
        (["--mesh.stick-weight", "1e308"], "--mesh.stick-weight 1e+308"),
    ],
)
def test_retarget_refuses_settings_beyond_any_use(
    flags: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A weight of 1e308 overflowed the QP (exit 1, "no solution", or overflow warnings and a
    motion); a negative contact length was taken silently."""
    argv = ["retarget", str(tmp_path / "missing.bvh"), "--out", str(tmp_path / "m.npz"), *flags]
    _refused(argv, capsys, named)
    assert _files(tmp_path) == set()


@pytest.mark.parametrize("tol", ["-1", "nan"])
def test_replay_refuses_a_tolerance_no_replay_meets(
    tol: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A negative or NaN --tol called every replay DIFFERENT (exit 1, as for a real failure)."""
    _refused(["replay", str(tmp_path / "missing.npz"), "--tol", tol], capsys, "--tol")


@pytest.mark.parametrize("duration", ["-1", "nan"])
def test_view_refuses_a_negative_or_nan_duration(
    duration: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The viewer started and stopped at once (exit 0) on these, as for --duration 0."""
    argv = ["view", str(tmp_path / "missing.npz"), "--duration", duration]
    _refused(argv, capsys, "--duration")


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--num-envs", "100000000"],
        ["train", "--num-steps-per-env", "100000000"],
        ["distill", "--num-envs", "99999999999999999999"],
        ["eval", "--episodes", "100000000"],
        ["eval", "--num-envs", "100000000"],
        ["loop", "--num-envs", "100000000"],
    ],
)
def test_tracking_commands_refuse_more_envs_than_memory_holds(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A huge --num-envs or rollout length was allocated at once: a traceback (maximum array
    dimension exceeded, or an allocation of 27 GiB) and, for train, an empty run folder."""
    cmd, flag, value = argv
    paths = {
        "train": ["--motion", str(tmp_path / "m.npz"), "--out", str(tmp_path / "run")],
        "distill": ["--teacher", str(tmp_path / "t"), "--out", str(tmp_path / "run")],
        "eval": [str(tmp_path / "run")],
        "loop": ["--run", str(tmp_path / "t"), "--real", "backpack", "--out", str(tmp_path / "l")],
    }[cmd]
    _refused([cmd, *paths, flag, value], capsys, flag, "at most")
    assert _files(tmp_path) == set()


# --- Folders and files a command would clobber --------------------------------------------------


@pytest.mark.parametrize("cmd", ["train", "distill"])
def test_a_new_run_does_not_overwrite_files_in_a_folder_that_is_no_run(
    cmd: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--out a user's folder holding a progress.csv (no config.yaml): a new run wrote its own
    progress.csv over it."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "progress.csv").write_text("my numbers\n")
    source = ["--motion", str(tmp_path / "m.npz")] if cmd == "train" else ["--teacher", "t"]
    _refused([cmd, *source, "--out", str(folder)], capsys, str(folder), "not empty")
    assert (folder / "progress.csv").read_text() == "my numbers\n"
    assert _files(tmp_path) == {"mine", "mine/progress.csv"}


def test_retarget_never_writes_into_an_input_folder(
    tmp_path: Path, shared_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``retarget DIR --out DIR/out`` wrote its motions and reports into the input folder."""
    clips = tmp_path / "clips"
    clips.mkdir()
    (clips / "walk.bvh").write_bytes((shared_data / "cmu" / "09_01.bvh").read_bytes())
    for out in (clips / "out", clips):
        _refused(
            ["retarget", str(clips), "--out", str(out)], capsys, "--out", "inside the input folder"
        )
    assert _files(tmp_path) == {"clips", "clips/walk.bvh"}


def _robot_folder_copy(root: Path) -> Path:
    """A copy of the G1's Menagerie folder (its XML files; the meshes linked, not copied)."""
    from humimic.robots.model import _nominal_spec

    _, _, scene = _nominal_spec(get_robot("g1"), None)
    root.mkdir()
    for f in scene.parent.glob("*.xml"):
        (root / f.name).write_bytes(f.read_bytes())
    (root / "assets").symlink_to(scene.parent / "assets")
    return root


def test_robots_export_never_writes_into_the_robot_folder_it_reads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--out ROBOT/g1.xml replaced the g1.xml that ROBOT/scene.xml includes (the folder then
    failed to load), and --out g1.xml beside a robot folder named g1_assets removed that folder
    to put the copied meshes there."""
    robot = _robot_folder_copy(tmp_path / "unitree_g1")
    before = {p.name: p.read_bytes() for p in robot.glob("*.xml")}
    argv = ["robots", "export", "g1", "--menagerie-root", str(robot)]
    _refused([*argv, "--out", str(robot / "g1.xml")], capsys, "--out", "robot model's folder")
    assert {p.name: p.read_bytes() for p in robot.glob("*.xml")} == before

    named = robot.rename(tmp_path / "g1_assets")
    argv = ["robots", "export", "g1", "--menagerie-root", str(named)]
    _refused([*argv, "--out", str(tmp_path / "g1.xml")], capsys, "--out", "robot model's folder")
    assert {p.name: p.read_bytes() for p in named.glob("*.xml")} == before
    assert (named / "assets").is_symlink()
    assert not (tmp_path / "g1.xml").exists()


def test_loop_out_that_is_a_file_or_cannot_be_made_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """--out a regular file or /dev/null raised NotADirectoryError; an --out whose folder
    cannot be created (under /proc) raised FileNotFoundError: tracebacks."""
    import humimic.tracking.runs as runs_module

    # The run folder is read before --out is checked: a stand-in run keeps this test fast.

    class _Run:
        variant = "beyondmimic"

    monkeypatch.setattr(runs_module, "run_config", lambda run: ({}, _Run()))
    monkeypatch.setattr(runs_module, "resolve_checkpoint", lambda run, given: (run, {}))
    afile = tmp_path / "afile"
    afile.write_text("x\n")
    base = ["loop", "--run", str(tmp_path / "run"), "--real", "backpack"]
    _refused([*base, "--out", str(afile)], capsys, "--out", "not a folder")
    assert afile.read_text() == "x\n"
    _refused([*base, "--out", "/dev/null"], capsys, "--out", "/dev/null")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)

    def fail(self: Path, *args: object, **kwargs: object) -> None:
        raise FileNotFoundError(2, "No such file or directory", str(self))

    monkeypatch.setattr(Path, "mkdir", fail)
    _refused([*base, "--out", str(tmp_path / "new")], capsys, "--out", "cannot create")
    assert _files(tmp_path) == {"afile"}


# --- Inputs that are not regular files ---------------------------------------------------------


def test_a_bvh_that_is_a_pipe_is_refused_without_reading_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pipe named .bvh was read (blocking until its writer closed; /dev/zero never ends and
    raised MemoryError). A writer thread keeps this test from blocking either way."""
    fifo = tmp_path / "clip.bvh"
    os.mkfifo(fifo)

    def writer() -> None:
        with open(fifo, "w") as f:
            f.write("HIERARCHY\n")

    t = threading.Thread(target=writer, daemon=True)
    t.start()
    try:
        argv = ["retarget", str(fifo), "--out", str(tmp_path / "m.npz")]
        _refused(argv, capsys, str(fifo), "not a regular file")
    finally:
        fd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # Lets a writer still waiting finish.
        t.join(5)
        os.close(fd)
    assert _files(tmp_path) == {"clip.bvh"}


# --- Writers ------------------------------------------------------------------------------------


def test_mcap_writer_fails_with_one_line_and_writes_usual_permissions(tmp_path: Path) -> None:
    """An MCAP whose folder cannot hold files raised FileNotFoundError from mkstemp (humimic
    eval --out /proc/m.json: a traceback); a wrong suffix made its folder first; the files
    were 0600 where every other output is 0666 less the umask."""
    with pytest.raises(OutputPathError, match=r"x\.mcap"):
        McapWriter("/proc/x.mcap")  # No file can be made in /proc.
    with pytest.raises(Exception, match=r"\.mcap"):
        McapWriter(tmp_path / "new" / "x.txt")
    assert not (tmp_path / "new").exists()
    with McapWriter(tmp_path / "log.mcap") as w:
        w.add_metadata("robot", {"name": "g1"})
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "log.mcap").stat().st_mode) == 0o666 & ~umask
    assert _files(tmp_path) == {"log.mcap"}


@pytest.mark.parametrize("cmd", ["simulate", "import"])
def test_an_mcap_write_cut_short_exits_2_with_one_line_and_no_file(
    cmd: str, tmp_path: Path
) -> None:
    """A write that fails mid-file (here a 64 KiB file size limit, as a full disk would)
    ended sysid simulate and sysid import in the MCAP writer's OSError traceback."""
    import subprocess
    import sys

    src = tmp_path / "low.npz"
    if cmd == "import":  # A Unitree low-state log of 2 s (the import's own test makes one).
        log = tmp_path / "seed.mcap"
        assert main(["sysid", "simulate", "--duration", "2", "--base", "floating",
                     "--out", str(log)]) == 0  # fmt: skip
        from humimic.real2sim.report import load_robot_log

        _, _, lg = load_robot_log(log)
        assert lg.imu is not None
        idx = lg.command_index(lg.t)
        np.savez(src, time=lg.t, q=lg.q, dq=lg.qd, cmd_q=lg.cmd_q[idx], cmd_dq=lg.cmd_qd[idx],
                 cmd_tau=lg.cmd_tau[idx], cmd_kp=lg.kp[idx], cmd_kd=lg.kd[idx],
                 quaternion=lg.imu.quat_w, gyroscope=lg.imu.gyro_b)  # fmt: skip
        log.unlink()
    out = tmp_path / "out.mcap"
    argv = (["sysid", "simulate", "--duration", "20", "--out", str(out)] if cmd == "simulate"
            else ["sysid", "import", str(src), "--out", str(out), "--base", "floating"])  # fmt: skip
    script = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536)); "
              "from humimic.cli.main import main; sys.exit(main(sys.argv[1:]))")  # fmt: skip
    r = subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True,
                       timeout=300)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("humimic: error: ") and r.stderr.count("\n") == 1, r.stderr
    assert str(out) in r.stderr and "cannot write" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == (["low.npz"] if cmd == "import" else [])


def test_refine_reports_rollouts_that_all_diverge_as_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """When every sampled rollout's cost is NaN, refine stopped on an AssertionError (a
    traceback); it is an optimizer failure: exit 1, one line, nothing written."""
    from humimic.retarget.dynamics import sampler

    motion = _stand(tmp_path / "stand.npz")
    monkeypatch.setattr(
        sampler.DynamicsRetargeter,
        "_costs",
        lambda self, states, sens, ctrl, f0: np.full(states.shape[0], np.nan),
    )
    out = tmp_path / "r.npz"
    argv = ["refine", str(motion), "--out", str(out), "--dyn.samples", "4",
            "--dyn.iterations", "1", "--dyn.horizon-s", "0.1", "--dyn.commit-s", "0.05",
            "--dyn.polish-iterations", "0", "--robustness", "0", "--quiet"]  # fmt: skip
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.startswith("humimic: error: ") and err.count("\n") == 1, err
    assert "diverged" in err
    assert _files(tmp_path) == {"stand.npz"}
