"""Human-to-robot maps: typed, validated data.

A map names, for each key point, the human joint and the robot point (a body origin plus an
optional offset in that body's frame) that correspond, the key point's parent in the scaling
tree, and its task weight. Frames (orientation targets) are derived from key points the same
way on the human and on the robot, so no per-file rest-pose convention is needed.

The shipped maps are not written per (skeleton, robot) pair: the key points are humimic's
canonical ones (:data:`CANONICAL_KEYPOINTS`), a *skeleton map* (``skeletons/<name>.yaml``)
names each one's joint in a skeleton, and a *robot map* (``robots/<name>.yaml``) says where
each one is on a robot. N skeletons and M robots make N x M maps from N + M files
(:func:`get_map`). A user's own map (``--map FILE``) is one file in the combined form
(:func:`parse_map`; :func:`map_data` writes any map in it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from humimic.errors import InputError, MapError
from humimic.io import read_yaml

SCHEMA_VERSION = 1

CANONICAL_KEYPOINTS = (
    "pelvis", "neck", "head",
    "left_hip", "left_knee", "left_ankle", "left_toe",
    "right_hip", "right_knee", "right_ankle", "right_toe",
    "left_shoulder", "left_elbow", "left_wrist", "left_hand",
    "right_shoulder", "right_elbow", "right_wrist", "right_hand",
)  # fmt: skip
"""The human key points every shipped skeleton and robot map uses (a robot map may use a
subset; a skeleton map names a joint for each one it can)."""


@dataclass(frozen=True, kw_only=True)
class KeypointMap:
    """One key point.

    Attributes:
        human: Human joint name.
        body: Robot body name.
        offset: Point in the robot body's frame [m].
        parent: Parent key point in the scaling tree (None for the root).
        frame: If set, the key point is rigidly attached to this derived frame (e.g. the hips
            to the pelvis frame): its target is placed from the frame, not from the human bone.
        weight: Position task cost [1/m].
    """

    human: str
    body: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    parent: str | None = None
    frame: str | None = None
    weight: float = 1.0


@dataclass(frozen=True, kw_only=True)
class FrameMap:
    """An orientation target derived from key points. The map's first frame (the pelvis) gives
    the clip's heading.

    The frame's y axis is ``left[1] - left[0]`` made orthogonal to its z axis
    ``up[1] - up[0]``; x points forward. The robot body's orientation target is this frame
    times the constant offset measured on the robot in its zero pose.
    """

    body: str
    left: tuple[str, str]
    up: tuple[str, str]
    weight: float = 1.0


@dataclass(frozen=True, kw_only=True)
class FootMap:
    """A foot: the key points at the ankle and the toe, and the robot's foot body."""

    ankle: str
    toe: str
    body: str


