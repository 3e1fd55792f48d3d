"""Every number flag of every ``humimic`` command, walked with a shared table of hostile
values: each is refused before the command reads or writes anything (the parser's exit 2,
or one :class:`InputError` naming the flag), unless this file says why the value is valid.

The flags come from the command types themselves, so a new flag or command is walked too;
one this file cannot give a value (a new kind of type) fails the walk by name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import types
import typing
from pathlib import Path
from typing import Any

import pytest

from humimic.cli.flags import validate_command
from humimic.cli.main import RUNNERS, main, parse
from humimic.errors import InputError

HOSTILE = ("-1", "0", "nan", "inf", "-inf", "1e308", "100000000000000000000")
"""Negative, zero, NaN, infinities, the largest double, an integer beyond any use."""

BASE: dict[str, list[str]] = {
    "RetargetCommand": ["retarget", "clip.bvh", "--out", "o.npz"],
    "RefineCommand": ["refine", "m.npz", "--out", "o.npz"],
    "ReplayCommand": ["replay", "m.npz"],
    "DemoSettings": ["demo"],
    "ConvertCommand": ["convert", "m.npz", "m.mcap"],
    "ViewCommand": ["view", "m.npz"],
    "RobotsList": ["robots", "list"],
    "RobotsExport": ["robots", "export", "g1", "--out", "g1.xml"],
    "RobotsAdd": ["robots", "add", "bot.urdf", "--name", "bot"],
    "SysidSimulate": ["sysid", "simulate", "--out", "l.mcap"],
    "SysidResidual": ["sysid", "residual", "l.mcap"],
    "SysidDiagnose": ["sysid", "diagnose", "l.mcap", "--out-dir", "d"],
    "SysidImport": ["sysid", "import", "s.npz", "--out", "l.mcap"],
    "FetchCommand": ["fetch"],
    "TrainSettings": ["train", "--motion", "m.npz", "--out", "run"],
    "DistillSettings": ["distill", "--teacher", "run", "--out", "student"],
    "EvalSettings": ["eval", "run"],
    "ExportSettings": ["export", "run"],
    "LoopSettings": ["loop", "--run", "run", "--real", "worn_knees", "--out", "loop"],
    "ImitateSettings": ["imitate", "clip.bvh", "--out", "job"],
}
"""A command line of each command with its required arguments (the files need not exist:
numbers are checked before anything is read)."""

_OFF = {"0"}
"""A weight, scale, tolerance, count or noise of 0: that part off (or none of it)."""
_DYN = {f"--dyn.{n}": _OFF for n in (
    "min-improvement", "noise", "horizon-noise", "upper-body-noise", "body-weight",
    "root-weight", "joint-weight", "velocity-weight", "foot-weight", "effort-weight",
    "feedforward", "polish-iterations", "fall-tilt", "fall-cost", "ensemble")} | {
    "--dyn.seed": {"0"},  # Seeds start at 0.
}  # fmt: skip
VALID: dict[str, dict[str, set[str]]] = {
    "RetargetCommand": {
        "--start": {"0"},  # The first frame.
        **{
            f"--ik.{n}": _OFF
            for n in (
                "damping",
                "tol",
                "stage1-position-scale",
                "stage2-orientation-scale",
                "contact-weight-scale",
                "foot-orientation-weight",
                "foot-contact-orientation-weight",
                "velocity-limit-scale",
                "collision-margin",
                "smooth-weight",
                "repair-iters",
                "contact-min-frames",
                "first-frame-iters",
            )
        },
        # One stage may be skipped (the other one still runs: both 0 are refused).
        "--ik.stage1-iters": _OFF,
        "--ik.stage2-iters": _OFF,
        # Detect self-collision only at contact (retargets a walk: tried by hand).
        "--ik.collision-detection": _OFF,
        # A height: the clip's floor may be below its world origin, or at it.
        "--ik.floor-height": {"-1", "0"},
        **{
            f"--mesh.{n}": _OFF
            for n in (
                "mesh-weight",
                "keypoint-scale",
                "max-scene-points",
                "tol",
                "penetration-margin",
                "stick-weight",
                "stick-height-scale",
                "contact-weight",
                "smooth-weight",
                "reattach-iterations",
                "contact-gap",
                "still-speed",
            )
        },
        **_DYN,
    },
    "RefineCommand": {**_DYN, "--robustness": _OFF},
    "ReplayCommand": {"--tol": {"0"}},  # Bit-for-bit replay.
    "ViewCommand": {
        "--port": {"0"},  # Any free port.
        "--frame": {"0"},  # The first frame.
        "--duration": {"0"},  # Start, then stop (a smoke test of the viewer).
    },
    "SysidSimulate": {"--seed": {"0"}, "--imu-tilt": {"0"}},  # An IMU mounted straight.
    # Positions and quaternion components are signed; the quaternion's norm is checked
    # when the robot is known.
    "SysidImport": {"--base-pose": {"-1", "0"}},
    "TrainSettings": {
        "--seed": {"0"},
        "--task.reward-weights": {"-1", "0"},  # Penalties are negative; 0 turns a term off.
        "--task.feedback-delay": {"0"},  # No latency.
        "--task.dr-replay": {"0"},  # No replay.
        "--ppo.actor-output-gain": {"0"},  # A policy that starts at the action base.
        "--ppo.critic-warmup-iterations": {"0"},
        "--ppo.entropy-coef": {"0"},
        "--ppo.value-loss-coef": {"0"},
    },
    "DistillSettings": {"--seed": {"0"}},
    "EvalSettings": {"--seed": {"0"}},
    "LoopSettings": {"--seed": {"0"}},
    "ImitateSettings": {"--seed": {"0"}},
}
"""Command -> flag -> the hostile values that are valid settings, and why. Every other
hostile value of every number flag must be refused."""


def _numeric(t: Any) -> tuple[str, int] | None:
    """How a flag of type ``t`` takes a number: ``("scalar", 1)``, ``("tuple", n)`` (n
    copies; 1 for a variable tuple) or ``("dict", 1)`` (a key and a value); None: no number."""
    while typing.get_origin(t) is typing.Annotated:
        t = typing.get_args(t)[0]
    if typing.get_origin(t) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(t) if a is not type(None)]
        return _numeric(inner[0]) if len(inner) == 1 else None
    if t in (int, float):
        return ("scalar", 1)
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is tuple and args and all(a in (int, float) or a is Ellipsis for a in args):
        return ("tuple", 1 if Ellipsis in args else len(args))
    if origin is dict and args[1] in (int, float):
        return ("dict", 1)
    return None


def _flags(cls: type, prefix: str = "--") -> list[tuple[str, tuple[str, int]]]:
    """Each number flag of a command type (nested settings walked) and how it takes a value."""
    out = []
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        bare = t
        while typing.get_origin(bare) is typing.Annotated:
            bare = typing.get_args(bare)[0]
        flag = prefix + f.name.replace("_", "-")
        if dataclasses.is_dataclass(bare):
            out += _flags(typing.cast(type, bare), flag + ".")
        elif (how := _numeric(t)) is not None:
            out.append((flag, how))
    return out


CASES = [
    pytest.param(cls.__name__, flag, how, id=f"{cls.__name__}{flag}")
    for cls in RUNNERS
    for flag, how in _flags(cls)
]


def _argv(name: str, flag: str, how: tuple[str, int], value: str) -> list[str]:
    kind, n = how
    given = ["body_pos", value] if kind == "dict" else [value] * n
    return [*BASE[name], flag, *given]


def _outcome(argv: list[str]) -> str:
    """``parser`` (exit 2 from parsing), ``refused: MESSAGE`` or ``accepted``."""
    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            cmd = parse(argv)
    except SystemExit as e:
        assert e.code == 2, argv
        return "parser"
    try:
        validate_command(cmd)
    except InputError as e:
        return f"refused: {e}"
    return "accepted"


def test_every_command_has_a_command_line_here() -> None:
    assert sorted(BASE) == sorted(cls.__name__ for cls in RUNNERS)
    for argv in BASE.values():
        assert _outcome(argv) == "accepted", argv


@pytest.mark.parametrize(("name", "flag", "how"), CASES)
def test_hostile_values_of_every_number_flag_are_refused_by_name(
    name: str, flag: str, how: tuple[str, int]
) -> None:
    valid = VALID.get(name, {}).get(flag, set())
    for value in HOSTILE:
        out = _outcome(_argv(name, flag, how, value))
        if value in valid:
            assert out == "accepted", (flag, value, out)
        elif out.startswith("refused"):
            named = out.replace("_", "-")
            assert flag[2:].split(" ")[0] in named, (flag, value, out)
            assert "\n" not in out
        else:
            assert out == "parser", (flag, value, out)


@pytest.mark.parametrize(
    "argv",
    [
        ["sysid", "residual", "l.mcap", "--horizon", "1e308"],
        ["sysid", "diagnose", "l.mcap", "--out-dir", "d", "--horizon", "1e308"],
        ["sysid", "simulate", "--out", "l.mcap", "--seed", "-1"],
        ["sysid", "simulate", "--out", "l.mcap", "--inject", "payload_mass:torso_link=1e308"],
        ["imitate", "clip.bvh", "--out", "job", "--minutes", "1e308"],
        ["train", "--motion", "m.npz", "--out", "run", "--max-minutes", "inf"],
        ["view", "m.npz", "--duration", "1e308"],
        ["retarget", "clip.bvh", "--out", "o.npz", "--ik.stage1-iters", "100000"],
        ["refine", "m.npz", "--out", "o.npz", "--dyn.elites", "100000"],
    ],
)
def test_the_reported_tracebacks_and_runaway_settings_exit_2_leaving_nothing(
    argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """The commands of the hostile pass that ended in a traceback (OverflowError, MuJoCo's
    inertia, JSON's out-of-range floats; MUJOCO_LOG.TXT left behind) or ran on
    (1e308 s, an iteration budget beyond any use): one line, exit 2, nothing in the folder."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("humimic: error: ") and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []
