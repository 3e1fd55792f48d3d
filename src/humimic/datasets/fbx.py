"""FBX skeleton animation (OptiTrack Motive, Xsens MVN, Mixamo, Blender exports) as clips of
joint positions, read through pufbx (Python bindings of the ufbx C library).

What is read: the skeleton's joints (nodes with a bone attribute: FBX ``LimbNode`` and ``Root``),
each joint's parent (its nearest joint ancestor), and one take, baked by ufbx to local
translation, rotation and scale keys at the file's frame rate. World positions follow by
composing every node on the way from the scene root (so a Blender ``Armature`` node's scale, or a
MotionBuilder reference node's offset, is applied), checked against ufbx's own world transforms
in the file's rest pose.

pufbx 0.1.0 does not expose the file's global settings (unit scale, up axis, time mode), so
they are measured from the skeleton, as for BVH files: the units from the rest-pose height
(``units="auto"``), the up axis from the rest pose (the spine's side of the hips against the
legs'), the frame rate from the spacing of the animation keys. Each is recorded in
``clip.meta`` with how it was found, and each can be given instead.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.datasets.units import auto_units, metres_per_unit
from humimic.errors import InputError
from humimic.transforms import Y_UP_TO_Z_UP, quat_to_matrix

PUFBX_PIN = "pufbx==0.1.0"
"""The reader this module is written against (``pip install`` line in errors)."""

UP_AXIS_MIN_ALIGNMENT = 0.8
"""How closely (cosine) the skeleton's spine-over-legs direction must match one axis for
``up="auto"`` to take it."""

REST_CHECK_TOL = 1e-6
"""Largest disagreement (relative to the skeleton's size) between this module's composition of
the rest pose and ufbx's world transforms before the file is refused."""

FPS_DEFAULT_NOTE = "the keys' spacing"

MAX_FRAMES = 1_000_000
"""Most frames read from one take (2.3 hours at 120 fps): a key time far out of range would
otherwise ask for terabytes."""


def _import_pufbx() -> Any:
    try:
        import pufbx  # type: ignore[import-untyped]
        from pufbx.animation.bake_anim import bake_anim  # type: ignore[import-untyped]
    except ImportError:
        return None
    return pufbx, bake_anim


def load_fbx(
    path: str | os.PathLike[str],
    *,
    units: str | float = "auto",
    up: str = "auto",
    skeleton: str | None = None,
    take: str | None = None,
) -> HumanClip:
    """Load the skeleton animation of an FBX file (binary or ASCII) as a clip.

    Args:
        path: The ``.fbx`` file.
        units: ``"auto"`` (see :func:`humimic.datasets.units.auto_units`), a unit name (``m``,
            ``cm``, ``mm``, ``inch``) or metres per file unit, applied after the nodes' own
            scales.
        up: ``"auto"`` (from the rest pose, see :func:`detect_up`), ``"y"`` or ``"z"``.
        skeleton: Skeleton convention name; default ``"fbx"`` (the map is then matched or
            proposed from the joint names).
        take: The animation take (stack) by name; default the first with keys.

    Returns:
        The clip: z up, metres; positions only (``quats_w`` None).

    Raises:
        InputError: pufbx missing, a file that is not FBX or has no skeleton or animation, an
            unknown take, a transform inheritance this reader cannot compose, or bad
            ``units``/``up``.
    """
    p = Path(path)
    if up not in ("auto", "y", "z"):
        raise InputError(f"{p}: unknown up axis {up!r}; expected 'auto', 'y' or 'z'")
    factor = None if units == "auto" else metres_per_unit(units, p)
    scene, bake_anim = _read_scene(p)
    nodes = list(scene.nodes)
    index = {int(n.typed_id): i for i, n in enumerate(nodes)}
    parent = [index[int(n.parent.typed_id)] if n.parent is not None else -1 for n in nodes]
    joints = [i for i, n in enumerate(nodes) if n.bone is not None]
    if not joints:
        raise InputError(f"{p}: no skeleton: the file has no joint nodes (LimbNode or Root)")
    joints = _largest_skeleton(joints, parent)
    joint_parents = _joint_parents(joints, parent)

    stack = _pick_take(p, scene, take)
    times, fps = _frame_times(p, stack)
    baked = bake_anim(scene, stack.anim, resample_rate=fps, key_reduction_enabled=False)
    animated = {index[int(b.typed_id)]: b for b in baked.modified_nodes}
    pos, rest = _joint_tracks(p, nodes, parent, joints, animated, times)

    turn, how_up = _up_turn(p, up, rest, joint_parents)
    pos = pos @ turn.T
    rest = rest @ turn.T
    rest_height = float(rest[:, 2].max() - rest[:, 2].min())
    if factor is None:
        factor, how_units = auto_units(p, rest, joint_parents, rest_height)
    else:
        how_units = f"given: {units}" if isinstance(units, str) else f"given: {factor:g} m/unit"
    meta = {
        "units": how_units,
        "metres_per_unit": f"{factor:.6g}",
        "rest_height_m": f"{rest_height * factor:.4f}",
        "up": how_up,
        "fps": f"{fps:.6g} (from {FPS_DEFAULT_NOTE})",
        "take": str(stack.name),
        "takes": ", ".join(str(s.name) for s in scene.anim_stacks),
        "joints": str(len(joints)),
    }
    return HumanClip(
        names=tuple(str(nodes[i].name) for i in joints),
        parents=joint_parents,
        positions_w=pos * factor,
        fps=fps,
        source=str(p),
        skeleton=skeleton or "fbx",
        meta=meta,
    )


def _read_scene(p: Path) -> tuple[Any, Any]:
    """The file's scene read by pufbx, and pufbx's baking function (for the take's keys).

    Raises:
        InputError: No such file, pufbx missing (says what to install), or a file pufbx
            cannot read (its message on one line).
    """
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    mod = _import_pufbx()
    if mod is None:
        raise InputError(
            f"{p}: reading FBX needs the pufbx package (Python bindings of ufbx): "
            f"pip install {PUFBX_PIN}"
        )
    pufbx, bake_anim = mod
    try:
        scene = pufbx.load_fbx(str(p))
    except Exception as e:  # pufbx raises UFBXError; a path it cannot encode, others.
        detail = " ".join(str(e).split()) or type(e).__name__
        raise InputError(f"{p}: not a readable FBX file ({detail})") from None
    return scene, bake_anim


def _joint_tracks(
    p: Path,
    nodes: list[Any],
    parent: list[int],
    joints: list[int],
    animated: dict[int, Any],
    times: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The joints' world positions at ``times`` and in the rest pose, in the file's units and
    axes: every node a joint depends on composed from the scene root, its baked keys where
    it is animated, else its static transform. The rest pose is checked against ufbx's own
    world transforms first (:func:`_check_rest`), so a file this reader would compose wrongly
    is refused rather than read.

    Returns:
        Positions, shape (T, J, 3); the rest pose, shape (J, 3).
    """
    local = _static_locals(nodes)  # (N, 3, 4) affine, file units
    chain = _ancestors_of(joints, parent)  # every node a joint's world pose depends on
    _check_inheritance(p, nodes, chain, animated)
    world_rest = _compose(local[None], parent, chain)[0]
    _check_rest(p, nodes, joints, world_rest)

    T = len(times)
    frames = np.repeat(local[None], T, axis=0)
    for i, b in animated.items():
        if i in chain:
            frames[:, i] = _baked_affine(b, times)
    world = _compose(frames, parent, chain)
    return world[:, joints][..., 3], world_rest[joints, :, 3]


def _up_turn(
    p: Path, up: str, rest: np.ndarray, joint_parents: tuple[int, ...]
) -> tuple[np.ndarray, str]:
    """The rotation taking the file's up axis to +z, and how the axis was found (for
    ``clip.meta["up"]``): ``up`` as given, or from the rest pose (:func:`detect_up`)."""
    if up == "auto":
        axis = detect_up(p, rest, joint_parents)
        return _turn_to_z_up(axis), f"auto: {axis}"
    return _turn_to_z_up("+" + up), up


def _largest_skeleton(joints: list[int], parent: list[int]) -> list[int]:
    """The joints of the largest skeleton (joints under one topmost joint), in file order."""
    jset = set(joints)

    def top(i: int) -> int:
        t, k = i, parent[i]
        while k >= 0:
            if k in jset:
                t = k
            k = parent[k]
        return t

    tops = [top(i) for i in joints]
    best = max(set(tops), key=lambda t: (tops.count(t), -t))
    return [i for i, t in zip(joints, tops, strict=True) if t == best]


def _joint_parents(joints: list[int], parent: list[int]) -> tuple[int, ...]:
    """Each joint's nearest joint ancestor, as an index into ``joints`` (-1 for none)."""
    pos = {n: k for k, n in enumerate(joints)}
    out = []
    for i in joints:
        k = parent[i]
        while k >= 0 and k not in pos:
            k = parent[k]
        out.append(pos[k] if k >= 0 else -1)
    return tuple(out)


def _ancestors_of(joints: list[int], parent: list[int]) -> set[int]:
    out: set[int] = set()
    for j in joints:
        k = j
        while k >= 0 and k not in out:
            out.add(k)
            k = parent[k]
    return out


def _pick_take(path: Path, scene: Any, take: str | None) -> Any:
    stacks = list(scene.anim_stacks)
    names = [str(s.name) for s in stacks]
    if take is not None:
        if take not in names:
            raise InputError(
                f"{path}: no take {take!r}; the file has: {', '.join(names) or 'none'}"
            )
        return stacks[names.index(take)]
    if not stacks:
        raise InputError(f"{path}: no animation: the file has no take (animation stack)")
    return stacks[0]


def _curves(stack: Any) -> list[Any]:
    """The animation curves of one take (its layers' animated values' curves)."""
    return [
        c
        for layer in stack.layers
        for value in layer.anim_values
        for c in value.curves
        if c is not None
    ]


def _frame_times(path: Path, stack: Any) -> tuple[np.ndarray, float]:
    """The frame times [s] and rate of a take, from its keys: the rate is the inverse of the
    most common spacing of successive keys over its curves."""
    steps, lo, hi = [], math.inf, -math.inf
    for curve in _curves(stack):
        keys = curve.get_keyframes()
        t = np.asarray(keys["time"], dtype=float) if len(keys) else np.zeros(0)
        if t.size == 0:
            continue
        lo, hi = min(lo, float(t.min())), max(hi, float(t.max()))
        d = np.diff(t)
        steps.append(d[d > 1e-9])
    dt = np.concatenate(steps) if steps else np.zeros(0)
    if dt.size == 0 or not math.isfinite(hi - lo) or hi <= lo:
        raise InputError(
            f"{path}: no animation: no node has keys at two different times in take {stack.name!r}"
        )
    # The most common spacing (to a microsecond; a clip with a few missing keys keeps its
    # rate), refined as the median of the spacings near it.
    vals, counts = np.unique(np.round(dt, 6), return_counts=True)
    mode = float(vals[np.argmax(counts)])
    step = float(np.median(dt[np.abs(dt - mode) <= 0.01 * mode]))
    fps = 1.0 / step
    n = round((hi - lo) / step) + 1
    if n > MAX_FRAMES:
        raise InputError(
            f"{path}: take {stack.name!r} spans {hi - lo:.6g} s at {fps:.6g} frames/s: {n} "
            f"frames, more than the {MAX_FRAMES} this reader takes (a key time out of range?)"
        )
    return lo + np.arange(n) / fps, fps


def _affine(t: np.ndarray, q_xyzw: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``[R diag(s) | t]`` from translations, xyzw quaternions and scales. (..., 3, 4)."""
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    rot = quat_to_matrix(np.concatenate([q[..., 3:], q[..., :3]], axis=-1))
    return np.concatenate([rot * np.asarray(s)[..., None, :], np.asarray(t)[..., :, None]], -1)


def _static_locals(nodes: list[Any]) -> np.ndarray:
    out = np.zeros((len(nodes), 3, 4))
    for i, n in enumerate(nodes):
        lt = n.local_transform
        out[i] = _affine(
            np.array(list(lt.translation), dtype=float),
            np.array(list(lt.rotation), dtype=float),
            np.array(list(lt.scale), dtype=float),
        )
    return out


def _interp(keys: Any, fields: tuple[str, ...], times: np.ndarray) -> np.ndarray:
    """A baked channel at ``times`` (linear between keys, held beyond them). (T, len(fields))."""
    kt = np.asarray(keys["time"], dtype=float)
    val = keys["value"]
    return np.stack([np.interp(times, kt, np.asarray(val[f], dtype=float)) for f in fields], -1)


def _baked_affine(node: Any, times: np.ndarray) -> np.ndarray:
    t = _interp(node.translation_keys, ("x", "y", "z"), times)
    rk = node.rotation_keys
    q = np.stack([np.asarray(rk["value"][f], dtype=float) for f in "xyzw"], -1)
    # Keys on one hemisphere (ufbx bakes for linear interpolation; a sign flip would not be).
    flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=-1) < 0, -1.0, 1.0))
    q[1:] *= flip[:, None]
    kt = np.asarray(rk["time"], dtype=float)
    qi = np.stack([np.interp(times, kt, q[:, k]) for k in range(4)], -1)
    s = _interp(node.scale_keys, ("x", "y", "z"), times)
    return _affine(t, qi, s)


def _compose(local: np.ndarray, parent: list[int], chain: set[int]) -> np.ndarray:
    """World affines of the nodes in ``chain`` (others stay zero). local: (T, N, 3, 4)."""
    world = np.zeros_like(local)
    done: set[int] = set()

    def visit(i: int) -> None:
        if i in done:
            return
        k = parent[i]
        if k < 0:
            world[:, i] = local[:, i]
        else:
            visit(k)
            a, b = world[:, k], local[:, i]
            world[:, i, :, :3] = a[:, :, :3] @ b[:, :, :3]
            world[:, i, :, 3] = (a[:, :, :3] @ b[:, :, 3:])[..., 0] + a[:, :, 3]
        done.add(i)

    for i in sorted(chain):
        visit(i)
    return world


def _check_inheritance(path: Path, nodes: list[Any], chain: set[int], animated: dict) -> None:
    """Nodes that do not inherit their parent's scale normally compose as normal ones only while
    every scale on the way is 1: refuse the file otherwise (rather than place joints wrongly)."""
    odd = [i for i in chain if getattr(nodes[i].inherit_mode, "name", "NORMAL") != "NORMAL"]
    if not odd:
        return
    for i in chain:
        s = np.array(list(nodes[i].local_transform.scale), dtype=float)
        scaled = not np.allclose(s, 1.0, atol=1e-6)
        if i in animated:
            v = animated[i].scale_keys["value"]
            keys = np.stack([np.asarray(v[f], dtype=float) for f in "xyz"], -1)
            scaled = scaled or not np.allclose(keys, 1.0, atol=1e-6)
        if scaled:
            n = nodes[odd[0]]
            raise InputError(
                f"{path}: node {n.name!r} does not inherit its parent's scale normally "
                f"({n.inherit_mode.name}) and node {nodes[i].name!r} is scaled: this reader "
                "composes normal inheritance only"
            )


def _check_rest(path: Path, nodes: list[Any], joints: list[int], world: np.ndarray) -> None:
    """This module's rest pose against ufbx's ``node_to_world`` of the same nodes."""
    ours = world[joints, :, 3]
    theirs = np.array([[nodes[i].node_to_world[f"m{r}3"] for r in range(3)] for i in joints])
    size = max(float(np.ptp(theirs, axis=0).max()), 1e-9)
    err = np.abs(ours - theirs).max(axis=1)
    if float(err.max()) > REST_CHECK_TOL * size:
        k = int(np.argmax(err))
        raise InputError(
            f"{path}: joint {nodes[joints[k]].name!r}: composing the file's transforms puts it "
            f"{err[k]:.3g} units from where ufbx does; this FBX uses transform features this "
            "reader does not support"
        )


def detect_up(path: Path, rest: np.ndarray, parents: tuple[int, ...]) -> str:
    """The up axis of a human skeleton's rest pose: from the hips (the first joint with three
    or more children, down from the root) the largest child subtree is the spine's (arms, head),
    the others are the legs; up is the axis (``+x`` ... ``-z``) nearest the direction from the
    legs' joints' mean to the spine's.

    Raises:
        InputError: No such branching, or no axis within :data:`UP_AXIS_MIN_ALIGNMENT`.
    """
    children: list[list[int]] = [[] for _ in parents]
    for j, k in enumerate(parents):
        if k >= 0:
            children[k].append(j)
    hips = next((j for j in range(len(parents)) if len(children[j]) >= 3), None)
    if hips is None:
        raise InputError(
            f"{path}: up='auto' needs a hip joint with the spine and two legs below it; none "
            "has three children: pass the up axis (--up y or --up z)"
        )

    def subtree(j: int) -> list[int]:
        out, stack = [], [j]
        while stack:
            k = stack.pop()
            out.append(k)
            stack.extend(children[k])
        return out

    branches = sorted((subtree(c) for c in children[hips]), key=len, reverse=True)
    spine = rest[branches[0]].mean(axis=0)
    legs = rest[[k for b in branches[1:] for k in b]].mean(axis=0)
    v = spine - legs
    norm = float(np.linalg.norm(v))
    k = int(np.argmax(np.abs(v)))
    if norm == 0 or abs(v[k]) / norm < UP_AXIS_MIN_ALIGNMENT:
        raise InputError(
            f"{path}: up='auto' cannot tell the up axis (the spine over the legs points "
            f"{np.round(v / max(norm, 1e-12), 2).tolist()}): pass --up y or --up z"
        )
    return ("+" if v[k] > 0 else "-") + "xyz"[k]


def _turn_to_z_up(axis: str) -> np.ndarray:
    """A proper rotation taking the file's up axis to +z (y up: the BVH convention's turn)."""
    if axis == "+y":
        return Y_UP_TO_Z_UP
    if axis == "+z":
        return np.eye(3)
    e = np.zeros(3)
    e["xyz".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
    z = np.array([0.0, 0.0, 1.0])
    if e @ z < 0:  # -z: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(e, z)  # a quarter turn about e x z
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + K + K @ K