@dataclass(frozen=True, kw_only=True)
class RetargetMap:
    """A skeleton-to-robot map. See the module docstring."""

    skeleton: str
    robot: str
    root: str
    keypoints: dict[str, KeypointMap]
    frames: dict[str, FrameMap] = field(default_factory=dict)
    feet: dict[str, FootMap] = field(default_factory=dict)
    posture_weight: float = 0.05
    source: str = "<memory>"

    def validate(self, human_names: tuple[str, ...] | None, robot_bodies: set[str]) -> None:
        """Check every name against a clip's joints and a robot's bodies.

        Raises:
            MapError: Naming the map file, the field and the bad name.
        """
        where = self.source
        if not self.frames:
            raise MapError(
                f"{where}: frames: at least one is required (the first gives the heading)"
            )
        if set(self.feet) != {"left", "right"}:
            raise MapError(
                f"{where}: feet: expected exactly 'left' and 'right', got {sorted(self.feet)}"
            )
        if not (0 <= self.posture_weight <= MAX_WEIGHT):
            raise MapError(
                f"{where}: posture_weight must be in [0, {MAX_WEIGHT:g}], got {self.posture_weight}"
            )
        if self.root not in self.keypoints:
            raise MapError(f"{where}: root {self.root!r} is not a key point")
        seen: set[str] = set()
        for name, kp in self.keypoints.items():
            if human_names is not None and kp.human not in human_names:
                raise MapError(
                    f"{where}: keypoints.{name}.human: no joint {kp.human!r} in the clip "
                    f"(joints: {', '.join(human_names)})"
                )
            if kp.body not in robot_bodies:
                raise MapError(f"{where}: keypoints.{name}.body: robot has no body {kp.body!r}")
            if name != self.root and kp.parent is None:
                raise MapError(f"{where}: keypoints.{name}.parent: required for non-root points")
            if kp.parent is not None and kp.parent not in seen:
                raise MapError(
                    f"{where}: keypoints.{name}.parent: {kp.parent!r} must be listed before it"
                )
            if kp.frame is not None and kp.frame not in self.frames:
                raise MapError(f"{where}: keypoints.{name}.frame: no frame {kp.frame!r}")
            if not (0 <= kp.weight <= MAX_WEIGHT):
                raise MapError(
                    f"{where}: keypoints.{name}.weight must be in [0, {MAX_WEIGHT:g}], got {kp.weight}"
                )
            seen.add(name)
        for name, fr in self.frames.items():
            if fr.body not in robot_bodies:
                raise MapError(f"{where}: frames.{name}.body: robot has no body {fr.body!r}")
            for k in (*fr.left, *fr.up):
                if k not in self.keypoints:
                    raise MapError(f"{where}: frames.{name}: no key point {k!r}")
        for side, foot in self.feet.items():
            for k in (foot.ankle, foot.toe):
                if k not in self.keypoints:
                    raise MapError(f"{where}: feet.{side}: no key point {k!r}")
            if foot.body not in robot_bodies:
                raise MapError(f"{where}: feet.{side}.body: robot has no body {foot.body!r}")
            if self.keypoints[foot.ankle].body != foot.body:
                raise MapError(
                    f"{where}: feet.{side}: the ankle key point {foot.ankle!r} must be on the foot "
                    f"body {foot.body!r}, not {self.keypoints[foot.ankle].body!r}"
                )


MAX_WEIGHT = 1e6
"""Largest task weight a map may give: weights are relative, and far larger ones only make the
IK's QP ill-conditioned (1e300 overflowed it)."""


def _pair(value: object, where: str) -> tuple[str, str]:
    if not (isinstance(value, list) and len(value) == 2 and all(isinstance(v, str) for v in value)):
        raise MapError(f"{where}: expected a list of two key point names, got {value!r}")
    return (value[0], value[1])


