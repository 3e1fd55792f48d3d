"""BVH (Biovision Hierarchy) motion files to :class:`~humimic.datasets.clip.HumanClip`:
:func:`load_bvh`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.datasets.units import auto_units
from humimic.datasets.units import metres_per_unit as metres_per_unit
from humimic.datasets.units import rest_leg_length as rest_leg_length
from humimic.errors import BvhParseError, InputError
from humimic.transforms import Y_UP_TO_Z_UP, euler_to_matrix, matrix_to_quat

MAX_JOINT_DEPTH = 200
"""Most levels of ``JOINT`` blocks below the root (real skeletons nest 10 to 30): the parser
recurses once per level, so a hostile file would otherwise exhaust Python's recursion."""

_ROTATIONS = {"xrotation": "x", "yrotation": "y", "zrotation": "z"}
_POSITIONS = {"xposition": 0, "yposition": 1, "zposition": 2}
_TOKEN = re.compile(r"[{}]|[^\s{}]+")
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


@dataclass
class _Joint:
    """One joint of the hierarchy while parsing."""

    name: str
    parent: int
    line: int
    offset: np.ndarray
    channels: list[str] = field(default_factory=list)
    is_end: bool = False


@dataclass(frozen=True)
class _Token:
    text: str
    line: int


def load_bvh(
    path: str | os.PathLike[str],
    *,
    units: str | float = "auto",
    up: str = "y",
    skeleton: str | None = None,
) -> HumanClip:
    """Load a BVH file as a clip of global joint positions and orientations.

    Reads any BVH: arbitrary channel orders per joint, position channels on any joint, joints
    with no channels, ``End Site`` blocks (kept as zero-channel joints named
    ``<Parent>_End``), CRLF, LF or mixed line endings, tabs or spaces. Conventions:

    * Rotation channels are intrinsic Euler angles in degrees, applied in the order they are
      listed: channels ``Zrotation Xrotation Yrotation`` give ``R_local = Rz @ Rx @ Ry``.
    * A joint's local translation is its position channels when it has them (the BVH root),
      else its ``OFFSET``; an axis without a position channel keeps its ``OFFSET`` component.
    * Global pose: ``R_w = R_parent_w @ R_local`` and ``p_w = p_parent_w + R_parent_w @
      t_local``.
    * Output is z up and in metres. A y-up file is turned with the proper rotation
      :data:`humimic.transforms.Y_UP_TO_Z_UP` (never a reflection): ``p_z = C p_y``,
      ``R_z = C R_y``.

    Args:
        path: The ``.bvh`` file.
        units: ``"m"``, ``"cm"``, ``"mm"``, ``"inch"``, a number of metres per file unit, or
            ``"auto"``: the first named unit (in that order) that makes the rest-pose height
            (all channels zero) between 1.0 and 2.3 m; if none does, the skeleton is scaled so
            that its leg (see :func:`humimic.datasets.units.rest_leg_length`) is 0.9 m. ``clip.meta["units"]`` says
            what was done and ``clip.meta["metres_per_unit"]`` holds the factor.
        up: The file's up axis, ``"y"`` (the usual BVH convention) or ``"z"``.
        skeleton: Skeleton convention name; by default ``"cmu"`` when the joints include
            ``LHipJoint`` and ``LowerBack``, else ``"bvh"``.

    Returns:
        The clip: positions in metres, z up, shape (T, J, 3); orientations wxyz, shape
        (T, J, 4); J counts the joints and the ``End Site`` joints.

    Raises:
        InputError: The file is missing or unreadable, or ``units``/``up`` are invalid.
        BvhParseError: The file is malformed; the message names the file and the line.
    """
    p = Path(path)
    if up not in ("y", "z"):
        raise InputError(f"{p}: unknown up axis {up!r}; expected 'y' or 'z'")
    factor = None if units == "auto" else metres_per_unit(units, p)
    lines = _read_lines(p)
    joints, motion_line = _parse_hierarchy(p, lines)
    num_channels = sum(len(j.channels) for j in joints)
    frame_time, data = _parse_motion(p, lines, motion_line, num_channels)

    up_matrix = Y_UP_TO_Z_UP if up == "y" else np.eye(3)
    parents = tuple(j.parent for j in joints)
    factor, how, rest_height = _scale(p, joints, up_matrix, units, factor)
    rot_w, pos_w = _forward_kinematics(joints, data)
    pos_w = np.einsum("ij,tkj->tki", up_matrix * factor, pos_w)
    rot_w = np.einsum("ij,tkjl->tkil", up_matrix, rot_w)
    names = tuple(j.name for j in joints)
    if skeleton is None:
        skeleton = "cmu" if {"LHipJoint", "LowerBack"} <= set(names) else "bvh"
    meta = {
        "units": how,
        "metres_per_unit": f"{factor:.6g}",
        "rest_height_m": f"{rest_height * factor:.4f}",
        "up": up,
        "frame_time": f"{frame_time:.9g}",
        "end_sites": str(sum(j.is_end for j in joints)),
    }
    return HumanClip(
        names=names,
        parents=parents,
        positions_w=pos_w,
        quats_w=matrix_to_quat(rot_w),
        fps=1.0 / frame_time,
        source=str(p),
        skeleton=skeleton,
        meta=meta,
    )


