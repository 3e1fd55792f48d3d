"""The numbers on every command line, checked before any command runs: a flag that is NaN,
infinite or beyond any use (``1e308``, a 30-digit integer) is refused by name, whatever the
command, so that a new flag cannot let one through to the code that would overflow on it.
Each command's ``validate()`` then checks its own ranges (negative, zero, too large)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import fields, is_dataclass
from typing import Any

from humimic.errors import InputError

MAX_FLAG_MAGNITUDE = 1e6
"""Largest magnitude of a real-valued flag (as :data:`humimic.configs.retarget.MAX_SETTING`)."""
MAX_FLAG_INT = 2**32 - 1
"""Largest magnitude of an integer flag (a seed's range)."""


def number_flags(cmd: Any, prefix: str = "--") -> Iterator[tuple[str, int | float]]:
    """Every number a parsed command holds, with the flag that set it (``--ik.stage1-iters``;
    a tuple's items under its flag, a mapping's values as ``--task.reward-weights NAME``);
    nested settings are walked, booleans skipped."""
    for f in fields(cmd):
        flag = prefix + f.name.replace("_", "-")
        yield from _numbers(getattr(cmd, f.name), flag)


def _numbers(value: Any, flag: str) -> Iterator[tuple[str, int | float]]:
    if isinstance(value, bool):
        return
    if isinstance(value, int | float):
        yield flag, value
    elif is_dataclass(value) and not isinstance(value, type):
        yield from number_flags(value, flag + ".")
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _numbers(item, flag)
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _numbers(item, f"{flag} {key}")


def check_number_flags(cmd: Any) -> None:
    """Refuse a parsed command whose numbers are not finite or beyond
    :data:`MAX_FLAG_MAGNITUDE` (reals) or :data:`MAX_FLAG_INT` (integers).

    Raises:
        InputError: Names the flag and the value.
    """
    for flag, v in number_flags(cmd):
        if isinstance(v, int):
            if abs(v) > MAX_FLAG_INT:
                raise InputError(f"{flag} {v}: beyond any use (at most {MAX_FLAG_INT} in size)")
        elif not math.isfinite(v):
            raise InputError(f"{flag} {v}: must be a finite number")
        elif abs(v) > MAX_FLAG_MAGNITUDE:
            raise InputError(
                f"{flag} {v:g}: beyond any use (at most {MAX_FLAG_MAGNITUDE:g} in size)"
            )


def validate_command(cmd: Any) -> None:
    """Check a parsed command before it runs: its numbers (:func:`check_number_flags`), then
    its own ranges, ``validate()`` (every command with a number flag has one; a test walks
    them all with hostile values)."""
    check_number_flags(cmd)
    validate = getattr(cmd, "validate", None)
    if validate is not None:
        validate()