def _build(cls: type, data: object, where: str, convert: dict | None = None):
    if not isinstance(data, dict):
        raise MapError(f"{where}: expected a mapping, got {type(data).__name__}")
    allowed = set(cls.__dataclass_fields__)
    unknown = set(data) - allowed
    if unknown:  # Sorted as text: YAML keys may be numbers, dates or null.
        raise MapError(
            f"{where}: unknown field(s) {sorted(unknown, key=str)}; allowed: {sorted(allowed)}"
        )
    kwargs = dict(data)
    for key, fn in (convert or {}).items():
        if key in kwargs:
            kwargs[key] = fn(kwargs[key], f"{where}.{key}")
    for key, value in kwargs.items():
        expected = cls.__dataclass_fields__[key].type
        if "float" in str(expected) and "tuple" not in str(expected):
            kwargs[key] = _finite(value, f"{where}.{key}", "a number")
        elif str(expected) in ("str", "str | None") and not (
            isinstance(value, str) or (value is None and "None" in str(expected))
        ):
            raise MapError(f"{where}.{key}: expected a name (text), got {value!r}")
    missing = [
        k
        for k, f in cls.__dataclass_fields__.items()
        if k not in kwargs
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise MapError(f"{where}: missing field(s) {missing}")
    return cls(**kwargs)


def _finite(value: object, where: str, expected: str) -> float:
    """``value`` as a finite float; YAML booleans, text, ``.nan``, ``.inf`` and integers too
    large for a float are refused."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise MapError(f"{where}: expected {expected}, got {value!r}")
    try:
        out = float(value)
    except OverflowError:
        out = math.inf
    if not math.isfinite(out):
        raise MapError(f"{where}: expected {expected} (finite), got {value!r}")
    return out


def _offset(value: object, where: str) -> tuple[float, float, float]:
    if not (isinstance(value, list) and len(value) == 3):
        raise MapError(f"{where}: expected [x, y, z] in metres, got {value!r}")
    try:  # Text such as "0.5" is accepted, as float() reads it.
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError, OverflowError):
        raise MapError(f"{where}: expected numbers, got {value!r}") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise MapError(f"{where}: expected finite numbers, got {value!r}")
    return (x, y, z)


def parse_map(data: object, source: str) -> RetargetMap:
    """Build a :class:`RetargetMap` from parsed YAML, with errors naming the field."""
    if not isinstance(data, dict):
        raise MapError(f"{source}: expected a mapping at the top level")
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise MapError(f"{source}: schema_version is {version!r}, expected {SCHEMA_VERSION}")
    body = {k: v for k, v in data.items() if k != "schema_version"}
    kps = body.get("keypoints")
    if not isinstance(kps, dict) or not kps:
        raise MapError(f"{source}: keypoints: expected a non-empty mapping")
    body["keypoints"] = {
        k: _build(KeypointMap, v, f"{source}: keypoints.{k}", {"offset": _offset})
        for k, v in kps.items()
    }
    frames, feet = (body.get(k) or {} for k in ("frames", "feet"))
    for name, value in (("frames", frames), ("feet", feet)):
        if not isinstance(value, dict):
            raise MapError(f"{source}: {name}: expected a mapping, got {type(value).__name__}")
    body["frames"] = {
        k: _build(FrameMap, v, f"{source}: frames.{k}", {"left": _pair, "up": _pair})
        for k, v in frames.items()
    }
    body["feet"] = {k: _build(FootMap, v, f"{source}: feet.{k}") for k, v in feet.items()}
    return _build(RetargetMap, {**body, "source": source}, source)


def load_map_file(path: str | Path) -> RetargetMap:
    """Load and parse a map YAML file.

    Raises:
        MapError: The file is missing or unreadable, not valid YAML (or nested too deeply,
            see :func:`humimic.io.read_yaml`), or not a valid map; the message names the file.
    """
    p = Path(path)
    if not p.exists():
        raise MapError(f"{p}: cannot read: no such file")
    try:
        data = read_yaml(p)
    except InputError as e:
        raise MapError(str(e)) from None
    return parse_map(data, str(p))


def _read(path: Path, kind: str) -> dict:
    try:
        data = read_yaml(path)
    except InputError as e:
        raise MapError(str(e)) from None
    if not isinstance(data, dict):
        raise MapError(f"{path}: expected a mapping at the top level")
    if data.get("schema_version") != SCHEMA_VERSION:
        raise MapError(
            f"{path}: schema_version is {data.get('schema_version')!r}, expected {SCHEMA_VERSION}"
        )
    if not isinstance(data.get(kind), str):
        raise MapError(f"{path}: {kind}: expected a name")
    return data


@dataclass(frozen=True, kw_only=True)
class SkeletonMap:
    """A skeleton's joint for each canonical key point it has.

    Attributes:
        skeleton: Its name.
        joints: Canonical key point -> joint name.
        source: Where it comes from (a file, or how it was proposed).
    """

    skeleton: str
    joints: dict[str, str]
    source: str


def _canonical(value: object, where: str, what: str) -> dict:
    """``value`` as a non-empty mapping keyed by canonical key points."""
    if not isinstance(value, dict) or not value:
        raise MapError(f"{where}: expected a non-empty mapping of {what}")
    unknown = [k for k in value if k not in CANONICAL_KEYPOINTS]
    if unknown:
        raise MapError(
            f"{where}: {unknown} are not canonical key points ({', '.join(CANONICAL_KEYPOINTS)})"
        )
    return value


def load_skeleton_map(path: str | Path) -> SkeletonMap:
    """Read a skeleton map file (``joints``: canonical key point -> joint name)."""
    p = Path(path)
    data = _read(p, "skeleton")
    joints = _canonical(data.get("joints"), f"{p}: joints", "key points to joint names")
    bad = [k for k, v in joints.items() if not isinstance(v, str) or not v]
    if bad:
        raise MapError(f"{p}: joints: {bad}: expected joint names (text)")
    return SkeletonMap(skeleton=data["skeleton"], joints=dict(joints), source=str(p))


def compose_map(skeleton: str | Path | SkeletonMap, robot_file: str | Path) -> RetargetMap:
    """The (skeleton, robot) map made of a skeleton map (a file or a :class:`SkeletonMap`)
    and a robot map (the combined form without ``skeleton`` and the key points' ``human``),
    with errors naming the file and the key point."""
    sk = skeleton if isinstance(skeleton, SkeletonMap) else load_skeleton_map(skeleton)
    rp = Path(robot_file)
    rb = _read(rp, "robot")
    kps = _canonical(rb.get("keypoints"), f"{rp}: keypoints", "key points")
    combined = {}
    for k, v in kps.items():
        if not isinstance(v, dict):
            raise MapError(f"{rp}: keypoints.{k}: expected a mapping, got {type(v).__name__}")
        if "human" in v:
            raise MapError(f"{rp}: keypoints.{k}.human: a robot map names no human joint")
        if k not in sk.joints:
            raise MapError(
                f"{sk.source}: joints: no joint for the key point {k!r}, which {rp.name} uses"
            )
        combined[k] = {"human": sk.joints[k], **v}
    data = {**rb, "skeleton": sk.skeleton, "keypoints": combined}
    return parse_map(data, f"{sk.source} + {rp}")


def map_data(m: RetargetMap) -> dict:
    """``m`` in the combined YAML form :func:`parse_map` reads (``--map FILE``)."""
    kps = {}
    for name, kp in m.keypoints.items():
        d: dict = {"human": kp.human, "body": kp.body}
        if kp.offset != (0.0, 0.0, 0.0):
            d["offset"] = list(kp.offset)
        for key in ("parent", "frame"):
            if getattr(kp, key) is not None:
                d[key] = getattr(kp, key)
        d["weight"] = kp.weight
        kps[name] = d
    return {
        "schema_version": SCHEMA_VERSION,
        "skeleton": m.skeleton,
        "robot": m.robot,
        "root": m.root,
        "posture_weight": m.posture_weight,
        "keypoints": kps,
        "frames": {
            n: {"body": f.body, "left": list(f.left), "up": list(f.up), "weight": f.weight}
            for n, f in m.frames.items()
        },
        "feet": {n: dataclasses.asdict(f) for n, f in m.feet.items()},
    }


def _shipped(kind: str) -> dict[str, Path]:
    folder = resources.files(__name__).joinpath(kind)
    return {
        e.name[: -len(".yaml")]: Path(str(e)) for e in folder.iterdir() if e.name.endswith(".yaml")
    }


def skeleton_maps() -> dict[str, SkeletonMap]:
    """The shipped skeleton maps, by skeleton name."""
    return {name: load_skeleton_map(p) for name, p in _shipped("skeletons").items()}


def _robot_maps() -> dict[str, Path]:
    """Robot maps by robot: the shipped ones and the added robots' (``map.yaml`` in each
    added robot's folder, :mod:`humimic.robots.user`)."""
    from humimic.robots.user import MAP_FILE, robots_dir, user_robot_names

    root = robots_dir()
    added = {n: root / n / MAP_FILE for n in user_robot_names(root)}
    return {**{n: p for n, p in added.items() if p.is_file()}, **_shipped("robots")}


def robot_map_file(robot: str) -> Path | None:
    """The robot map of ``robot`` (shipped, or an added robot's), or None."""
    return _robot_maps().get(robot)


def builtin_maps() -> dict[tuple[str, str], tuple[Path, Path]]:
    """Shipped maps: (skeleton, robot) -> (skeleton map file, robot map file), every pair of
    a shipped skeleton map and a robot map (shipped, or an added robot's)."""
    skeletons, robots = _shipped("skeletons"), _robot_maps()
    return {(s, r): (sp, rp) for s, sp in skeletons.items() for r, rp in robots.items()}


def get_map(skeleton: str, robot: str) -> RetargetMap:
    """The shipped map for a skeleton/robot pair."""
    maps = builtin_maps()
    if (skeleton, robot) not in maps:
        skeletons = ", ".join(sorted({s for s, _ in maps}))
        robots = ", ".join(sorted({r for _, r in maps}))
        raise MapError(
            f"no map from skeleton {skeleton!r} to robot {robot!r}; shipped skeleton maps: "
            f"{skeletons}; robot maps: {robots}. Pass --map FILE to use your own."
        )
    return compose_map(*maps[(skeleton, robot)])
