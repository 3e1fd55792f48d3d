"""Every subcommand says what it does, and every flag has a help text."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterator

import pytest
from tyro import _docstrings

from humimic.cli.main import Commands, main


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


CLASSES = list(_dataclasses(Commands, set()))


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
