"""The humanoid structure of a model ``humimic robots add`` reads (:mod:`humimic.robots.add`):
feet, knees, hips, hands, elbows, shoulders, torso and head found from its kinematic tree and
collision geometry at ``qpos0``, and the way it faces (:func:`find_structure`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from humimic.errors import InputError
from humimic.robots.collision import robot_geoms


@dataclass(kw_only=True)
class Structure:
    """The humanoid structure found in a model (body names; None where not found)."""

    root: str
    torso: str
    feet: dict[str, str]
    hips: dict[str, str]
    knees: dict[str, str | None]
    shoulders: dict[str, str | None] = field(default_factory=dict)
    elbows: dict[str, str | None] = field(default_factory=dict)
    hands: dict[str, str | None] = field(default_factory=dict)
    head: str | None = None
    height: float = 0.0
    forward: tuple[float, float, float] = (1.0, 0.0, 0.0)
    """The robot's forward direction at ``qpos0``, in the world (where its toes point)."""

    def missing(self) -> list[str]:
        """What was not found, as the check list says it."""
        out = []
        for what, d in (("knee", self.knees), ("shoulder", self.shoulders),
                        ("elbow", self.elbows), ("hand", self.hands)):  # fmt: skip
            for side in ("left", "right"):
                if d.get(side) is None:
                    out.append(f"{side} {what}")
        if self.head is None:
            out.append("head")
        return out


