"""Scenes a human interacts with (boxes, terrain, objects): :class:`Scene` and
:func:`load_scene`, which ``humimic retarget --scene`` and ``humimic view --scene`` both read
scenes with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from humimic.errors import InputError
from humimic.io import read_yaml
from humimic.transforms import axis_angle_matrix, quat_mul, quat_to_matrix

SCENE_SCHEMA_VERSION = 1
_MESH_SUFFIXES = (".obj", ".stl")

# What a scene may hold. Sampling and the per-frame contact and mesh queries cost memory in
# proportion to these, so they are checked before anything is allocated.
MAX_OBJECTS = 64
MAX_FACES = 20_000
"""Most triangles of one object (every frame measures every key point against them)."""
MAX_SCENE_FACES = 100_000
"""Most triangles of all objects together."""
MAX_EXTENT = 100.0
"""Largest size of an object along any axis [m, the clip's scale]."""
MIN_EXTENT = 1e-3
"""Smallest largest size of an object [m]: anything flatter in every direction is no surface."""
MAX_POSITION = 1000.0
"""Farthest an object's pose may be from the origin [m]."""
MAX_TRAJECTORY_FRAMES = 1_000_000
MAX_MESH_FILE_BYTES = 64 << 20
MAX_POINTS_PER_OBJECT = 20_000
"""Most surface points sampled on one object (:meth:`Scene.surface_points`)."""
MAX_SCENE_POINTS = 100_000
"""Most surface points sampled on the whole scene."""


@dataclass(frozen=True, kw_only=True)
class SceneObject:
    """One rigid object.

    Attributes:
        name: Unique within the scene.
        vertices: In the object's frame [m]. Shape: (V, 3).
        faces: Triangles, vertex indices. Shape: (F, 3).
        poses: Object-to-world poses, position and wxyz quaternion; one row for a static
            object, else one per frame of the scene's ``fps``. Shape: (1 or T, 7).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    poses: np.ndarray

    @property
    def static(self) -> bool:
        return self.poses.shape[0] == 1

    def pose(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (3, 3) and position (3,) at frame ``t`` (the last pose after the end)."""
        p = self.poses[min(t, self.poses.shape[0] - 1)]
        return quat_to_matrix(p[3:]), p[:3]

    def world_vertices(self, t: int = 0) -> np.ndarray:
        """Vertices in the world frame at frame ``t``. Shape: (V, 3)."""
        rot, pos = self.pose(t)
        return self.vertices @ rot.T + pos


@dataclass(frozen=True, kw_only=True)
class Scene:
    """Rigid objects in the clip's world frame.

    Each object is a triangle mesh in its own frame with a pose per frame (or one pose:
    static). Scenes are in the clip's world frame: metres, z up, the same frame as the human
    clip's joint positions. :meth:`to_robot` maps a scene by the similarity (heading, origin,
    scale, height calibration) the retargeter maps the human by.

    Attributes:
        objects: The objects.
        fps: Frame rate of the objects' trajectories (``None`` if all are static).
        source: Where it was read from.
    """

    objects: tuple[SceneObject, ...]
    fps: float | None = None
    source: str = ""

    @property
    def static(self) -> bool:
        return all(o.static for o in self.objects)

    def resample(self, fps: float, num_frames: int, start_s: float = 0.0) -> Scene:
        """Trajectories at ``fps`` for ``num_frames`` frames from ``start_s`` seconds on
        (linear positions, normalized linear quaternions between neighbouring samples);
        static objects unchanged."""
        if self.static or self.fps is None:
            return self
        t = (start_s + np.arange(num_frames) / fps) * self.fps
        objects = []
        for o in self.objects:
            if o.static:
                objects.append(o)
                continue
            n = o.poses.shape[0]
            i0 = np.clip(np.floor(t).astype(int), 0, n - 1)
            i1 = np.clip(i0 + 1, 0, n - 1)
            u = np.clip(t - i0, 0.0, 1.0)[:, None]
            pos = (1 - u) * o.poses[i0, :3] + u * o.poses[i1, :3]
            q0, q1 = o.poses[i0, 3:], o.poses[i1, 3:]
            q1 = np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0, -q1, q1)
            q = (1 - u) * q0 + u * q1
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            objects.append(replace(o, poses=np.concatenate([pos, q], axis=1)))
        return replace(self, objects=tuple(objects), fps=fps)

    def to_robot(
        self, *, scale: float, yaw: float, origin: np.ndarray, ground: float, z_offset: float
    ) -> Scene:
        """The scene in the robot's frame, mapped as the retargeter maps the human: turned by
        ``yaw`` about z after moving ``origin`` to the world origin, scaled by ``scale`` about
        it, and a height ``z`` above the human ground ``ground`` put at
        ``scale * z + z_offset``.

        Vertices are scaled in the object's frame and poses are mapped; the result is again
        rigid objects with poses.
        """
        rot = axis_angle_matrix("z", np.asarray(yaw))
        shift = np.array([0.0, 0.0, z_offset - scale * ground])
        qz = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
        objects = []
        for o in self.objects:
            pos = scale * ((o.poses[:, :3] - origin) @ rot.T) + shift
            quat = quat_mul(np.broadcast_to(qz, o.poses[:, 3:].shape), o.poses[:, 3:])
            objects.append(
                replace(o, vertices=scale * o.vertices, poses=np.concatenate([pos, quat], axis=1))
            )
        return replace(self, objects=tuple(objects))

    def surface_points(self, spacing: float) -> list[np.ndarray]:
        """Points on each object's surface in its own frame, about ``spacing`` apart: the
        vertices plus a regular sampling of every triangle. One array per object, Shape: (N, 3).

        The number of points is bounded: an object that would get more than
        :data:`MAX_POINTS_PER_OBJECT` is sampled more coarsely, and if the scene would get
        more than :data:`MAX_SCENE_POINTS` every object is (:meth:`sampling_spacings` says how
        far apart each object's points are). The counts are computed before any point is.
        """
        return [
            _sample_triangles(o.vertices, o.faces, s)
            for o, s in zip(self.objects, self.sampling_spacings(spacing), strict=True)
        ]

    def sampling_spacings(self, spacing: float) -> list[float]:
        """The spacing :meth:`surface_points` samples each object with: ``spacing``, or a
        larger one for objects too big to sample that finely (see there)."""
        if not (isinstance(spacing, int | float) and math.isfinite(spacing) and spacing > 0):
            raise InputError(f"--mesh.scene_spacing: must be a positive number, got {spacing}")
        out = [_spacing_for(o, spacing, MAX_POINTS_PER_OBJECT) for o in self.objects]

        def total(factor: float) -> float:
            return sum(
                _sample_count(o.vertices, o.faces, s * factor)
                for o, s in zip(self.objects, out, strict=True)
            )

        if total(1.0) > MAX_SCENE_POINTS:  # Coarser everywhere, by one common factor.
            # Past every object's longest edge only the vertices remain (bounded by the loader).
            lo = 1.0
            hi = max(_max_edge(o) / s for o, s in zip(self.objects, out, strict=True)) * 1.01
            while hi / lo > 1.01:
                mid = math.sqrt(lo * hi)
                lo, hi = (mid, hi) if total(mid) > MAX_SCENE_POINTS else (lo, mid)
            out = [s * hi for s in out]
        return out