def _scale(
    p: Path,
    joints: list[_Joint],
    up_matrix: np.ndarray,
    units: str | float,
    factor: float | None,
) -> tuple[float, str, float]:
    """Metres per file unit, from the rest pose when ``units="auto"`` (``factor`` None), with
    how it was found (for ``clip.meta["units"]``) and the rest-pose height in file units.

    Raises:
        BvhParseError: The OFFSETs add up to a rest pose beyond floats.
        InputError: ``units="auto"`` and a rest pose with no height.
    """
    parents = tuple(j.parent for j in joints)
    rest = _rest_positions(joints) @ up_matrix.T  # (J, 3), file units, z up.
    if not np.isfinite(rest).all():  # Each OFFSET is finite; their sums can overflow.
        raise BvhParseError(p, None, "the joint OFFSETs add up to a rest pose too large for floats")
    rest_height = float(rest[:, 2].max() - rest[:, 2].min())
    if factor is None:
        factor, how = auto_units(p, rest, parents, rest_height)
    else:
        how = f"given: {units}" if isinstance(units, str) else f"given: {factor:g} m per unit"
    return factor, how, rest_height


def _read_lines(path: Path) -> list[str]:
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected a .bvh file")
    if not path.is_file():  # A pipe would block forever, a device such as /dev/zero never end.
        raise InputError(f"{path}: not a regular file, expected a .bvh file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InputError(f"{path}: cannot read: {e.strerror}") from e
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return _LINE_BREAK.split(text)


def _tokens(lines: list[str]) -> list[_Token]:
    """Tokens of the hierarchy, up to and including a line that starts with MOTION."""
    out: list[_Token] = []
    for n, line in enumerate(lines, start=1):
        words = _TOKEN.findall(line)
        out.extend(_Token(t, n) for t in words)
        if words and words[0].upper() == "MOTION":
            break
    return out


class _TokenStream:
    def __init__(self, path: Path, tokens: list[_Token], last_line: int) -> None:
        self.path = path
        self.tokens = tokens
        self.i = 0
        self.last_line = last_line

    def error(self, line: int | None, message: str) -> BvhParseError:
        return BvhParseError(self.path, line, message)

    def peek(self) -> _Token | None:
        return self.tokens[self.i] if self.i < len(self.tokens) else None

    def next(self, expected: str) -> _Token:
        tok = self.peek()
        if tok is None:
            raise self.error(self.last_line, f"unexpected end of file: expected {expected}")
        self.i += 1
        return tok

    def expect(self, text: str, expected: str | None = None) -> _Token:
        tok = self.next(expected or repr(text))
        if tok.text.upper() != text.upper():
            raise self.error(tok.line, f"expected {expected or repr(text)}, found {tok.text!r}")
        return tok

    def rest_of_line(self, line: int) -> list[_Token]:
        out = []
        while (tok := self.peek()) is not None and tok.line == line and tok.text != "{":
            out.append(tok)
            self.i += 1
        return out


def _parse_hierarchy(path: Path, lines: list[str]) -> tuple[list[_Joint], int]:
    """Parse HIERARCHY..MOTION. Returns the joints (parents before children) and MOTION's line."""
    tokens = _tokens(lines)
    last_line = next((n for n in range(len(lines), 0, -1) if lines[n - 1].strip()), 1)
    s = _TokenStream(path, tokens, last_line)
    first = s.peek()
    if first is None or first.text.upper() != "HIERARCHY":
        line = first.line if first is not None else 1
        found = repr(first.text) if first is not None else "an empty file"
        raise s.error(line, f"expected 'HIERARCHY' at the start of a BVH file, found {found}")
    s.i += 1
    joints: list[_Joint] = []
    names: set[str] = set()
    while True:
        tok = s.peek()
        if tok is None:
            raise s.error(last_line, "unexpected end of file: expected 'ROOT' or 'MOTION'")
        key = tok.text.upper()
        if key == "MOTION":
            s.i += 1
            extra = s.peek()
            if extra is not None:
                raise s.error(extra.line, f"expected nothing after 'MOTION', found {extra.text!r}")
            break
        if key != "ROOT":
            if tok.text == "}":
                raise s.error(tok.line, "unbalanced braces: '}' without a matching '{'")
            raise s.error(tok.line, f"expected 'ROOT' or 'MOTION', found {tok.text!r}")
        s.i += 1
        _parse_joint(s, joints, names, parent=-1, keyword_line=tok.line, is_end=False, depth=0)
    if not joints:
        raise s.error(tok.line, "expected at least one 'ROOT' joint before 'MOTION'")
    for joint in joints:  # End Sites: <Parent>_End, never clashing with a named joint.
        if joint.is_end:
            base, k = joint.name, 2
            while joint.name in names:
                joint.name, k = f"{base}{k}", k + 1
            names.add(joint.name)
    return joints, tok.line


def _parse_joint(
    s: _TokenStream,
    joints: list[_Joint],
    names: set[str],
    *,
    parent: int,
    keyword_line: int,
    is_end: bool,
    depth: int,
) -> None:
    """Parse one ROOT/JOINT/End Site block, recursing into its children (``depth`` below the
    root, at most :data:`MAX_JOINT_DEPTH`)."""
    if depth > MAX_JOINT_DEPTH:
        raise s.error(
            keyword_line,
            f"joints nested more than {MAX_JOINT_DEPTH} levels deep (a real skeleton has tens)",
        )
    if is_end:
        name = f"{joints[parent].name}_End"  # Made unique once all joint names are known.
    else:
        words = s.rest_of_line(keyword_line)
        if not words:
            raise s.error(keyword_line, "expected a joint name after ROOT/JOINT")
        name = " ".join(w.text for w in words)
        if name in names:
            raise s.error(keyword_line, f"duplicate joint name {name!r}")
        names.add(name)
    open_tok = s.expect("{", f"'{{' opening joint {name!r}")
    joint = _Joint(name=name, parent=parent, line=keyword_line, offset=np.zeros(3), is_end=is_end)
    index = len(joints)
    joints.append(joint)
    seen_offset = False
    while True:
        tok = s.peek()
        if tok is None:
            raise s.error(
                s.last_line,
                f"unbalanced braces: end of file before the '}}' closing joint {name!r} "
                f"(opened at line {open_tok.line})",
            )
        s.i += 1
        key = tok.text.upper()
        if tok.text == "}":
            break
        if key == "OFFSET":
            joint.offset = np.array([_number(s, f"OFFSET of {name!r}") for _ in range(3)])
            seen_offset = True
        elif key == "CHANNELS":
            joint.channels = _parse_channels(s, name)
        elif key == "JOINT":
            _parse_joint(
                s, joints, names, parent=index, keyword_line=tok.line, is_end=False, depth=depth + 1
            )
        elif key == "END":
            site = s.next("'Site' after 'End'")
            if site.text.upper() != "SITE":
                raise s.error(site.line, f"expected 'Site' after 'End', found {site.text!r}")
            _parse_joint(
                s, joints, names, parent=index, keyword_line=tok.line, is_end=True, depth=depth + 1
            )
        elif key == "MOTION":
            raise s.error(
                tok.line,
                f"unbalanced braces: 'MOTION' before the '}}' closing joint {name!r} "
                f"(opened at line {open_tok.line})",
            )
        else:
            raise s.error(
                tok.line,
                f"expected OFFSET, CHANNELS, JOINT, End Site or '}}' in joint {name!r}, "
                f"found {tok.text!r}",
            )
    if not seen_offset:
        raise s.error(open_tok.line, f"joint {name!r} has no OFFSET")


def _number(s: _TokenStream, what: str) -> float:
    tok = s.next(f"a number ({what})")
    try:
        value = float(tok.text)
    except ValueError:
        raise s.error(tok.line, f"expected a number ({what}), found {tok.text!r}") from None
    if not math.isfinite(value):
        raise s.error(tok.line, f"expected a finite number ({what}), found {tok.text!r}")
    return value


def _parse_channels(s: _TokenStream, name: str) -> list[str]:
    tok = s.next(f"the channel count of joint {name!r}")
    try:
        count = int(tok.text)
    except ValueError:
        count = -1
    if count < 0:
        raise s.error(
            tok.line,
            f"expected a channel count (an integer >= 0) for joint {name!r}, found {tok.text!r}",
        )
    channels: list[str] = []
    for _ in range(count):
        ch = s.next(f"{count} channel names for joint {name!r}")
        low = ch.text.lower()
        if low not in _ROTATIONS and low not in _POSITIONS:
            raise s.error(
                ch.line,
                f"unknown channel {ch.text!r} in joint {name!r} (CHANNELS {count} needs {count} "
                "names); expected Xposition, Yposition, Zposition, Xrotation, Yrotation or "
                "Zrotation",
            )
        if low in _POSITIONS and low in channels:
            raise s.error(ch.line, f"channel {ch.text!r} repeated in joint {name!r}")
        channels.append(low)
    return channels


def _parse_motion(
    path: Path, lines: list[str], motion_line: int, num_channels: int
) -> tuple[float, np.ndarray]:
    """Parse ``Frames:``, ``Frame Time:`` and the data lines after MOTION (1-based line).

    The number of non-empty data lines must equal ``Frames:``: fewer is a truncated file, more
    is a header that does not match its data (either way one of them is wrong).

    Returns:
        Frame time (s) and channel values (T, C).
    """
    frames, frames_line = _frame_count(path, lines, motion_line)
    frame_time, time_line = _frame_time(path, lines, frames_line)
    data_lines = _data_lines(path, lines, time_line, frames, frames_line)
    rows = [lines[k].split() for k in data_lines]
    for k, row in zip(data_lines, rows, strict=True):
        if len(row) != num_channels:
            raise BvhParseError(
                path,
                k + 1,
                f"expected {num_channels} values (one per channel) on this frame line, "
                f"found {len(row)}",
            )
    after = [k for k in range(data_lines[-1] + 1, len(lines)) if lines[k].strip()]
    if after:
        raise BvhParseError(
            path,
            after[0] + 1,
            f"more frame lines than 'Frames:' says: {frames + len(after)} non-empty lines "
            f"after 'Frame Time:', but 'Frames:' (line {frames_line}) says {frames}",
        )
    if num_channels == 0:
        return frame_time, np.zeros((frames, 0))
    return frame_time, _frame_values(path, data_lines, rows)


def _header_line(path: Path, lines: list[str], n: int, label: str, pattern: str) -> tuple[str, int]:
    """The value of a MOTION header line (``label``, matched by ``pattern``): the first
    non-empty line from 0-based index ``n`` on.

    Returns:
        The value's text and the 1-based line it is on (also the 0-based index after it).
    """
    while n < len(lines) and not lines[n].strip():
        n += 1
    if n >= len(lines):
        raise BvhParseError(path, len(lines), f"unexpected end of file: expected '{label}'")
    m = re.fullmatch(pattern, lines[n].strip(), flags=re.IGNORECASE)
    if m is None:
        raise BvhParseError(path, n + 1, f"expected '{label} <number>', found {lines[n].strip()!r}")
    return m.group(1), n + 1


def _frame_count(path: Path, lines: list[str], n: int) -> tuple[int, int]:
    """``Frames:``, a positive whole number, from 0-based line index ``n`` on.

    Returns:
        The count and its 1-based line (the 0-based index of the line after it).
    """
    frames_text, frames_line = _header_line(path, lines, n, "Frames:", r"Frames\s*:\s*(\S+)")
    try:
        frames = int(frames_text)
    except ValueError:
        raise BvhParseError(
            path, frames_line, f"expected a whole number of frames, found {frames_text!r}"
        ) from None
    if frames <= 0:
        raise BvhParseError(path, frames_line, f"zero frames (Frames: {frames}); nothing to load")
    return frames, frames_line


def _frame_time(path: Path, lines: list[str], n: int) -> tuple[float, int]:
    """``Frame Time:``, a positive finite number of seconds, from 0-based line index ``n`` on.

    Returns:
        The frame time and its 1-based line (the 0-based index of the line after it).
    """
    time_text, time_line = _header_line(path, lines, n, "Frame Time:", r"Frame\s+Time\s*:\s*(\S+)")
    try:
        frame_time = float(time_text)
    except ValueError:
        raise BvhParseError(
            path, time_line, f"expected a frame time in seconds, found {time_text!r}"
        ) from None
    if not math.isfinite(frame_time) or frame_time <= 0:
        raise BvhParseError(
            path, time_line, f"frame time must be a positive number of seconds, got {time_text}"
        )
    return frame_time, time_line


def _data_lines(
    path: Path, lines: list[str], time_line: int, frames: int, frames_line: int
) -> list[int]:
    """The 0-based indices of the first ``frames`` non-empty lines after ``Frame Time:``
    (1-based line ``time_line``, so 0-based index ``time_line`` is the next line).

    Raises:
        BvhParseError: Fewer lines than ``Frames:`` says (a truncated file: names where the
            data ends).
    """
    data_lines: list[int] = []
    for k in range(time_line, len(lines)):
        if lines[k].strip():
            data_lines.append(k)
            if len(data_lines) == frames:
                break
    if len(data_lines) < frames:
        end = data_lines[-1] + 1 if data_lines else time_line
        raise BvhParseError(
            path,
            end,
            f"truncated file: data ends at line {end} after {len(data_lines)} frames, but "
            f"'Frames:' (line {frames_line}) says {frames}",
        )
    return data_lines


def _frame_values(path: Path, data_lines: list[int], rows: list[list[str]]) -> np.ndarray:
    """The frame lines' words as numbers (T, C), each finite.

    Raises:
        BvhParseError: A word that is not a number, or NaN or inf: names the line and column.
    """
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:
        for k, row in zip(data_lines, rows, strict=True):
            for col, text in enumerate(row):
                try:
                    float(text)
                except ValueError:
                    raise BvhParseError(
                        path, k + 1, f"expected a number in column {col + 1}, found {text!r}"
                    ) from None
        raise BvhParseError(path, None, "frame data is not all numbers") from None
    bad = ~np.isfinite(data)
    if bad.any():
        t, col = np.argwhere(bad)[0]
        raise BvhParseError(
            path,
            data_lines[t] + 1,
            f"expected finite numbers, found {rows[t][col]!r} in column {col + 1} (frame {t})",
        )
    return data


def _rest_positions(joints: list[_Joint]) -> np.ndarray:
    """Joint positions with every channel zero and the OFFSETs as translations. Shape: (J, 3)."""
    pos = np.zeros((len(joints), 3))
    for j, joint in enumerate(joints):
        pos[j] = joint.offset + (pos[joint.parent] if joint.parent >= 0 else 0.0)
    return pos


def _forward_kinematics(joints: list[_Joint], data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global rotations and positions in file axes and units.

    Args:
        joints: Parents before children.
        data: Channel values, degrees for rotations. Shape: (T, C).

    Returns:
        Rotations, shape (T, J, 3, 3); positions, shape (T, J, 3).
    """
    num_frames = data.shape[0]
    rot = np.empty((num_frames, len(joints), 3, 3))
    pos = np.empty((num_frames, len(joints), 3))
    col = 0
    for j, joint in enumerate(joints):
        cols = {ch: col + k for k, ch in enumerate(joint.channels)}
        rot_cols = [col + k for k, ch in enumerate(joint.channels) if ch in _ROTATIONS]
        order = "".join(_ROTATIONS[ch] for ch in joint.channels if ch in _ROTATIONS)
        col += len(joint.channels)
        trans = np.broadcast_to(joint.offset, (num_frames, 3)).copy()
        for ch, axis in _POSITIONS.items():
            if ch in cols:
                trans[:, axis] = data[:, cols[ch]]
        if order:
            local = euler_to_matrix(np.deg2rad(data[:, rot_cols]), order)
        else:
            local = np.broadcast_to(np.eye(3), (num_frames, 3, 3))
        if joint.parent < 0:
            rot[:, j] = local
            pos[:, j] = trans
        else:
            parent_rot = rot[:, joint.parent]
            rot[:, j] = parent_rot @ local
            pos[:, j] = pos[:, joint.parent] + np.einsum("tij,tj->ti", parent_rot, trans)
    return rot, pos