def geom_bounds(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> np.ndarray:
    """World-frame corners of a geom's bounding box. Shape: (8, 3)."""
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
        return np.zeros((0, 3))
    c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    local = c + signs * h
    return data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T


@dataclass
class _Tree:
    """A compiled model's bodies under its floating root at ``qpos0``, with what
    :func:`find_structure` reads of them: their children, their collision geometry's corners
    and where each body's geometry reaches lowest (``inf`` where it has none)."""

    model: mujoco.MjModel
    data: mujoco.MjData
    root: int
    bodies: list[int]
    kids: dict[int, list[int]]
    leaves: list[int]
    geoms: list[int]
    corners: dict[int, np.ndarray]
    low: dict[int, float]
    ground: float
    height: float

    def chain(self, b: int) -> list[int]:
        """The bodies from the root down to ``b`` (the root first)."""
        out = [b]
        while out[-1] != self.root:
            out.append(int(self.model.body_parentid[out[-1]]))
        return out[::-1]  # root first

    def subtree(self, b: int) -> list[int]:
        """``b`` and every body below it."""
        out, todo = [], [b]
        while todo:
            x = todo.pop()
            out.append(x)
            todo += self.kids[x]
        return out

    def lowest_in(self, b: int) -> float:
        """How low the geometry of ``b``'s subtree reaches."""
        return min(self.low[x] for x in self.subtree(b))

    def middle(self, seq: list[int], a: int, b: int) -> int | None:
        """The jointed body of chain ``seq`` strictly between ``a`` and ``b`` farthest from
        both (a knee between hip and foot, an elbow between shoulder and hand), or None."""
        inner = seq[seq.index(a) + 1 : seq.index(b)]
        inner = [x for x in inner if self.model.body_jntnum[x] > 0]
        if not inner:
            return None
        pa, pb = self.data.xpos[a], self.data.xpos[b]
        return max(inner, key=lambda x: min(np.linalg.norm(self.data.xpos[x] - pa),
                                            np.linalg.norm(self.data.xpos[x] - pb)))  # fmt: skip


def _tree(model: mujoco.MjModel, root: int) -> _Tree:
    """The tree under ``root`` at ``qpos0`` and its collision geometry.

    Raises:
        InputError: The robot has no collision geometry.
    """
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    parent = model.body_parentid
    bodies = [b for b in range(model.nbody) if model.body_rootid[b] == root]
    kids: dict[int, list[int]] = {b: [] for b in bodies}
    for b in bodies:
        if b != root:
            kids[int(parent[b])].append(b)
    geoms = robot_geoms(model, model.body(root).name)
    if not geoms:
        raise InputError("the model has no collision geometry on its bodies")
    corners = {g: geom_bounds(model, data, g) for g in geoms}
    low = {b: min((corners[g][:, 2].min() for g in geoms if model.geom_bodyid[g] == b),
                  default=np.inf) for b in bodies}  # fmt: skip
    ground = min(low.values())
    top = max(corners[g][:, 2].max() for g in geoms)
    height = float(top - ground)
    leaves = [b for b in bodies if not kids[b] and b != root]
    return _Tree(model=model, data=data, root=root, bodies=bodies, kids=kids, leaves=leaves,
                 geoms=geoms, corners=corners, low=low, ground=ground,
                 height=height)  # fmt: skip


def find_structure(model: mujoco.MjModel, root: int) -> Structure:
    """The humanoid structure of a compiled model standing at ``qpos0`` (its root's frame: x
    forward, y left, z up): the feet are the lowest collision geometry at the ends of the two
    lowest chains, one per side; the hips the first bodies of those chains below the body they
    share; the knees the chain bodies nearest mid-height; the hands the bodies where each side's
    upper chains end (the common ancestor of a hand's fingers); the shoulders and elbows likewise
    on the arms; the torso the body both arms leave from; the head the highest central chain.

    Raises:
        InputError: No two feet found (no legs), or no collision geometry.
    """
    t = _tree(model, root)
    data = t.data
    foot_ends = _foot_ends(t)
    # Forward: perpendicular to the line between the feet, the way the toes point: where a
    # knee bent into its range moves the foot away from (knees bend backward); where no
    # joint of the leg is a one-sided knee about the sideways axis, where the feet's geometry
    # reaches beyond the ankles (toes are longer than heels); else the root frame's x.
    fwd = _forward(
        model, data, root, foot_ends, [t.chain(b) for b in foot_ends], t.corners, t.geoms, t.height
    )
    left_axis = np.cross([0.0, 0.0, 1.0], fwd)
    axes = np.stack([fwd, left_axis, [0.0, 0.0, 1.0]])
    local = {b: axes @ (data.xpos[b] - data.xpos[root]) for b in t.bodies}
    feet = _sided_feet(t, foot_ends, local)
    lc, rc = t.chain(feet["left"]), t.chain(feet["right"])
    common = [b for b in lc if b in rc]
    hips = {"left": lc[len(common)], "right": rc[len(common)]}
    _check_legs(t, feet, hips)
    knees = {s: t.middle(c, hips[s], feet[s]) for s, c in (("left", lc), ("right", rc))}
    legs = set(t.subtree(hips["left"])) | set(t.subtree(hips["right"]))
    width = float(np.linalg.norm(local[hips["left"]] - local[hips["right"]]))
    upper = [b for b in t.leaves if b not in legs]  # Hanging arms reach below the hips.
    structure = Structure(root=model.body(root).name, torso=model.body(root).name,
                          feet={s: model.body(b).name for s, b in feet.items()},
                          hips={s: model.body(b).name for s, b in hips.items()},
                          knees={s: (model.body(b).name if b is not None else None)
                                 for s, b in knees.items()},
                          height=t.height,
                          forward=(float(fwd[0]), float(fwd[1]), float(fwd[2])))  # fmt: skip
    _find_arms(t, structure, upper, local, width)
    return structure


def _foot_ends(t: _Tree) -> list[int]:
    """The foot bodies (none, one or two): the two leaves whose subtrees' geometry is lowest
    (within 5 % of the height of the ground), apart sideways; each foot body the body on its
    chain with the lowest geometry."""
    cands = sorted(
        (b for b in t.leaves if t.lowest_in(b) < t.ground + 0.05 * t.height), key=t.lowest_in
    )
    pair: list[int] = []
    for b in cands:
        if (
            not pair
            or np.linalg.norm((t.data.xpos[b] - t.data.xpos[pair[0]])[:2]) > 0.03 * t.height
        ):
            pair.append(b)
        if len(pair) == 2:
            break
    return [min(t.chain(b), key=lambda x: (t.low[x], -len(t.chain(x)))) for b in pair]


def _sided_feet(t: _Tree, foot_ends: list[int], local: dict[int, np.ndarray]) -> dict[str, int]:
    """The two feet by side (the left one further along the robot's left axis).

    Raises:
        InputError: Fewer than two feet found (no legs), saying what was found.
    """
    feet: dict[str, int] = {}
    if len(foot_ends) == 2:
        a, b = sorted(foot_ends, key=lambda x: -local[x][1])
        feet = {"left": a, "right": b}
    if len(feet) < 2:
        model = t.model
        found = ", ".join(model.body(b).name for b in foot_ends) or "none"
        bare = sum(1 for b in t.bodies if b != t.root and t.low[b] == np.inf)
        raise InputError(
            f"no legs found: no two chains end near the ground apart from each other (found "
            f"{found}; {bare} of {len(t.bodies) - 1} bodies have no collision geometry; humimic "
            "needs z up at qpos0 and collision geometry on the feet)"
        )
    return feet


def _check_legs(t: _Tree, feet: dict[str, int], hips: dict[str, int]) -> None:
    """Refuses chains that are not legs: legs hang from the root's height or below, and are
    long; a model without legs has its hands lowest, on arms that leave the torso above the
    root.

    Raises:
        InputError: A side's lowest chain is not a leg, saying where it leaves the body.
    """
    model, data, root, height = t.model, t.data, t.root, t.height
    for side, hip in hips.items():
        drop = data.xpos[hip, 2] - t.low[feet[side]]
        if data.xpos[hip, 2] > data.xpos[root, 2] + 0.05 * height or drop < 0.3 * height:
            raise InputError(
                f"no legs found: the lowest chain on the {side} ({model.body(feet[side]).name}) "
                f"leaves the body at {model.body(hip).name}, "
                f"{data.xpos[hip, 2] - data.xpos[root, 2]:+.2f} m from the root, "
                f"{drop:.2f} m above its end (legs start at the root's height or below and "
                "reach down at least 30 % of the height)"
            )


def _find_arms(
    t: _Tree, structure: Structure, upper: list[int], local: dict[int, np.ndarray], width: float
) -> None:
    """The arms, torso and head set on ``structure`` where both sides have upper chains: each
    side's hand is where its upper chains (those more than a quarter of the hips' width to
    that side) meet; the torso is where both hands' chains meet, the shoulders the first
    bodies below it, the elbows midway; the head the highest central chain below the torso."""
    model = t.model
    ends: dict[str, int] = {}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        mine = [b for b in upper if sign * local[b][1] > 0.25 * width]
        if not mine:
            continue
        chains = [t.chain(b) for b in mine]
        shared = [b for b in chains[0] if all(b in c for c in chains)]
        ends[side] = shared[-1]
    if len(ends) != 2:
        return
    la, ra = t.chain(ends["left"]), t.chain(ends["right"])
    shared = [b for b in la if b in ra]
    torso = shared[-1]
    structure.torso = model.body(torso).name
    for side, c in (("left", la), ("right", ra)):
        if len(c) <= len(shared):
            continue
        shoulder = c[len(shared)]
        structure.shoulders[side] = model.body(shoulder).name
        structure.hands[side] = model.body(ends[side]).name
        elbow = t.middle(c, shoulder, ends[side])
        structure.elbows[side] = model.body(elbow).name if elbow is not None else None
    centre = [b for b in upper if abs(local[b][1]) <= 0.25 * width]
    centre = [b for b in centre if torso in t.chain(b) and b != torso]
    if centre:
        structure.head = model.body(max(centre, key=lambda b: t.data.xpos[b, 2])).name


def _forward(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    root: int,
    feet: list[int],
    chains: list[list[int]],
    corners: dict[int, np.ndarray],
    geoms: list[int],
    height: float,
) -> np.ndarray:
    """The robot's forward direction at ``qpos0`` (a horizontal unit vector): see
    :func:`find_structure`."""
    up = np.array([0.0, 0.0, 1.0])
    if len(feet) == 2:
        side = data.xpos[feet[0]] - data.xpos[feet[1]]
        side[2] = 0.0
        side /= max(float(np.linalg.norm(side)), 1e-9)
        ahead = np.cross(side, up)  # Forward up to its sign.
        back = np.zeros(3)
        probe = mujoco.MjData(model)
        for foot, ch in zip(feet, chains, strict=True):
            # The knee: the hinge about the sideways axis nearest the leg's mid-height.
            mid = 0.5 * (data.xpos[ch[1], 2] + data.xpos[foot, 2]) if len(ch) > 1 else 0.0
            best, best_dz = -1, np.inf
            for b in ch[1:-1]:
                for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
                    if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE or not model.jnt_limited[j]:
                        continue
                    axis = data.xmat[b].reshape(3, 3) @ model.jnt_axis[j]
                    dz = abs(float(data.xpos[b, 2]) - mid)
                    if abs(float(axis @ side)) > 0.7 and dz < best_dz:
                        best, best_dz = j, dz
            if best < 0:
                continue
            lo, hi = (float(v) for v in model.jnt_range[best])
            if max(abs(lo), abs(hi)) < 1.0 or max(abs(lo), abs(hi)) < 3.0 * min(abs(lo), abs(hi)):
                continue  # Not one-sided: says nothing about which way it bends.
            probe.qpos[:] = model.qpos0
            probe.qpos[model.jnt_qposadr[best]] = 0.5 if hi > -lo else -0.5
            mujoco.mj_kinematics(model, probe)
            back += probe.xpos[foot] - data.xpos[foot]
        if abs(float(back @ ahead)) > 0.02 * height:
            return -ahead * np.sign(float(back @ ahead))
        reach = np.zeros(3)
        for f in feet:
            pts = np.vstack([corners[g] for g in geoms if model.geom_bodyid[g] == f])
            reach += pts.mean(axis=0) - data.xpos[f]
        if abs(float(reach @ ahead)) > 0.01 * height:
            return ahead * np.sign(float(reach @ ahead))
    x = data.xmat[root].reshape(3, 3)[:, 0].copy()
    x[2] = 0.0
    return x / max(float(np.linalg.norm(x)), 1e-9)