def _edges(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The longer of each triangle's two edges from its first corner (what sets its sampling).
    Shape: (F,)."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return np.maximum(np.linalg.norm(b - a, axis=1), np.linalg.norm(c - a, axis=1))


def _max_edge(o: SceneObject) -> float:
    return float(_edges(o.vertices, o.faces).max(initial=0.0))


def _sample_count(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> float:
    """How many points :func:`_sample_triangles` makes (before removing duplicates), computed
    without making them (as a float: a tiny spacing would overflow integers)."""
    with np.errstate(over="ignore", divide="ignore"):
        n = np.maximum(np.ceil(_edges(vertices, faces) / spacing), 1.0)
        per = np.where(n >= 2, (n + 1) * (n + 2) / 2, 0.0)
    return float(vertices.shape[0] + per.sum())


def _spacing_for(o: SceneObject, spacing: float, cap: int) -> float:
    """``spacing``, or the smallest larger one (within 1%) that samples at most ``cap`` points."""
    if _sample_count(o.vertices, o.faces, spacing) <= cap:
        return spacing
    # Past the longest edge only the vertices remain (no more than ``cap`` for meshes that
    # pass the loader's checks).
    lo, hi = spacing, max(_max_edge(o) * 1.01, spacing)
    while hi / lo > 1.01:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if _sample_count(o.vertices, o.faces, mid) > cap else (lo, mid)
    return hi


def _sample_triangles(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> np.ndarray:
    pts = [vertices]
    for f in faces:
        a, b, c = vertices[f]
        n = max(math.ceil(max(np.linalg.norm(b - a), np.linalg.norm(c - a)) / spacing), 1)
        if n < 2:
            continue
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        u, v = i[keep] / n, j[keep] / n
        pts.append(a + u[:, None] * (b - a) + v[:, None] * (c - a))
    out = np.concatenate(pts)
    return np.unique(np.round(out, 6), axis=0)


# ------------------------------------------------------------------------------ loading


def box_mesh(size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A box of full extents ``size`` centred at the origin: vertices (8, 3), faces (12, 3),
    outward counter-clockwise."""
    h = 0.5 * np.asarray(size, dtype=np.float64)
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * h
    f = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return v, f


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of an OBJ or STL file, repeated vertices merged.

    Raises:
        InputError: Missing, too large or unreadable; fewer than 4 vertices or triangles
            (empty), more than :data:`MAX_FACES` triangles or :data:`MAX_POINTS_PER_OBJECT`
            vertices, NaN or inf, or triangles naming missing vertices (names the file).
    """
    import trimesh

    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    if path.suffix.lower() not in _MESH_SUFFIXES:
        raise InputError(f"{path}: unknown mesh type; expected one of {_MESH_SUFFIXES}")
    size = path.stat().st_size
    if size > MAX_MESH_FILE_BYTES:
        raise InputError(
            f"{path}: {size} bytes, more than the {MAX_MESH_FILE_BYTES} a scene mesh may have"
        )
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
        v = np.asarray(getattr(mesh, "vertices", None), dtype=np.float64)
        f = np.asarray(getattr(mesh, "faces", None), dtype=np.int64)
    except Exception as e:  # trimesh raises many types on bad files.
        text = " ".join(str(e).split())[:200]
        raise InputError(f"{path}: not a readable mesh ({type(e).__name__}: {text})") from None
    if v.ndim != 2 or v.shape[0] < 4 or f.ndim != 2 or f.shape[0] < 4:
        raise InputError(f"{path}: a mesh needs at least 4 vertices and 4 triangles")
    if v.shape[1] != 3 or f.shape[1] != 3:
        raise InputError(f"{path}: expected triangles in 3D, got {v.shape} {f.shape}")
    if not np.isfinite(v).all():
        raise InputError(f"{path}: vertices hold NaN or inf")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise InputError(f"{path}: a triangle names a vertex the mesh does not have")
    if f.shape[0] > MAX_FACES:
        raise InputError(
            f"{path}: {f.shape[0]} triangles, more than the {MAX_FACES} a scene object may "
            "have: simplify the mesh"
        )
    v, f = _merge_vertices(v, f)
    if v.shape[0] > MAX_POINTS_PER_OBJECT:
        raise InputError(
            f"{path}: {v.shape[0]} distinct vertices, more than the {MAX_POINTS_PER_OBJECT} a "
            "scene object may have: simplify the mesh"
        )
    return v, f


def _merge_vertices(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Repeated vertices (an STL file repeats each triangle's corners) merged; the first
    occurrences keep their order, so a mesh without repeats is returned unchanged."""
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    if first.size == v.shape[0]:
        return v, f
    order = np.argsort(first)  # Unique rows by first occurrence.
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return v[first[order]], rank[inverse.reshape(-1)][f]


def _check_object(where: str, v: np.ndarray, f: np.ndarray) -> None:
    """An object's size is one humimic can sample and simulate: at most :data:`MAX_EXTENT`
    along every axis, at least :data:`MIN_EXTENT` along one, with some surface area."""
    extent = v.max(axis=0) - v.min(axis=0)
    if extent.max() > MAX_EXTENT:
        raise InputError(
            f"{where}: {extent.max():.4g} m across, more than the {MAX_EXTENT:g} m a scene "
            "object may measure (are the units metres?)"
        )
    if extent.max() < MIN_EXTENT:
        raise InputError(f"{where}: {extent.max():.3g} m across: too small to be a surface")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    if not np.linalg.norm(np.cross(b - a, c - a), axis=1).any():
        raise InputError(f"{where}: every triangle has zero area")


def _check_scene(source: Path, objects: list[SceneObject]) -> None:
    """The whole scene's size: objects, triangles and vertices (bounded per frame's work)."""
    if len(objects) > MAX_OBJECTS:
        raise InputError(f"{source}: {len(objects)} objects, at most {MAX_OBJECTS}")
    faces = sum(o.faces.shape[0] for o in objects)
    if faces > MAX_SCENE_FACES:
        raise InputError(f"{source}: {faces} triangles in all, at most {MAX_SCENE_FACES}")
    verts = sum(o.vertices.shape[0] for o in objects)
    if verts > MAX_SCENE_POINTS:
        raise InputError(f"{source}: {verts} vertices in all, at most {MAX_SCENE_POINTS}")


def load_scene(path: str | Path) -> Scene:
    """Load a scene file, a holosoma-style folder or one mesh file.

    Inputs:

    - a scene file (``.yaml``), schema version 1::

          schema_version: 1
          fps: 120                    # only needed when an object has a trajectory
          objects:
            - name: step
              box: [1.0, 0.8, 0.18]   # full extents x, y, z [m], centred on the pose
              pos: [0.6, 0.0, 0.09]
              quat: [1, 0, 0, 0]      # wxyz
            - name: crate
              mesh: crate.obj         # OBJ or STL, relative to the scene file
              scale: 1.0
              trajectory: crate.npy   # optional: (T, 7) poses, pos + wxyz quat, at `fps`

    - a folder in the layout of holosoma's climbing demo (``box_models/*.obj`` at human
      scale, in the world frame): the folder of a clip of ``../shared/data/holosoma_climb``
      loads as-is;
    - a single ``.obj`` / ``.stl`` file: one static object, in the world frame.

    Scenes are bounded (object sizes and poses, triangles, sampled points: the ``MAX_*``
    constants), checked on loading and, for the sampled points, counted before they are made
    (:meth:`Scene.surface_points`).

    Raises:
        InputError: Missing or unreadable files, bad fields, or a scene too large or too
            strange to retarget in (sizes, poses, triangle counts: the limits above); the
            message names the scene file and the object.
    """
    p = Path(path)
    identity = np.array([[0.0, 0, 0, 1, 0, 0, 0]])
    if p.is_dir():
        meshes = sorted((p / "box_models").glob("*.obj")) if (p / "box_models").is_dir() else []
        if not meshes:
            raise InputError(
                f"{p}: a scene folder needs box_models/*.obj (holosoma's layout); "
                "or give a scene .yaml file"
            )
        if len(meshes) > MAX_OBJECTS:
            raise InputError(f"{p}: {len(meshes)} meshes in box_models, at most {MAX_OBJECTS}")
        objs = []
        for m in meshes:
            v, f = read_mesh(m)
            _check_object(str(m), v, f)
            objs.append(SceneObject(name=m.stem, vertices=v, faces=f, poses=identity))
        _check_scene(p, objs)
        return Scene(objects=tuple(objs), source=str(p))
    if p.suffix.lower() in _MESH_SUFFIXES:
        v, f = read_mesh(p)
        _check_object(str(p), v, f)
        return Scene(objects=(SceneObject(name=p.stem, vertices=v, faces=f, poses=identity),),
                     source=str(p))  # fmt: skip
    if p.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"{p}: expected a scene .yaml, a mesh (.obj/.stl) or a scene folder")
    return _parse_scene(p, read_yaml(p))


def _positive(value: Any, upper: float) -> bool:
    """A real number (not a bool) in (0, upper]."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    return ok and math.isfinite(value) and 0 < value <= upper


def _parse_scene(p: Path, raw: Any) -> Scene:
    if not isinstance(raw, dict):
        raise InputError(f"{p}: expected a mapping with schema_version and objects")
    if raw.get("schema_version") != SCENE_SCHEMA_VERSION:
        raise InputError(
            f"{p}: schema_version: expected {SCENE_SCHEMA_VERSION}, got {raw.get('schema_version')!r}"
        )
    unknown = set(raw) - {"schema_version", "fps", "objects"}
    if unknown:
        raise InputError(f"{p}: unknown keys {sorted(map(str, unknown))}")
    items = raw.get("objects")
    if not isinstance(items, list) or not items:
        raise InputError(f"{p}: objects: expected a non-empty list")
    if len(items) > MAX_OBJECTS:
        raise InputError(f"{p}: objects: {len(items)} objects, at most {MAX_OBJECTS}")
    fps = raw.get("fps")
    if fps is not None and not _positive(fps, 10_000.0):
        raise InputError(f"{p}: fps: expected a positive number (at most 10000), got {fps!r}")
    objects: list[SceneObject] = []
    for k, it in enumerate(items):
        objects.append(_parse_object(p, k, it, objects, fps))
    _check_scene(p, objects)
    return Scene(objects=tuple(objects), fps=None if fps is None else float(fps), source=str(p))


def _parse_object(p: Path, k: int, it: Any, objects: list[SceneObject], fps: Any) -> SceneObject:
    """Object ``k`` of a scene file: its name (unique among ``objects``, those before it), its
    mesh (a box or a mesh file, scaled and checked) and its poses.

    Raises:
        InputError: A bad field, naming the file, the object and the field.
    """
    where = f"{p}: objects[{k}]"
    if not isinstance(it, dict):
        raise InputError(f"{where}: expected a mapping")
    unknown = set(it) - {"name", "box", "mesh", "scale", "pos", "quat", "trajectory"}
    if unknown:
        raise InputError(f"{where}: unknown keys {sorted(map(str, unknown))}")
    name = it.get("name", f"object{k}")
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{where}.name: expected a non-empty string, got {name!r}")
    where = f"{p}: objects[{k}] ({name})"
    if any(o.name == name for o in objects):
        raise InputError(f"{where}.name: {name!r} repeats")
    v, f = _object_mesh(p, where, it)
    scale = it.get("scale", 1.0)
    if not _positive(scale, 1e6):
        raise InputError(f"{where}.scale: expected a positive number, got {scale!r}")
    v = v * float(scale)
    _check_object(where, v, f)
    return SceneObject(name=name, vertices=v, faces=f, poses=_object_poses(p, where, it, fps))


def _object_mesh(p: Path, where: str, it: dict) -> tuple[np.ndarray, np.ndarray]:
    """An object's vertices and faces, unscaled: a ``box`` of the given extents, or a ``mesh``
    file relative to the scene file ``p`` (exactly one of the two)."""
    if ("box" in it) == ("mesh" in it):
        raise InputError(f"{where}: give exactly one of box (extents) or mesh (file)")
    if "box" in it:
        size = _vector(where + ".box", it["box"], 3)
        if (size <= 0).any() or (size > MAX_EXTENT).any():
            raise InputError(
                f"{where}.box: extents must be positive and at most {MAX_EXTENT:g} m, got "
                f"{size.tolist()}"
            )
        return box_mesh(size)
    if not isinstance(it["mesh"], str):
        raise InputError(f"{where}.mesh: expected a file name, got {it['mesh']!r}")
    try:
        return read_mesh(p.parent / it["mesh"])
    except InputError as e:
        raise InputError(f"{where}.mesh: {e}") from None


def _object_poses(p: Path, where: str, it: dict, fps: Any) -> np.ndarray:
    """An object's poses (1 or T, 7), quaternions normalized: its ``trajectory`` file (the
    scene needs ``fps`` then), else its one ``pos`` and ``quat``; each finite, within
    :data:`MAX_POSITION` of the origin, no quaternion zero."""
    if "trajectory" in it:
        if fps is None:
            raise InputError(f"{where}.trajectory: the scene needs fps for trajectories")
        if not isinstance(it["trajectory"], str):
            raise InputError(f"{where}.trajectory: expected a file name, got {it['trajectory']!r}")
        poses = _read_trajectory(where, p.parent / it["trajectory"])
    else:
        pos = _vector(where + ".pos", it.get("pos", [0, 0, 0]), 3)
        quat = _vector(where + ".quat", it.get("quat", [1, 0, 0, 0]), 4)
        poses = np.concatenate([pos, quat])[None]
    if not np.isfinite(poses).all():
        raise InputError(f"{where}: poses hold NaN or inf")
    far = np.linalg.norm(poses[:, :3], axis=1)
    if far.max() > MAX_POSITION:
        raise InputError(
            f"{where}: a pose is {far.max():.4g} m from the origin, at most "
            f"{MAX_POSITION:g} m (frame {int(np.argmax(far))})"
        )
    norms = np.linalg.norm(poses[:, 3:], axis=1)
    if (norms < 1e-9).any():
        raise InputError(f"{where}: a quaternion is zero (frame {int(np.argmax(norms < 1e-9))})")
    poses[:, 3:] /= norms[:, None]
    return poses


def _read_trajectory(where: str, tp: Path) -> np.ndarray:
    """An object's poses (T, 7) from an ``.npy`` file, its size checked before reading."""
    from humimic.npyio import read_npy_file

    if not tp.is_file():
        raise InputError(f"{where}.trajectory: {tp}: no such file")
    try:
        # At most MAX_TRAJECTORY_FRAMES poses of 7 numbers of at most 16 bytes.
        poses = read_npy_file(
            tp, max_bytes=MAX_TRAJECTORY_FRAMES * 7 * 16, kinds="iuf", error=InputError
        )
    except InputError as e:
        raise InputError(f"{where}.trajectory: {e}") from None
    if poses.ndim != 2 or poses.shape[1] != 7:  # read_npy_file checked the dtype.
        raise InputError(
            f"{where}.trajectory: {tp}: expected poses of shape (T, 7) (position, wxyz "
            f"quaternion), got shape {poses.shape} and dtype {poses.dtype}"
        )
    if not 1 <= poses.shape[0] <= MAX_TRAJECTORY_FRAMES:
        raise InputError(
            f"{where}.trajectory: {tp}: {poses.shape[0]} poses, expected 1 to "
            f"{MAX_TRAJECTORY_FRAMES}"
        )
    return poses.astype(np.float64)


def _vector(where: str, value: Any, n: int) -> np.ndarray:
    ok = isinstance(value, list | tuple) and len(value) == n
    ok = ok and all(isinstance(x, int | float) and math.isfinite(x) for x in value)
    if not ok:
        raise InputError(f"{where}: expected {n} numbers, got {value!r}")
    return np.asarray(value, dtype=np.float64)


__all__ = [
    "SCENE_SCHEMA_VERSION",
    "Scene",
    "SceneObject",
    "box_mesh",
    "load_scene",
    "read_mesh",
]
