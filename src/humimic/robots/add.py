"""``humimic robots add``: any humanoid, from its MJCF or URDF, as a robot every command takes.

The model is read by MuJoCo's own compiler (URDF too); what MuJoCo cannot use is made usable and
said: a URDF gets a floating base (a ``floating`` joint from a new world link: MuJoCo makes it a
free joint), its visual geometry is dropped (the viewer draws the collision geometry), collision
meshes MuJoCo cannot read (DAE and the like) are converted with trimesh or, where trimesh cannot
read them either, replaced by the box of the link's inertia. A floor is added where the model has
none, position actuators where it has none. Then the robot's humanoid structure is found from
its tree and geometry (:func:`find_structure`: feet, knees, hips, hands, elbows, shoulders,
torso, head) and a robot map of humimic's canonical key points is written from it, beside a
``robot.yaml`` with a motor per joint (the model's effort limits where it gives them, stated
defaults where not). Everything lands in one folder under the user's robots folder
(:mod:`humimic.robots.user`), written whole or not at all.
"""

from __future__ import annotations

import math
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from humimic.errors import InputError, OutputPathError
from humimic.io import atomic_write_text
from humimic.robots.actuators import ActuatorRecipe
from humimic.robots.collision import robot_geoms
from humimic.robots.registry import ROBOTS
from humimic.robots.user import MAP_FILE, NAME_PATTERN, ROBOT_FILE, SCHEMA_VERSION, robots_dir

MESH_FORMATS = (".stl", ".obj", ".msh")
"""Mesh files MuJoCo reads itself."""
DEFAULT_ARMATURE_SWING = 0.5
"""Where a model gives no rotor inertia, the armature is chosen so that the gain recipe's kp
is the joint's effort limit over this many radians (a servo saturating at half a radian)."""
BOUND_MASS = 1e-3
"""Smallest link mass [kg] in an added URDF (massless links between joints get it)."""
BOUND_INERTIA = 1e-6
"""Smallest link principal inertia [kg m^2] in an added URDF."""
MIN_INERTIA = 1e-10
"""A link inertia's smallest principal moment below this [kg m^2] is broken (iCub's ankles
give 1e-20: MuJoCo refuses them)."""
RECIPE_HZ = ActuatorRecipe.natural_frequency_hz
"""The gain recipe's natural frequency an added robot gets (the registered robots' default)."""
DEFAULT_SPEED = 20.0
"""Joint speed limit [rad/s] where the model gives none: a stated default, as for the
registered robots without one."""


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


@dataclass(kw_only=True)
class AddResult:
    """What ``robots add`` did."""

    name: str
    folder: Path
    structure: Structure
    notes: list[str]
    joints: int
    mass: float


# --- Reading the model ---------------------------------------------------------------------


def _resolve_mesh(filename: str, model: Path) -> Path:
    """A mesh file name as URDFs write it (``package://pkg/...``, ``file://``, relative to the
    URDF, absolute) as a path: ``package://pkg`` is the nearest folder named ``pkg`` among the
    URDF's folder, its parents and their children."""
    if filename.startswith("file://"):
        return Path(filename[len("file://") :])
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://") :].partition("/")
        for folder in [model.parent, *model.parent.parents]:
            for base in (folder, folder / pkg):
                if base.name == pkg and base.is_dir():
                    return base / rest
        return model.parent / pkg / rest
    p = Path(filename)
    return p if p.is_absolute() else model.parent / p


def _numbers(el: ET.Element, key: str, link: ET.Element) -> list[float]:
    """The numbers of an attribute (``0`` where absent), or refused naming the link."""
    text = el.get(key, "0")
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(f"link {link.get('name')!r}: <{el.tag} {key}={text!r}>: not numbers")
    return values


def _inertia_box(link: ET.Element) -> tuple[list[float], list[float]] | None:
    """The box (size, centre) with the link's mass and principal inertia, or None."""
    inertial = link.find("inertial")
    mass_el = inertial.find("mass") if inertial is not None else None
    i = inertial.find("inertia") if inertial is not None else None
    if inertial is None or mass_el is None or i is None:
        return None
    mass = _numbers(mass_el, "value", link)[0]
    ixx, iyy, izz = (_numbers(i, k, link)[0] for k in ("ixx", "iyy", "izz"))
    if mass <= 0:
        return None
    sq = [
        6.0 / mass * (iyy + izz - ixx),
        6.0 / mass * (ixx + izz - iyy),
        6.0 / mass * (ixx + iyy - izz),
    ]
    size = [math.sqrt(max(v, 1e-6)) for v in sq]
    origin = inertial.find("origin")
    centre = _numbers(origin, "xyz", link) if origin is not None else [0.0, 0.0, 0.0]
    if len(centre) != 3:
        raise InputError(f"link {link.get('name')!r}: <origin xyz=...>: expected 3 numbers")
    return size, centre


