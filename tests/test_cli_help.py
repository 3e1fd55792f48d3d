"""Every subcommand says what it does, every flag has a help text, the registries' choices are
listed, and each parse starts from its own defaults."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterator
from pathlib import Path

import pytest
from tyro import _docstrings

from humimic.cli.main import commands, main, parse
from humimic.cli.retarget import RetargetCommand
from humimic.configs import RETARGET_CONFIGS, retarget_default, retarget_fast
from humimic.configs.choices import shipped_physics
from humimic.robots.registry import ROBOTS


def _dataclasses(tp: object, seen: set[type]) -> Iterator[type]:
    """The dataclasses reachable from a type: subcommands and nested configs."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        yield from _dataclasses(typing.get_args(tp)[0], seen)
    elif origin in (typing.Union, types.UnionType) or (origin is not None and origin is not type):
        for arg in typing.get_args(tp):
            yield from _dataclasses(arg, seen)
    elif isinstance(tp, type) and dataclasses.is_dataclass(tp) and tp not in seen:
        seen.add(tp)
        yield tp
        hints = typing.get_type_hints(tp, include_extras=True)
        for f in dataclasses.fields(tp):
            yield from _dataclasses(hints[f.name], seen)


CLASSES = list(_dataclasses(commands([]), set()))


def test_the_walk_finds_every_command() -> None:
    names = {c.__name__ for c in CLASSES}
    for expected in ("RetargetCommand", "TrainSettings", "SysidDiagnose", "RetargetConfig"):
        assert expected in names
    assert len(CLASSES) >= 20


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_flag_has_help(cls: type) -> None:
    doc = (cls.__doc__ or "").strip()
    assert doc and not doc.startswith(("What ", cls.__name__ + "(")), f"{cls.__name__}: {doc!r}"
    missing = [
        f.name
        for f in dataclasses.fields(cls)
        if not (_docstrings.get_field_docstring(cls, f.name, ()) or "").strip()
    ]
    assert not missing, f"{cls.__name__}: no help text for {missing}"


@pytest.mark.parametrize("argv", [["train", "--help"], ["sysid", "simulate", "--help"]])
def test_help_shows_the_texts(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "What ``humimic" not in out and "runs." not in out.splitlines()[2]


def _help(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


def test_retarget_help_lists_the_registered_robots_and_presets(
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = _help(["retarget"], capsys)
    assert {"g1", "t1"} <= set(ROBOTS)
    assert "--robot {" + ",".join(ROBOTS) + "}" in out
    assert "--preset {" + ",".join(RETARGET_CONFIGS) + "}" in out


def test_physics_choices_are_the_shipped_files(capsys: pytest.CaptureFixture[str]) -> None:
    from humimic.sim.physics import SHIPPED

    assert set(shipped_physics()) == set(SHIPPED)
    out = _help(["eval"], capsys)
    assert all(name in out for name in SHIPPED)


def test_train_help_lists_the_task_and_ppo_settings(capsys: pytest.CaptureFixture[str]) -> None:
    out = _help(["train"], capsys)
    for flag in ("--task.action-scale", "--task.episode-length-s", "--task.reward-weights",
                 "--ppo.learning-rate", "--ppo.actor-hidden-dims", "--ppo.entropy-coef"):  # fmt: skip
        assert flag in out, flag
    # The variant sets the observation groups, --num-steps-per-env the rollout: no second flag.
    assert "--ppo.obs-groups" not in out and "--ppo.num-steps-per-env" not in out


def test_a_preset_does_not_carry_over_to_the_next_parse() -> None:
    """--preset sets the base of the --ik.* flags for its own command line only."""
    argv = ["retarget", "walk.bvh", "--out", "m.npz"]
    fast = parse([*argv, "--preset", "fast"])
    assert fast.preset == "fast" and fast.ik == retarget_fast()
    assert parse([*argv, "--preset=fast", "--ik.stage2-iters", "4"]).ik.stage2_iters == 4
    # A command made in code after that parse (as ``humimic demo`` makes one) has the
    # default settings, and so does the next parse.
    made = RetargetCommand(inputs=(Path("walk.bvh"),), out=Path("m.npz"))
    assert made.preset == "default" and made.ik == retarget_default()
    again = parse(argv)
    assert again.preset == "default" and again.ik == retarget_default()
    assert retarget_fast() != retarget_default()
