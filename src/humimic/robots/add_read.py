"""Reading a model for ``humimic robots add`` (:mod:`humimic.robots.add`): a URDF or an MJCF
as a MuJoCo spec with a floating root, its meshes copied into the new robot's assets folder.

A URDF is made usable where MuJoCo cannot use it as it is: it gets a floating base (a
``floating`` joint from a new world link), its visual geometry is dropped, link inertias that
are not positive definite are repaired, and collision meshes MuJoCo cannot read are converted
with trimesh or, where trimesh cannot read them either, replaced by the box of the link's
inertia. Each change is said in the notes.
"""

from __future__ import annotations

import math
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from humimic.errors import InputError

MESH_FORMATS = (".stl", ".obj", ".msh")
"""Mesh files MuJoCo reads itself."""
BOUND_MASS = 1e-3
"""Smallest link mass [kg] in an added URDF (massless links between joints get it)."""
BOUND_INERTIA = 1e-6
"""Smallest link principal inertia [kg m^2] in an added URDF."""
MIN_INERTIA = 1e-10
"""A link inertia's smallest principal moment below this [kg m^2] is broken (iCub's ankles
give 1e-20: MuJoCo refuses them)."""


def one_line(e: BaseException) -> str:
    """An error's message on one line, at most 300 characters (MuJoCo's span several)."""
    return " ".join(str(e).split())[:300]


# --- URDF ----------------------------------------------------------------------------------


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


def read_urdf(path: Path, assets: Path, notes: list[str]) -> mujoco.MjSpec:
    """The URDF as a spec with a floating base, collision geometry only, its meshes copied
    (or converted) into ``assets``."""
    robot = _parse_urdf(path)
    links = {lk.get("name"): lk for lk in robot.findall("link")}
    root = _floating_root(robot, links, path, notes)
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
    _collision_meshes(robot, path, assets, notes)
    return _urdf_spec(robot, root, path, assets)


def _parse_urdf(path: Path) -> ET.Element:
    """The URDF's ``<robot>`` element, or refused: a file that cannot be read, is not XML or
    is not a URDF."""
    try:
        tree = ET.parse(path)
    except ET.ParseError as e:
        raise InputError(f"{path}: not valid XML: {e}") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read: {e.strerror}") from None
    robot = tree.getroot()
    if robot.tag != "robot":
        raise InputError(f"{path}: not a URDF (its root element is <{robot.tag}>, not <robot>)")
    return robot


def _floating_root(
    robot: ET.Element, links: dict[str | None, ET.Element], path: Path, notes: list[str]
) -> str | None:
    """The link that floats: the one link that is no joint's child (refused where there is
    not one). A massless "world" link fixed to the robot's base is removed from ``robot``
    (said in the notes): its base floats instead."""
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
    return root


def _collision_meshes(robot: ET.Element, path: Path, assets: Path, notes: list[str]) -> None:
    """Every collision mesh of the URDF's links into ``assets``, its ``filename`` set to the
    copy: copied where MuJoCo reads it, else converted to STL (trimesh), else replaced by the
    box of the link's inertia (or dropped where the link has none). Links that share a mesh
    (the same file and scale) share one copy; copies get unique names."""
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
                    _unreadable_mesh(link, col, geom, mesh, src, path, notes)
                    continue
                notes.append(f"{src.name}: converted to STL (trimesh)")
            mesh.set("filename", dest.name)
            done[key] = dest.name


def _unreadable_mesh(
    link: ET.Element,
    col: ET.Element,
    geom: ET.Element,
    mesh: ET.Element,
    src: Path,
    path: Path,
    notes: list[str],
) -> None:
    """A collision mesh neither MuJoCo nor trimesh reads, replaced by the box of its link's
    inertia (centred on the link's centre of mass), or its collision element dropped where
    the link has no inertia; said in the notes."""
    try:
        box = _inertia_box(link)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    geom.remove(mesh)
    if box is None:
        link.remove(col)
        notes.append(f"{src.name}: MuJoCo and trimesh cannot read it, and link "
                     f"{link.get('name')!r} has no inertia: dropped")  # fmt: skip
        return
    ET.SubElement(geom, "box", size=" ".join(f"{v:.6g}" for v in box[0]))
    origin = col.find("origin")
    if origin is not None:
        col.remove(origin)
    ET.SubElement(col, "origin", xyz=" ".join(f"{v:.6g}" for v in box[1]))
    notes.append(f"{src.name}: MuJoCo and trimesh cannot read it: replaced by "
                 f"the box of link {link.get('name')!r}'s inertia")  # fmt: skip


def _urdf_spec(robot: ET.Element, root: str | None, path: Path, assets: Path) -> mujoco.MjSpec:
    """The prepared URDF compiled into a spec by MuJoCo: its ``<mujoco>`` extension (meshes
    from ``assets``, visuals discarded, static bodies fused) and a floating joint from a new
    world link to ``root`` added first."""
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
        raise InputError(f"{path}: MuJoCo cannot read this URDF: {one_line(e)}") from None
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


# --- MJCF ----------------------------------------------------------------------------------


def read_mjcf(path: Path, assets: Path, notes: list[str]) -> mujoco.MjSpec:
    """The MJCF as a spec, its meshes copied into ``assets``."""
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:
        raise InputError(f"{path}: MuJoCo cannot read this model: {one_line(e)}") from None
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
