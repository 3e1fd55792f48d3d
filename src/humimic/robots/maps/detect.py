"""Which skeleton a clip's joints are: a shipped skeleton map matched by joint names, or, for a
rig no map knows, a skeleton map proposed from the joints' names and the tree.

A shipped map matches when every joint it names is in the clip (namespace prefixes such as
Mixamo's ``mixamorig:`` or ``mixamorig1:`` aside). A proposal places each canonical key point
by the name patterns of :data:`PATTERNS` (after the side, the namespace and separators are
taken off the name: ``LeftUpLeg``, ``L_Hip``, ``leftThigh``, ``Hip.L`` and ``RightUpperLeg``
all read as a hip) and checks that each limb is a chain of the tree (hip above knee above
ankle above toe; shoulder above elbow above wrist). It is used only when every key point is
found once; otherwise :class:`~humimic.errors.MapError` names the key points it could not
place, or placed more than once.
"""

from __future__ import annotations

import itertools
import re

from humimic.errors import MapError
from humimic.robots.maps import CANONICAL_KEYPOINTS, SkeletonMap, skeleton_maps

PATTERNS: dict[str, tuple[tuple[str, ...], ...]] = {
    # Per key point, groups of name stems in order of preference: the first group that
    # matches exactly one joint (per side) places it.
    "hip": (("upleg", "upperleg", "thigh", "femur"), ("hip",)),
    "knee": (("leg", "lowerleg", "knee", "shin", "calf", "tibia"),),
    "ankle": (("foot", "ankle"),),
    "toe": (("toebase", "toe", "toes", "ball", "footend"),),
    "shoulder": (("arm", "upperarm", "humerus"), ("shoulder",)),
    "elbow": (("forearm", "lowerarm", "elbow"),),
    "wrist": (("hand", "wrist"),),
    "neck": (("neck",),),
    "pelvis": (("hips", "pelvis"), ("hip",), ("root",)),
}
"""Name stems (lower case, no side, no separators) of each key point's joint."""

LIMBS = (("hip", "knee", "ankle", "toe"), ("shoulder", "elbow", "wrist"))
"""Chains that must run down the tree in this order on each side."""


def _bare(name: str) -> str:
    """A joint name without its namespace (``mixamorig:Hips`` -> ``Hips``)."""
    return name.rsplit(":", 1)[-1]


def _split(name: str) -> tuple[str | None, str]:
    """(side, stem) of a joint name: side ``left``, ``right`` or None; the stem in lower case
    without separators. ``L_Hip`` -> (left, hip); ``LeftUpLeg`` -> (left, upleg); ``LHip`` ->
    (left, hip); ``hip.R`` -> (right, hip); ``Leg`` -> (None, leg)."""
    raw = _bare(name)
    sides = {"l": "left", "r": "right"}
    m = re.match(r"^([LR])(?=[A-Z][a-z])", raw)  # LHip, RKnee: a capital before a capital.
    if m:
        return sides[m.group(1).lower()], _squash(raw[1:])
    s = _squash(raw)
    for side in ("left", "right"):
        if s.startswith(side) and len(s) > len(side):
            return side, s[len(side) :]
        if s.endswith(side) and len(s) > len(side):
            return side, s[: -len(side)]
    # One letter with a separator: L_Hip, hip.R (not the l of "leg" or the r of "root").
    m = re.match(r"^([LlRr])[_\-. ](.+)$", raw) or re.match(r"^(.+)[_\-. ]([LlRr])$", raw)
    if m:
        letter, rest = (
            (m.group(1), m.group(2)) if len(m.group(1)) == 1 else (m.group(2), m.group(1))
        )
        return sides[letter.lower()], _squash(rest)
    return None, s


def _squash(text: str) -> str:
    return re.sub(r"[_\-. ]", "", text).lower()


def _ancestors(parents: tuple[int, ...], j: int) -> set[int]:
    out = set()
    while parents[j] >= 0:
        j = parents[j]
        out.add(j)
    return out


def match_skeleton(names: tuple[str, ...]) -> SkeletonMap | None:
    """The shipped skeleton map whose every joint is in ``names`` (the most joints wins; an
    exact match before one up to namespace prefixes), with the clip's own names; None if
    none matches."""
    have = set(names)
    bare = {}
    for n in names:
        bare.setdefault(_bare(n), n)
    spaced = any(":" in n for n in names)
    best: tuple[int, int, int, str, SkeletonMap] | None = None
    for sk in skeleton_maps().values():
        wanted = list(sk.joints.values())
        if all(w in have for w in wanted):
            rank, joints = 1, dict(sk.joints)
        elif all(_bare(w) in bare for w in wanted):
            rank, joints = 0, {k: bare[_bare(w)] for k, w in sk.joints.items()}
        else:
            continue
        # Exact before bare; then a map with namespaces for a rig with them (a Mixamo rig
        # whose prefix is mixamorig1: is Mixamo's, not CMU's, whose bare names it shares).
        same_style = int(any(":" in w for w in wanted) == spaced)
        key = (rank, same_style, len(wanted), sk.skeleton)
        if best is None or key[:3] > best[:3]:
            best = (*key, SkeletonMap(skeleton=sk.skeleton, joints=joints, source=sk.source))
    return None if best is None else best[4]


def propose_skeleton_map(
    names: tuple[str, ...], parents: tuple[int, ...], source: str
) -> SkeletonMap:
    """A skeleton map for a rig no shipped map knows, from its joint names and tree.

    Raises:
        MapError: Naming ``source`` and each key point not found, or found more than once,
            with the joints it considered.
    """
    split = [_split(n) for n in names]
    joints: dict[str, str] = {}
    index: dict[str, int] = {}
    problems: list[str] = []
    for key in CANONICAL_KEYPOINTS:
        side, _, part = key.partition("_") if "_" in key else (None, "", key)
        if part not in PATTERNS:
            continue  # head, hands: optional, not placed by names.
        found: list[int] = []
        for group in PATTERNS[part]:
            found = [j for j, (s, stem) in enumerate(split) if s == side and stem in group]
            if found:
                break
        if len(found) == 1:
            joints[key] = names[found[0]]
            index[key] = found[0]
        elif not found:
            problems.append(f"{key}: no joint")
        else:
            problems.append(f"{key}: {len(found)} joints ({', '.join(names[j] for j in found)})")
    for side in ("left", "right"):
        for chain in LIMBS:
            keys = [f"{side}_{p}" for p in chain if f"{side}_{p}" in index]
            for upper, lower in itertools.pairwise(keys):
                if index[upper] not in _ancestors(parents, index[lower]):
                    problems.append(f"{lower}: {joints[lower]} is not below {joints[upper]}")
    if problems:
        raise MapError(
            f"{source}: no shipped skeleton map fits its joints, and humimic cannot place every "
            f"key point by name: {'; '.join(problems)}. Write a map (--map FILE; "
            "docs/retargeting.md) or rename the joints"
        )
    return SkeletonMap(skeleton="proposed", joints=joints, source=f"{source} (proposed by name)")


__all__ = ["LIMBS", "PATTERNS", "match_skeleton", "propose_skeleton_map"]
