"""File helpers: atomic writes (an interrupted run never leaves a half file that looks whole)
and reading YAML with errors that name the file."""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from humimic.errors import InputError, OutputPathError


def check_writable(path: str | os.PathLike[str]) -> Path:
    """Fail early, before any work, when ``path`` cannot be written.

    Creates missing parent folders. Raises :class:`OutputPathError` naming the path.
    """
    p = Path(path)
    if p.exists() and p.is_dir():
        raise OutputPathError(f"{p}: is a folder, expected a file path")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"{p}: cannot create folder {p.parent}: {e.strerror}") from e
    if not os.access(p.parent, os.W_OK):
        raise OutputPathError(f"{p}: folder {p.parent} is not writable")
    return p


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success.

    The file gets the usual permissions (0666 less the umask). Operating-system errors become
    :class:`OutputPathError` naming the path; the temporary file is removed on any failure.
    """
    p = check_writable(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as e:
        raise OutputPathError(f"{p}: cannot write here: {e.strerror}") from None
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, p)
    except OSError as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise OutputPathError(f"{p}: cannot write: {e.strerror or e}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_write(path, "w") as f:
        f.write(text)


def json_ready(value: Any) -> Any:
    """NaN and infinities become null (reports are strict JSON); tuples become lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    return value


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """The parsed contents of a YAML file (``None`` for an empty one).

    Raises:
        InputError: The file is missing, unreadable or not valid YAML (names the file).
    """
    import yaml

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    try:
        return yaml.safe_load(p.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: cannot read: {e}") from None
    except yaml.YAMLError as e:
        raise InputError(f"{p}: not valid YAML ({e})") from None