def _read_urdf(path: Path, assets: Path, notes: list[str]) -> mujoco.MjSpec:
    """The URDF as a spec with a floating base, collision geometry only, its meshes copied
    (or converted) into ``assets``."""
    try:
        tree = ET.parse(path)
    except ET.ParseError as e:
        raise InputError(f"{path}: not valid XML: {e}") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read: {e.strerror}") from None
    robot = tree.getroot()
    if robot.tag != "robot":
        raise InputError(f"{path}: not a URDF (its root element is <{robot.tag}>, not <robot>)")
    links = {lk.get("name"): lk for lk in robot.findall("link")}
    joints = robot.findall("joint")
    children = {j.find("child").get("link") for j in joints if j.find("child") is not None}  # type: ignore[union-attr]
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise InputError(
            f"{path}: no floating root found: {len(roots)} links are no joint's child "
            f"({', '.join(map(str, roots[:5]))}); a humanoid URDF has one"
        )
    root = roots[0]
    # A "world" link fixed to the robot's base: the base is the root.
    fixed = [j for j in joints if j.find("parent") is not None
             and j.find("parent").get("link") == root]  # type: ignore[union-attr]  # fmt: skip
    if (
        links[root].find("inertial") is None
        and len(fixed) == 1
        and fixed[0].get("type") in ("fixed", "floating")
    ):
        child = fixed[0].find("child").get("link")  # type: ignore[union-attr]
        robot.remove(fixed[0])
        robot.remove(links[root])
        notes.append(f"link {root!r} (the world, fixed to {child!r}) dropped: {child!r} floats")
        root = child
    try:
        for link in links.values():
            _repair_inertia(link, notes)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    visual = 0
    for link in links.values():
        for v in link.findall("visual"):
            link.remove(v)
            visual += 1
    if visual:
        notes.append(f"{visual} visual elements dropped (the viewer draws collision geometry)")
    used: set[str] = set()
    # (source mesh, scale) -> its file in assets: links that share a mesh share one copy.
    done: dict[tuple[Path, str | None], str] = {}
    for link in robot.findall("link"):
        for col in link.findall("collision"):
            geom = col.find("geometry")
            mesh = geom.find("mesh") if geom is not None else None
            if geom is None or mesh is None:
                continue
            src = _resolve_mesh(mesh.get("filename", ""), path)
            if not src.is_file():
                raise InputError(
                    f"{path}: link {link.get('name')!r}: collision mesh {mesh.get('filename')!r}"
                    f" not found (looked for {src})"
                )
            key = (src, mesh.get("scale"))
            if key in done:
                mesh.set("filename", done[key])
                continue
            stem = src.stem
            name = stem
            k = 1
            while name in used:
                name, k = f"{stem}_{k}", k + 1
            used.add(name)
            if src.suffix.lower() in MESH_FORMATS and not _ascii_stl(src):
                dest = assets / f"{name}{src.suffix.lower()}"
                shutil.copy2(src, dest)
            else:
                dest = assets / f"{name}.stl"
                if not _convert_mesh(src, dest):
                    try:
                        box = _inertia_box(link)
                    except InputError as e:
                        raise InputError(f"{path}: {e}") from None
                    geom.remove(mesh)
                    if box is None:
                        link.remove(col)
                        notes.append(f"{src.name}: MuJoCo and trimesh cannot read it, and link "
                                     f"{link.get('name')!r} has no inertia: dropped")  # fmt: skip
                        continue
                    ET.SubElement(geom, "box", size=" ".join(f"{v:.6g}" for v in box[0]))
                    origin = col.find("origin")
                    if origin is not None:
                        col.remove(origin)
                    ET.SubElement(col, "origin", xyz=" ".join(f"{v:.6g}" for v in box[1]))
                    notes.append(f"{src.name}: MuJoCo and trimesh cannot read it: replaced by "
                                 f"the box of link {link.get('name')!r}'s inertia")  # fmt: skip
                    continue
                notes.append(f"{src.name}: converted to STL (trimesh)")
            mesh.set("filename", dest.name)
            done[key] = dest.name
    ext = ET.SubElement(robot, "mujoco")
    ET.SubElement(ext, "compiler", strippath="false", discardvisual="true", fusestatic="true",
                  balanceinertia="true", meshdir=str(assets))  # fmt: skip
    ET.SubElement(robot, "link", name="humimic_world")
    base = ET.SubElement(robot, "joint", name="floating_base", type="floating")
    ET.SubElement(base, "parent", link="humimic_world")
    ET.SubElement(base, "child", link=str(root))
    text = ET.tostring(robot, encoding="unicode")
    try:
        spec = mujoco.MjSpec.from_string(text)
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot read this URDF: {_one_line(e)}") from None
    # Links without mass between joints (a 3-DoF hip as three links, the "human" URDF's
    # virtual links) get MuJoCo's smallest allowed mass and inertia; meshes count as shells
    # for their (unused: URDF links give their inertia) volume, which flat meshes lack.
    spec.compiler.boundmass, spec.compiler.boundinertia = BOUND_MASS, BOUND_INERTIA
    for mesh in spec.meshes:
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    return spec


