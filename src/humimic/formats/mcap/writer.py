"""Write MCAP files atomically, every message validated against its topic's schema."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from mcap.writer import Writer

from humimic.errors import InputError, OutputPathError
from humimic.formats.mcap.schemas import SCHEMAS, TOPICS, McapFormatError
from humimic.formats.mcap.validate import VALIDATORS
from humimic.io import check_writable, file_mode


class McapWriter:
    """Write an MCAP file atomically: a temporary file renamed into place on success only.

    Use as a context manager. Each message is validated against its topic's schema; the first
    invalid message raises :class:`McapFormatError` naming the topic and the field, and no
    file is left behind.
    """

    def __init__(self, path: str | os.PathLike[str], *, profile: str = "humimic") -> None:
        if Path(path).suffix != ".mcap":  # Before any folder is made for it.
            raise InputError(f"{path}: MCAP files must end in .mcap")
        self.path = check_writable(path, create=True)
        try:
            fd, tmp = tempfile.mkstemp(
                prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent
            )
        except OSError as e:
            raise OutputPathError(f"{self.path}: cannot write here: {e.strerror or e}") from None
        self._tmp = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        self._writer = Writer(self._file)
        self._writer.start(profile=profile, library="humimic")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._seq: dict[str, int] = {}

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
            return
        self.abort()
        if isinstance(exc, OSError):  # A write cut short (a full disk, a file size limit).
            raise OutputPathError(f"{self.path}: cannot write: {exc.strerror or exc}") from None

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (string to string)."""
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def _channel(self, topic: str, schema: str | None) -> tuple[int, str]:
        if topic in self._channels:
            return self._channels[topic]
        name = schema or TOPICS.get(topic)
        if name is None or name not in SCHEMAS:
            raise InputError(
                f"topic {topic}: no schema known; pass one of {sorted(SCHEMAS)} or use a known "
                f"topic ({', '.join(sorted(TOPICS))})"
            )
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode()
            )
        cid = self._writer.register_channel(
            topic=topic, message_encoding="json", schema_id=self._schemas[name]
        )
        self._channels[topic] = (cid, name)
        return cid, name

    def write(
        self, topic: str, log_time_ns: int, message: dict[str, Any], *, schema: str | None = None
    ) -> None:
        """Validate and write one message."""
        cid, name = self._channel(topic, schema)
        err = VALIDATORS[name](message)
        if err is not None:
            raise McapFormatError(f"topic {topic} ({name}): field {err}")
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        data = json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
        self._writer.add_message(
            channel_id=cid, log_time=int(log_time_ns), data=data, publish_time=int(log_time_ns),
            sequence=seq,
        )  # fmt: skip

    def close(self) -> Path:
        """Finish the file and move it into place (with the usual permissions, 0666 less the
        umask, as :func:`humimic.io.atomic_write` gives)."""
        try:
            self._writer.finish()
            self._file.close()
            os.chmod(self._tmp, file_mode())
            os.replace(self._tmp, self.path)
        except OSError as e:
            self.abort()
            raise OutputPathError(f"{self.path}: cannot write: {e.strerror or e}") from None
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self) -> None:
        """Discard everything written."""
        with contextlib.suppress(Exception):
            self._file.close()
        with contextlib.suppress(OSError):
            self._tmp.unlink()
