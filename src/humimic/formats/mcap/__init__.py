"""MCAP files that Foxglove opens: motion references, rollouts and robot logs.

JSON message encoding with ``jsonschema`` schemas. Topics and their schemas are fixed in
:mod:`.schemas` (:data:`TOPICS`), so a file written by humimic, by a robot's logger or by a
user's script is read and validated the same way.
"""

from humimic.formats.mcap.logs import qpos_from_log, sample_at
from humimic.formats.mcap.motion import (
    iter_frames,
    read_motion_mcap,
    write_motion_mcap,
    write_motion_topics,
)
from humimic.formats.mcap.reader import McapLog, read_mcap
from humimic.formats.mcap.schemas import SCHEMAS, TOPICS, McapFormatError, stamp, tf_message
from humimic.formats.mcap.validate import Checker, compile_schema
from humimic.formats.mcap.writer import McapWriter

__all__ = [
    "SCHEMAS",
    "TOPICS",
    "Checker",
    "McapFormatError",
    "McapLog",
    "McapWriter",
    "compile_schema",
    "iter_frames",
    "qpos_from_log",
    "read_mcap",
    "read_motion_mcap",
    "sample_at",
    "stamp",
    "tf_message",
    "write_motion_mcap",
    "write_motion_topics",
]