def _ascii_stl(path: Path) -> bool:
    """An ASCII STL (MuJoCo reads binary STL only): it starts with ``solid`` and its first
    kilobyte is text with a ``facet``."""
    if path.suffix.lower() != ".stl":
        return False
    with path.open("rb") as f:
        head = f.read(1024)
    return head.lstrip().startswith(b"solid") and b"facet" in head


def _repair_inertia(link: ET.Element, notes: list[str]) -> None:
    """A link inertia that is not positive definite (iCub's ankles) replaced by its diagonal
    made positive; said in the notes. (The triangle inequality MuJoCo's compiler balances.)"""
    i = link.find("inertial/inertia")
    if i is None:
        return
    keys = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    xx, xy, xz, yy, yz, zz = (_numbers(i, k, link)[0] for k in keys)
    m = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    if np.all(np.isfinite(m)) and np.linalg.eigvalsh(m).min() > MIN_INERTIA:
        return
    mass_el = link.find("inertial/mass")
    mass = _numbers(mass_el, "value", link)[0] if mass_el is not None else 0.0
    floor = max(0.4 * mass * 0.03**2, MIN_INERTIA)  # A 3 cm ball of the link's mass.
    diag = np.maximum(np.abs(np.diag(m)), floor)
    for k, v in zip(keys, (diag[0], 0.0, 0.0, diag[1], 0.0, diag[2]), strict=True):
        i.set(k, f"{v:.9g}")
    notes.append(f"link {link.get('name')!r}: its inertia is not positive definite: its "
                 "diagonal used, at least that of a 3 cm ball of its mass")  # fmt: skip


def _convert_mesh(src: Path, dest: Path) -> bool:
    """``src`` as an STL at ``dest`` through trimesh; False where trimesh cannot read it."""
    try:
        import trimesh

        mesh = trimesh.load(str(src), force="mesh")
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            return False
        if src.suffix.lower() == ".dae" and b"<up_axis>Y_UP</up_axis>" in src.read_bytes():
            # COLLADA's up axis, which trimesh leaves to the caller (as ROS's loaders do
            # not): y up in the file is z up here, a quarter turn about x.
            mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
        mesh.export(str(dest))
        return True
    except Exception:
        return False


def _read_mjcf(path: Path, assets: Path, notes: list[str]) -> mujoco.MjSpec:
    """The MJCF as a spec, its meshes copied into ``assets``."""
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot read this model: {_one_line(e)}") from None
    meshdir = path.parent / (spec.meshdir or "")
    for i, mesh in enumerate(spec.meshes):
        if not mesh.file:
            continue
        src = Path(mesh.file) if Path(mesh.file).is_absolute() else meshdir / mesh.file
        if not src.is_file():
            raise InputError(f"{path}: mesh {mesh.name or mesh.file!r}: no file {src}")
        dest = assets / f"{i}_{src.name}"
        shutil.copy2(src, dest)
        mesh.file = dest.name
    spec.meshdir = str(assets)
    top = list(spec.worldbody.bodies)
    if not top:
        raise InputError(f"{path}: no floating root found: the model has no body")
    moving = [b for b in top if list(b.joints) or list(b.bodies)]
    if len(moving) != 1:
        raise InputError(
            f"{path}: no floating root found: {len(moving)} top-level bodies with joints or "
            "children; a humanoid model has one"
        )
    root = moving[0]
    joints = list(root.joints)
    if not joints:
        root.add_freejoint(name="floating_base")
        notes.append(f"body {root.name!r} was fixed to the world: given a free joint")
    elif joints[0].type != mujoco.mjtJoint.mjJNT_FREE:
        raise InputError(
            f"{path}: no floating root found: body {root.name!r}'s first joint is a "
            f"{joints[0].type.name} joint, not a free one"
        )
    return spec


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())[:300]


