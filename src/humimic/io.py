"""File helpers: atomic writes (an interrupted run never leaves a half file that looks whole)
and reading YAML with errors that name the file."""

from __future__ import annotations

import contextlib
import functools
import math
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

from humimic.errors import InputError, OutputPathError


def check_writable(path: str | os.PathLike[str], *, create: bool = False) -> Path:
    """Fail early, before any work, when ``path`` cannot be written.

    Args:
        path: The file to be written.
        create: Create the missing parent folders now (for a writer that needs them at
            once). Otherwise nothing is created: the nearest existing folder above ``path``
            must be writable, and :func:`atomic_write` makes the rest when it writes, so a
            command that fails later leaves no empty folder behind.

    Raises:
        OutputPathError: ``path`` is a folder or not a regular file (a device such as
            /dev/null, which the rename would replace), a file stands where a folder must
            be, or the folder is not writable (names the path).
    """
    p = Path(path)
    if p.is_dir():
        raise OutputPathError(f"{p}: is a folder, expected a file path")
    if p.exists() and not p.is_file():
        # The write renames a new file over the path: that would replace a device such as
        # /dev/null, a pipe or a socket with a regular file.
        raise OutputPathError(f"{p}: not a regular file (a device, pipe or socket); choose a file")
    if create:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputPathError(f"{p}: cannot create folder {p.parent}: {e.strerror}") from e
    base = p.parent
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise OutputPathError(f"{p}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputPathError(f"{p}: folder {base} is not writable")
    return p


def check_not_input(
    output: str | os.PathLike[str] | None,
    inputs: Mapping[str, str | os.PathLike[str] | None],
    flag: str,
) -> None:
    """Refuse an output path that names one of the command's inputs (or another output).

    Args:
        output: The output path (``None``: nothing to check).
        inputs: What the output must not overwrite: a label (the flag or argument that gave
            it, e.g. ``"the motion"`` or ``"--out"``) -> its path. Paths are compared
            resolved, so ``./a.npz`` and ``/abs/a.npz`` are the same file.
        flag: The output's flag, for the message (e.g. ``"--report"``).

    Raises:
        OutputPathError: The output resolves to an input's path.
    """
    if output is None:
        return
    out = _resolved(output, flag)
    for label, path in inputs.items():
        if path is None:
            continue
        if out == _resolved(path, label):
            raise OutputPathError(
                f"{flag} {output}: would overwrite {label} ({path}); choose another path"
            )


def _resolved(path: str | os.PathLike[str], label: str) -> Path:
    """The absolute path with links followed; a link loop is bad input, not a crash."""
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError) as e:
        raise InputError(f"{label} {path}: cannot resolve the path ({e})") from None


def check_input_file(path: str | os.PathLike[str], what: str) -> Path:
    """``path`` as a :class:`Path` if it is a regular file; otherwise one line saying what it
    is instead (missing, a folder, a pipe or device), before anything opens it (a FIFO
    would block the reader).

    Args:
        path: The input.
        what: What was expected, for the message (``"a motion file"``).

    Raises:
        InputError: Names the path.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a folder, expected {what}")
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file (a pipe or device), expected {what}")
    return p


def file_mode() -> int:
    """The permissions of a new file: 0666 less the umask (what ``open`` would give)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success.

    The file gets the usual permissions (0666 less the umask). Operating-system errors become
    :class:`OutputPathError` naming the path; the temporary file is removed on any failure.
    """
    p = check_writable(path, create=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as e:
        raise OutputPathError(f"{p}: cannot write here: {e.strerror}") from None
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.chmod(tmp, file_mode())
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


@functools.cache
def _unique_key_loader() -> Any:
    """PyYAML's ``SafeLoader``, refusing a mapping that names a key twice (which keeps the
    last value in silence: ``floor_friction: 0.2`` then ``floor_friction: 1.0``)."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node: Any, deep: bool = False) -> Any:
            seen: set[tuple[str, str]] = set()
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag.endswith(":merge"):
                    continue  # Merge keys (<<) may repeat what they merge in.
                key = (key_node.tag, key_node.value)
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"the key {key_node.value!r} appears twice",
                        key_node.start_mark,
                    )  # fmt: skip
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def read_yaml(
    path: str | os.PathLike[str], *, max_depth: int = 64, max_values: int = 1_000_000
) -> Any:
    """The parsed contents of a YAML file (``None`` for an empty one).

    Hostile files are refused, never crash: a tree nested deeper than ``max_depth`` (a deep
    file exhausts the parser's recursion, and code that walks the result recurses too), an
    alias that contains itself, or aliases that expand to more than ``max_values`` values
    (a "billion laughs" file is small but expands to gigabytes when walked).

    Args:
        path: The YAML file.
        max_depth: Most levels of nested mappings and lists accepted.
        max_values: Most values accepted, counting each alias as a copy of what it names.

    Raises:
        InputError: The file is missing, unreadable, not valid YAML, nested too deeply, recursive
            or too large once its aliases are expanded (the message names the file).
    """
    p = check_input_file(path, "a YAML file")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    data = _parse_yaml(p, text, max_depth)
    _check_yaml_tree(p, data, max_depth, max_values)
    return data


