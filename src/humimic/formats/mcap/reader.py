"""Read MCAP files into memory, every JSON message validated against its schema.

Corrupt or truncated files, and files that are not MCAP at all, raise
:class:`~.schemas.McapFormatError` naming the file (and the topic, message and field).
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.reader import make_reader

from humimic.errors import HumimicError, InputError
from humimic.formats.mcap.schemas import TOPICS, McapFormatError
from humimic.formats.mcap.validate import VALIDATORS, Checker, compile_schema
from humimic.io import check_input_file


@dataclass
class McapLog:
    """An MCAP file in memory: metadata records and validated JSON messages per topic.

    Attributes:
        path: The file.
        metadata: Record name -> string map.
        messages: Topic -> list of (log time [ns], message).
        schemas: Topic -> schema name.
    """

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)

    def topic(self, name: str) -> list[tuple[int, dict[str, Any]]]:
        """Messages of one topic; :class:`McapFormatError` names the topics present if absent."""
        if name not in self.messages or not self.messages[name]:
            present = ", ".join(sorted(self.messages)) or "none"
            raise McapFormatError(f"{self.path}: no messages on topic {name} (topics: {present})")
        return self.messages[name]

    def meta(self, name: str) -> dict[str, str]:
        """One metadata record; :class:`McapFormatError` if absent."""
        if name not in self.metadata:
            raise McapFormatError(
                f"{self.path}: no metadata record {name!r} "
                f"(records: {', '.join(sorted(self.metadata)) or 'none'})"
            )
        return self.metadata[name]


class _Bounded:
    """A read-only file that never asks the OS for more bytes than the file has left: a
    corrupt record length then costs a short read, not an allocation of its size."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self._size = os.fstat(f.fileno()).st_size

    def read(self, n: int = -1) -> bytes:
        left = max(self._size - self._f.tell(), 0)
        return self._f.read(left if n is None or n < 0 else min(n, left))

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True


def _check_is_mcap(p: Path) -> None:
    """Refuse, saying what it is, a file that is not MCAP (an ``.npz`` motion, text...)."""
    from humimic.motion import sniff  # On use: humimic.motion imports MuJoCo.

    try:
        kind = sniff(p)
    except OSError as e:
        raise InputError(f"{p}: cannot read: {e.strerror}") from None
    if kind == "mcap":
        return
    if kind == "npz":
        raise McapFormatError(
            f"{p}: is a zip archive (an .npz motion?), not an MCAP file; rename it to "
            f"{p.with_suffix('.npz').name}"
        )
    what = {"empty": "an empty file", "text": "a text file", "npy": "an .npy array"}
    raise McapFormatError(f"{p}: {what.get(kind, 'not an MCAP file')}: expected an MCAP file")


def read_mcap(
    path: str | os.PathLike[str],
    *,
    topics: Iterable[str] | None = None,
    require: Iterable[str] = (),
) -> McapLog:
    """Read an MCAP file, validating every JSON message against its schema.

    Args:
        path: The file.
        topics: Only these topics (default: all).
        require: Topics that must have at least one message.

    Raises:
        InputError: Missing file.
        McapFormatError: Truncated or corrupt file; a known topic with the wrong schema; a
            message that does not match its schema (names topic, message index and field); a
            required topic without messages.
    """
    p = check_input_file(path, "an MCAP file")
    _check_is_mcap(p)
    log = McapLog(path=p)
    wanted = None if topics is None else set(topics)
    validators: dict[str, Checker] = {}
    try:
        with p.open("rb") as raw:
            reader = make_reader(_Bounded(raw), validate_crcs=True)  # type: ignore[arg-type]
            for schema, channel, message in reader.iter_messages(
                topics=None if wanted is None else sorted(wanted)
            ):
                topic = channel.topic
                if topic not in validators:
                    validators[topic] = _validator_for(p, topic, schema)
                    log.schemas[topic] = schema.name if schema is not None else ""
                if channel.message_encoding != "json":
                    raise McapFormatError(
                        f"{p}: topic {topic}: message encoding {channel.message_encoding!r}, "
                        "expected 'json'"
                    )
                try:
                    msg = json.loads(message.data)
                except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
                    raise McapFormatError(
                        f"{p}: topic {topic}: message is not JSON ({e})"
                    ) from None
                msgs = log.messages.setdefault(topic, [])
                err = validators[topic](msg)
                if err is not None:
                    raise McapFormatError(
                        f"{p}: topic {topic} ({log.schemas[topic]}), message {len(msgs)}: "
                        f"field {err}"
                    )
                msgs.append((message.log_time, msg))
            for record in reader.iter_metadata():
                log.metadata[record.name] = dict(record.metadata)
    except HumimicError:
        raise
    except Exception as e:  # The mcap package, its decompressors and seeks raise many types.
        text = " ".join(f"{type(e).__name__}: {e}".split())[:200]
        raise McapFormatError(
            f"{p}: not a readable MCAP file (truncated or corrupt): {text}"
        ) from None
    for topic in require:
        log.topic(topic)
    return log


def _validator_for(p: Path, topic: str, schema: Any) -> Checker:
    expected = TOPICS.get(topic)
    name = schema.name if schema is not None else None
    if expected is not None and name != expected:
        raise McapFormatError(f"{p}: topic {topic} has schema {name!r}, expected {expected!r}")
    if name in VALIDATORS:
        return VALIDATORS[name]
    if schema is None or schema.encoding != "jsonschema":
        return compile_schema({})
    try:
        return compile_schema(json.loads(schema.data))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise McapFormatError(f"{p}: topic {topic}: schema {name!r} is not JSON ({e})") from None