# --- Making it a humimic robot -------------------------------------------------------------


def _complete(spec: mujoco.MjSpec, path: Path, notes: list[str]) -> str:
    """Floor, light, collision groups and actuators; returns the floor geom's name."""
    for j in spec.joints:
        if j.type in (mujoco.mjtJoint.mjJNT_BALL,) or (
            j.type == mujoco.mjtJoint.mjJNT_FREE and j is not next(iter(spec.joints))
        ):
            raise InputError(
                f"{path}: joint {j.name!r} is a {j.type.name} joint; humimic needs hinge and "
                "slide joints after the base's free joint"
            )
    planes = [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE]
    if planes:
        floor = planes[0]
        if not floor.name:
            floor.name = "floor"
    else:
        floor = spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE,
                                        size=[0, 0, 0.05], rgba=[0.5, 0.55, 0.6, 1])  # fmt: skip
        spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
        notes.append("a floor added")
    floor.contype, floor.conaffinity = 1, 1
    hinge = [j for j in spec.joints if j.type in (mujoco.mjtJoint.mjJNT_HINGE,
                                                   mujoco.mjtJoint.mjJNT_SLIDE)]  # fmt: skip
    if len(hinge) < 6:
        raise InputError(f"{path}: {len(hinge)} hinge or slide joints: not a humanoid (no legs)")
    if not list(spec.actuators):
        for j in hinge:
            spec.add_actuator(name=j.name, target=j.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        notes.append(f"{len(hinge)} position actuators added, one per joint")
    return str(floor.name)


def _geom_bounds(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> np.ndarray:
    """World-frame corners of a geom's bounding box. Shape: (8, 3)."""
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
        return np.zeros((0, 3))
    c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    local = c + signs * h
    return data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T


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
    corners = {g: _geom_bounds(model, data, g) for g in geoms}
    low = {b: min((corners[g][:, 2].min() for g in geoms if model.geom_bodyid[g] == b),
                  default=np.inf) for b in bodies}  # fmt: skip
    ground = min(low.values())
    top = max(corners[g][:, 2].max() for g in geoms)
    height = float(top - ground)

    def chain(b: int) -> list[int]:
        out = [b]
        while out[-1] != root:
            out.append(int(parent[out[-1]]))
        return out[::-1]  # root first

    def subtree(b: int) -> list[int]:
        out, todo = [], [b]
        while todo:
            x = todo.pop()
            out.append(x)
            todo += kids[x]
        return out

    def lowest_in(b: int) -> float:
        return min(low[x] for x in subtree(b))

    leaves = [b for b in bodies if not kids[b] and b != root]
    # Feet: the two leaves whose subtrees' geometry is lowest (within 5 % of the height of
    # the ground), apart sideways; each foot body the body on its chain with the lowest
    # geometry.
    cands = sorted((b for b in leaves if lowest_in(b) < ground + 0.05 * height), key=lowest_in)
    pair: list[int] = []
    for b in cands:
        if not pair or np.linalg.norm((data.xpos[b] - data.xpos[pair[0]])[:2]) > 0.03 * height:
            pair.append(b)
        if len(pair) == 2:
            break
    foot_ends = [min(chain(b), key=lambda x: (low[x], -len(chain(x)))) for b in pair]
    # Forward: perpendicular to the line between the feet, the way the toes point: where a
    # knee bent into its range moves the foot away from (knees bend backward); where no
    # joint of the leg is a one-sided knee about the sideways axis, where the feet's geometry
    # reaches beyond the ankles (toes are longer than heels); else the root frame's x.
    fwd = _forward(
        model, data, root, foot_ends, [chain(b) for b in foot_ends], corners, geoms, height
    )
    left_axis = np.cross([0.0, 0.0, 1.0], fwd)
    axes = np.stack([fwd, left_axis, [0.0, 0.0, 1.0]])
    local = {b: axes @ (data.xpos[b] - data.xpos[root]) for b in bodies}
    feet: dict[str, int] = {}
    if len(foot_ends) == 2:
        a, b = sorted(foot_ends, key=lambda x: -local[x][1])
        feet = {"left": a, "right": b}
    if len(feet) < 2:
        found = ", ".join(model.body(b).name for b in foot_ends) or "none"
        bare = sum(1 for b in bodies if b != root and low[b] == np.inf)
        raise InputError(
            f"no legs found: no two chains end near the ground apart from each other (found "
            f"{found}; {bare} of {len(bodies) - 1} bodies have no collision geometry; humimic "
            "needs z up at qpos0 and collision geometry on the feet)"
        )
    lc, rc = chain(feet["left"]), chain(feet["right"])
    common = [b for b in lc if b in rc]
    hips = {"left": lc[len(common)], "right": rc[len(common)]}
    # Legs hang from the root's height or below, and are long: a model without legs has its
    # hands lowest, on arms that leave the torso above the root.
    for side, hip in hips.items():
        drop = data.xpos[hip, 2] - low[feet[side]]
        if data.xpos[hip, 2] > data.xpos[root, 2] + 0.05 * height or drop < 0.3 * height:
            raise InputError(
                f"no legs found: the lowest chain on the {side} ({model.body(feet[side]).name}) "
                f"leaves the body at {model.body(hip).name}, "
                f"{data.xpos[hip, 2] - data.xpos[root, 2]:+.2f} m from the root, "
                f"{drop:.2f} m above its end (legs start at the root's height or below and "
                "reach down at least 30 % of the height)"
            )

    def middle(seq: list[int], a: int, b: int) -> int | None:
        inner = seq[seq.index(a) + 1 : seq.index(b)]
        inner = [x for x in inner if model.body_jntnum[x] > 0]
        if not inner:
            return None
        pa, pb = data.xpos[a], data.xpos[b]
        return max(inner, key=lambda x: min(np.linalg.norm(data.xpos[x] - pa),
                                            np.linalg.norm(data.xpos[x] - pb)))  # fmt: skip

    knees = {s: middle(c, hips[s], feet[s]) for s, c in (("left", lc), ("right", rc))}
    legs = set(subtree(hips["left"])) | set(subtree(hips["right"]))
    width = float(np.linalg.norm(local[hips["left"]] - local[hips["right"]]))
    upper = [b for b in leaves if b not in legs]  # Hanging arms reach below the hips.
    structure = Structure(root=model.body(root).name, torso=model.body(root).name,
                          feet={s: model.body(b).name for s, b in feet.items()},
                          hips={s: model.body(b).name for s, b in hips.items()},
                          knees={s: (model.body(b).name if b is not None else None)
                                 for s, b in knees.items()},
                          height=height,
                          forward=(float(fwd[0]), float(fwd[1]), float(fwd[2])))  # fmt: skip
    ends: dict[str, int] = {}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        mine = [b for b in upper if sign * local[b][1] > 0.25 * width]
        if not mine:
            continue
        chains = [chain(b) for b in mine]
        shared = [b for b in chains[0] if all(b in c for c in chains)]
        ends[side] = shared[-1]
    if len(ends) == 2:
        la, ra = chain(ends["left"]), chain(ends["right"])
        shared = [b for b in la if b in ra]
        torso = shared[-1]
        structure.torso = model.body(torso).name
        for side, c in (("left", la), ("right", ra)):
            if len(c) <= len(shared):
                continue
            shoulder = c[len(shared)]
            structure.shoulders[side] = model.body(shoulder).name
            structure.hands[side] = model.body(ends[side]).name
            elbow = middle(c, shoulder, ends[side])
            structure.elbows[side] = model.body(elbow).name if elbow is not None else None
        centre = [b for b in upper if abs(local[b][1]) <= 0.25 * width]
        centre = [b for b in centre if torso in chain(b) and b != torso]
        if centre:
            structure.head = model.body(max(centre, key=lambda b: data.xpos[b, 2])).name
    return structure


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


SOLE_SLAB = 0.02
"""A mesh foot stands on the box of its mesh's vertices within this height [m] of its lowest
point (the sole), not on the box of the whole mesh, which reaches up into the shin."""


def _box_feet(spec: mujoco.MjSpec, model: mujoco.MjModel, s: Structure, notes: list[str]) -> bool:
    """Feet whose collision geometry is meshes stand on boxes: the footprint of each foot
    mesh's lowest :data:`SOLE_SLAB` at ``qpos0`` (aligned with the robot's forward direction,
    1 cm thick) becomes the foot's collision geom, the mesh is kept for the look only (the
    feet's contact points come from boxes, spheres and capsules). Returns whether any foot
    changed."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    fwd = np.asarray(s.forward, dtype=float)
    axes = np.stack([fwd, np.cross([0.0, 0.0, 1.0], fwd), [0.0, 0.0, 1.0]])  # Rows: x y z.
    changed = False
    for side, name in s.feet.items():
        body = model.body(name).id
        meshes = [g for g in robot_geoms(model, s.root) if model.geom_bodyid[g] == body
                  and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]  # fmt: skip
        if not meshes:
            continue
        verts = []
        for g in meshes:
            mid = int(model.geom_dataid[g])
            v = model.mesh_vert[
                model.mesh_vertadr[mid] : model.mesh_vertadr[mid] + model.mesh_vertnum[mid]
            ]
            verts.append(data.geom_xpos[g] + v @ data.geom_xmat[g].reshape(3, 3).T)
        world = np.vstack(verts)
        low = world[world[:, 2] < world[:, 2].min() + SOLE_SLAB] @ axes.T  # In (fwd, left, up).
        lo, hi = low.min(axis=0), low.max(axis=0)
        lo[2], hi[2] = world[:, 2].min(), world[:, 2].min() + 0.01
        centre_w = axes.T @ (0.5 * (lo + hi))
        rot_b = data.xmat[body].reshape(3, 3)
        pos = rot_b.T @ (centre_w - data.xpos[body])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (rot_b.T @ axes.T).ravel())
        spec.body(name).add_geom(name=f"{name}_sole", type=mujoco.mjtGeom.mjGEOM_BOX,
                                 size=(0.5 * (hi - lo)).tolist(), pos=pos.tolist(),
                                 quat=quat.tolist(), contype=1, conaffinity=1,
                                 group=3)  # fmt: skip
        for g in meshes:
            mesh_geom = next((sg for sg in spec.geoms if sg.id == g), None)
            if mesh_geom is not None:
                mesh_geom.contype, mesh_geom.conaffinity, mesh_geom.group = 0, 0, 2
        changed = True
        size = 100 * (hi - lo)
        notes.append(f"{side} foot {name!r}: stands on a {size[0]:.0f} x {size[1]:.0f} cm box, "
                     "the footprint of its collision mesh's lowest 2 cm")  # fmt: skip
    return changed


def _toe_offset(
    model: mujoco.MjModel, data: mujoco.MjData, root: str, foot: int, forward: np.ndarray
) -> list[float]:
    """The toe key point in the foot body's frame: on the bottom of the foot's collision
    geometry, three quarters of the way from the ankle to its front (along ``forward``),
    under the ankle's line."""
    pts = np.vstack([_geom_bounds(model, data, g) for g in robot_geoms(model, root)
                     if model.geom_bodyid[g] == foot])  # fmt: skip
    ankle = data.xpos[foot]
    front = float(((pts - ankle) @ forward).max())
    toe = ankle + 0.75 * front * forward
    toe[2] = float(pts[:, 2].min())
    rot = data.xmat[foot].reshape(3, 3)
    return [round(float(v), 4) for v in rot.T @ (toe - ankle)]


def robot_map(model: mujoco.MjModel, s: Structure, name: str) -> dict[str, Any]:
    """The robot map (the shipped robot maps' form) of a found structure."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)

    def off(body: str, frame_body: str) -> list[float]:
        b, f = model.body(body).id, model.body(frame_body).id
        rot = data.xmat[f].reshape(3, 3)
        return [round(float(v), 4) for v in rot.T @ (data.xpos[b] - data.xpos[f])]

    kp: dict[str, dict[str, Any]] = {"pelvis": {"body": s.root, "weight": 10.0}}
    for side in ("left", "right"):
        kp[f"{side}_hip"] = {"body": s.root, "offset": off(s.hips[side], s.root),
                             "parent": "pelvis", "frame": "pelvis", "weight": 2.0}  # fmt: skip
    for side in ("left", "right"):
        last = f"{side}_hip"
        if s.knees[side] is not None:
            kp[f"{side}_knee"] = {"body": s.knees[side], "parent": last, "weight": 3.0}
            last = f"{side}_knee"
        kp[f"{side}_ankle"] = {"body": s.feet[side], "parent": last, "weight": 10.0}
        foot = model.body(s.feet[side]).id
        toe = _toe_offset(model, data, s.root, foot, np.asarray(s.forward))
        kp[f"{side}_toe"] = {"body": s.feet[side], "offset": toe,
                             "parent": f"{side}_ankle", "weight": 5.0}  # fmt: skip
    arms = all(s.shoulders.get(x) and s.hands.get(x) for x in ("left", "right"))
    if arms:
        ls, rs = str(s.shoulders["left"]), str(s.shoulders["right"])
        mid = 0.5 * (np.array(off(ls, s.torso)) + np.array(off(rs, s.torso)))
        neck = [0.0, 0.0, round(float(mid[2]), 4)]
        kp["neck"] = {"body": s.torso, "offset": neck, "parent": "pelvis", "weight": 3.0}
        for side in ("left", "right"):
            kp[f"{side}_shoulder"] = {"body": s.shoulders[side], "parent": "neck",
                                      "frame": "torso", "weight": 2.0}  # fmt: skip
            last = f"{side}_shoulder"
            if s.elbows.get(side):
                kp[f"{side}_elbow"] = {"body": s.elbows[side], "parent": last, "weight": 3.0}
                last = f"{side}_elbow"
            kp[f"{side}_wrist"] = {"body": s.hands[side], "parent": last, "weight": 4.0}
    else:
        legs = float(np.linalg.norm(data.xpos[model.body(s.hips["left"]).id]
                                    - data.xpos[model.body(s.feet["left"]).id]))  # fmt: skip
        kp["neck"] = {"body": s.root, "offset": [0.0, 0.0, round(0.55 * legs, 4)],
                      "parent": "pelvis", "weight": 3.0}  # fmt: skip
    frames: dict[str, Any] = {
        "pelvis": {"body": s.root, "left": ["right_hip", "left_hip"], "up": ["pelvis", "neck"],
                   "weight": 2.0},
    }  # fmt: skip
    if arms:
        frames["torso"] = {"body": s.torso, "left": ["right_shoulder", "left_shoulder"],
                           "up": ["pelvis", "neck"], "weight": 2.0}  # fmt: skip
    return {
        "schema_version": 1,
        "robot": name,
        "root": "pelvis",
        "posture_weight": 0.05,
        "keypoints": kp,
        "frames": frames,
        "feet": {
            side: {"ankle": f"{side}_ankle", "toe": f"{side}_toe", "body": s.feet[side]}
            for side in ("left", "right")
        },
    }


def _motors(model: mujoco.MjModel, mass: float, height: float) -> tuple[dict[str, Any], list[str]]:
    """A motor per actuated joint: the model's armature and effort limit where it gives them,
    stated defaults where not (said in the notes)."""
    notes: list[str] = []
    default_effort = round(mass * 9.81 * height / 4.0, 1)
    wn = 2.0 * math.pi * RECIPE_HZ
    motors: dict[str, Any] = {}
    no_effort, no_armature = [], []
    for a in range(model.nu):
        j = int(model.actuator_trnid[a, 0])
        name = model.joint(j).name
        effort = (float(model.jnt_actfrcrange[j, 1]) if model.jnt_actfrclimited[j]
                  else float(model.actuator_forcerange[a, 1]) if model.actuator_forcelimited[a]
                  else 0.0)  # fmt: skip
        if effort <= 0:
            effort = default_effort
            no_effort.append(name)
        armature = float(model.dof_armature[model.jnt_dofadr[j]])
        if armature <= 0:
            armature = effort / (DEFAULT_ARMATURE_SWING * wn * wn)
            no_armature.append(name)
        motors[name] = {"armature": float(f"{armature:.6g}"), "effort_limit": effort,
                        "velocity_limit": DEFAULT_SPEED}  # fmt: skip
    if no_effort:
        notes.append(f"{len(no_effort)} joints give no effort limit: {default_effort} N m stated "
                     "(mass x g x height / 4)")  # fmt: skip
    if no_armature:
        notes.append(f"{len(no_armature)} joints give no armature: chosen so that kp is the "
                     f"effort limit over {DEFAULT_ARMATURE_SWING} rad")  # fmt: skip
    notes.append(f"joint speeds: {DEFAULT_SPEED} rad/s stated (the model gives none)")
    return motors, notes


def add_robot(
    model_path: str | Path, name: str, *, root: Path | None = None, force: bool = False
) -> AddResult:
    """Add the humanoid in ``model_path`` (MJCF ``.xml`` or ``.urdf``) as robot ``name`` under
    ``root`` (default :func:`~humimic.robots.user.robots_dir`).

    Raises:
        InputError: A bad name, a model that cannot be read or is not a humanoid (no floating
            root, no legs, broken XML, missing meshes), naming what is wrong.
        OutputPathError: The robot exists (without ``force``) or the folder cannot be written.
    """
    import yaml

    path = Path(model_path)
    if not NAME_PATTERN.fullmatch(name):
        raise InputError(f"--name {name!r}: lower case letters, digits and _, a letter first")
    if name in ROBOTS:
        raise InputError(f"--name {name!r}: a registered robot has that name; choose another")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    kind = path.suffix.lower()
    if kind not in (".xml", ".urdf"):
        raise InputError(f"{path}: expected an MJCF .xml or a .urdf file")
    base = robots_dir() if root is None else Path(root)
    dest = base / name
    if dest.exists() and not force:
        raise OutputPathError(f"{dest}: robot {name!r} was added already; --force replaces it")
    try:
        base.mkdir(parents=True, exist_ok=True)
        tmp = base / f".{name}.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        (tmp / "assets").mkdir(parents=True)
    except OSError as e:
        raise OutputPathError(f"{base}: cannot write the robot's folder: {e.strerror}") from None
    try:
        notes: list[str] = []
        assets = (tmp / "assets").resolve()
        spec = (_read_urdf if kind == ".urdf" else _read_mjcf)(path, assets, notes)
        floor = _complete(spec, path, notes)
        try:
            model = spec.compile()
        except ValueError as e:
            raise InputError(f"{path}: MuJoCo cannot compile this model: {_one_line(e)}") from None
        free = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
        root_body = int(model.jnt_bodyid[free])
        try:
            structure = find_structure(model, root_body)
        except InputError as e:
            raise InputError(f"{path}: {e}") from None
        if _box_feet(spec, model, structure, notes):
            try:
                model = spec.compile()
            except ValueError as e:
                raise InputError(f"{path}: MuJoCo cannot compile the model with box feet: "
                                 f"{_one_line(e)}") from None  # fmt: skip
        mass = float(model.body_subtreemass[root_body])
        motors, motor_notes = _motors(model, mass, structure.height)
        notes += motor_notes
        # Stand the robot on the floor at qpos0: its root at the height that puts the lowest
        # collision point on z = 0.
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        lowest = min(float(_geom_bounds(model, data, g)[:, 2].min())
                     for g in robot_geoms(model, structure.root))  # fmt: skip
        rb = spec.body(model.body(root_body).name)
        rb.pos = np.asarray(rb.pos, dtype=float) - np.array([0.0, 0.0, lowest])
        # Facing +x at qpos0, as every registered robot does (iCub's base faces -x).
        yaw = math.atan2(structure.forward[1], structure.forward[0])
        if abs(yaw) > 1e-6:
            turn = np.array([math.cos(-yaw / 2), 0.0, 0.0, math.sin(-yaw / 2)])
            quat = np.zeros(4)
            mujoco.mju_mulQuat(quat, turn, np.asarray(rb.quat, dtype=float))
            rb.quat = quat
            pos = np.zeros(3)
            mujoco.mju_rotVecQuat(pos, np.asarray(rb.pos, dtype=float), turn)
            rb.pos = pos
            notes.append(f"turned {math.degrees(yaw):+.0f} deg about z to face +x at qpos0 "
                         "(its knees bend and its toes point that way)")  # fmt: skip
        spec.compile()
        xml = spec.to_xml().replace(f'meshdir="{assets}', 'meshdir="assets')
        model_file = f"{name}.xml"
        atomic_write_text(tmp / model_file, xml)
        map_doc = robot_map(model, structure, name)
        key_bodies = [structure.root]
        for side in ("left", "right"):
            key_bodies += [b for b in (structure.hips[side], structure.knees[side],
                                       structure.feet[side]) if b]  # fmt: skip
        if structure.torso != structure.root:
            key_bodies.append(structure.torso)
        for side in ("left", "right"):
            key_bodies += [b for b in (structure.shoulders.get(side), structure.elbows.get(side),
                                       structure.hands.get(side)) if b]  # fmt: skip
        robot_doc = {
            "schema_version": SCHEMA_VERSION,
            "description": f"{name}, {len(motors)} DoF, added from {path.name}",
            "license": f"as its source model's ({path})",
            "model": model_file,
            "root_body": structure.root,
            "torso_body": structure.torso,
            "floor_geom": floor,
            "feet": dict(structure.feet),
            "hands": {k: v for k, v in structure.hands.items() if v},
            "key_bodies": list(dict.fromkeys(key_bodies)),
            "natural_frequency_hz": RECIPE_HZ,
            "damping_ratio": ActuatorRecipe.damping_ratio,
            "motors": motors,
        }
        header = f"# Robot {name}, added by `humimic robots add` from {path.resolve()}.\n"
        atomic_write_text(
            tmp / ROBOT_FILE,
            header + yaml.safe_dump(robot_doc, sort_keys=False, default_flow_style=None),
        )
        map_header = (f"# Robot map of {name}, generated from its tree and geometry by "
                      "`humimic robots add`: edit it to move a key point.\n")  # fmt: skip
        atomic_write_text(
            tmp / MAP_FILE,
            map_header + yaml.safe_dump(map_doc, sort_keys=False, default_flow_style=None),
        )
        atomic_write_text(tmp / "SOURCE.txt", f"{path.resolve()}\n" + "\n".join(notes) + "\n")
        if dest.exists():
            shutil.rmtree(dest)
        tmp.rename(dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return AddResult(name=name, folder=dest, structure=structure, notes=notes,
                     joints=len(motors), mass=mass)  # fmt: skip
