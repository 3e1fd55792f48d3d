"""Error types. Every error a user can cause derives from :class:`HumimicError`."""

from __future__ import annotations


class HumimicError(Exception):
    """Root of all humimic errors."""


class InputError(HumimicError):
    """Bad user input (a file, an array, a name, a path). The CLI exits with code 2."""


class BvhParseError(InputError):
    """A BVH file is malformed or truncated."""

    def __init__(self, path: object, line: int | None, message: str) -> None:
        where = f"{path}:{line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {message}")
        self.path = path
        self.line = line


class MotionDataError(InputError):
    """An array of motion data is malformed (NaN, wrong shape, zero frames...)."""


class UnknownNameError(InputError):
    """A robot, joint, body or skeleton name is not known."""


class OutputPathError(InputError):
    """An output path cannot be written."""


class MapError(InputError):
    """A human-to-robot map file is invalid."""


class RetargetError(HumimicError):
    """Retargeting failed (e.g. the QP solver found no solution)."""


class MissingDependencyError(HumimicError):
    """An optional dependency is missing; the message carries the install hint."""


class FetchError(HumimicError):
    """Downloading data at run time failed."""


def first_line(e: BaseException, limit: int = 160) -> str:
    """An exception's message on one short line (torch's can span dozens; of a state dict
    that does not load, the line after its heading says what differs)."""
    lines = [line.strip() for line in str(e).strip().splitlines() if line.strip()]
    if len(lines) > 1 and lines[0].startswith("Error(s) in loading state_dict"):
        lines = lines[1:]
    text = lines[0] if lines else type(e).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."