def _too_deep(p: Path, max_depth: int) -> InputError:
    """The refusal of a YAML file nested deeper than ``max_depth``."""
    return InputError(
        f"{p}: nested too deeply (more than {max_depth} levels of mappings and lists)"
    )


def _parse_yaml(p: Path, text: str, max_depth: int) -> Any:
    """``text`` parsed by :func:`_unique_key_loader` (a ``SafeLoader``: no Python objects),
    its ``[ ]`` and ``{ }`` nesting bounded by ``max_depth`` first.

    PyYAML's scanner takes time quadratic in the depth of that nesting (minutes for a small
    hostile file), and its parser recurses once per level of any nesting.

    Raises:
        InputError: Nested too deeply, or not valid YAML (PyYAML's message on one line).
    """
    import re

    import yaml

    # Brackets inside quoted text count too: a false refusal needs more than max_depth
    # unclosed ones.
    flow = deepest = 0
    for m in re.finditer(r"[\[\]{}]", text):
        flow = flow + 1 if m.group() in "[{" else max(flow - 1, 0)
        deepest = max(deepest, flow)
    if deepest > max_depth:
        raise _too_deep(p, max_depth)
    try:
        return yaml.load(text, Loader=_unique_key_loader())  # A SafeLoader: no Python objects.
    except RecursionError:
        raise _too_deep(p, max_depth) from None
    except yaml.YAMLError as e:
        detail = " ".join(str(e).split())  # One line: PyYAML's messages span several.
        raise InputError(f"{p}: invalid YAML ({detail})") from None
    except (ValueError, TypeError, OverflowError) as e:
        # PyYAML's constructors let these through for values such as 2001-13-01 or !!int abc.
        raise InputError(f"{p}: invalid YAML value ({e})") from None


def _check_yaml_tree(p: Path, data: Any, max_depth: int, max_values: int) -> None:
    """Refuse a parsed YAML tree nested deeper than ``max_depth``, holding an alias that
    contains itself, or expanding (each alias a copy of what it names) to more than
    ``max_values`` values.

    The tree is walked without recursion. A node is a container object, shared when an alias
    names it, so the depth and expanded size of each are memoized by id.
    """
    containers = (dict, list, tuple, set, frozenset)

    def children(node: Any) -> list[Any]:
        items = [*node.keys(), *node.values()] if isinstance(node, dict) else list(node)
        return [c for c in items if isinstance(c, containers)]

    depth: dict[int, int] = {}
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[Any, bool]] = [(data, False)] if isinstance(data, containers) else []
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            kids = children(node)
            depth[key] = 1 + max((depth[id(c)] for c in kids), default=0)
            scalars = (2 * len(node) if isinstance(node, dict) else len(node)) - len(kids)
            size[key] = 1 + scalars + sum(size[id(c)] for c in kids)
            on_path.discard(key)
            if depth[key] > max_depth:
                raise _too_deep(p, max_depth)
            if size[key] > max_values:
                raise InputError(
                    f"{p}: too large once its aliases are expanded (more than {max_values} values)"
                )
            continue
        if key in depth:
            continue
        if key in on_path:
            raise InputError(f"{p}: an alias refers to the mapping or list that contains it")
        on_path.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in children(node) if id(c) not in depth)
