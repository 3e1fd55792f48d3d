"""ASCII FBX 7.4 files written by the tests: skeleton animations (a joint tree, one or more takes
of Euler-angle curves), so the FBX reader is tested on files the tests make, never on
third-party files. Written from the FBX file layout (objects, properties, connections), with
no code of the reader under test."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

KTIME_PER_SECOND = 46186158000
"""FBX time ticks per second."""

ROTATION_ORDERS = ("XYZ", "XZY", "YZX", "YXZ", "ZXY", "ZYX")
"""FBX ``RotationOrder`` enum values 0-5: ``XYZ`` turns about x first, then y, then z
(``R = Rz Ry Rx``)."""


@dataclass
class Take:
    """One animation take: local joint rotations and the root's translation per frame."""

    name: str
    fps: float
    rotations: np.ndarray  # (T, J, 3, 3) local rotation matrices
    root_translation: np.ndarray  # (T, 3), file units


@dataclass
class FbxSkeleton:
    """A joint tree to write: names, parents (-1 for the root), each joint's offset in its
    parent's frame (file units), optional non-joint nodes above the root."""

    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (J, 3)
    takes: list[Take] = field(default_factory=list)
    rotation_order: str = "XYZ"
    up_axis: int = 1  # 0 x, 1 y, 2 z
    unit_scale_cm: float = 1.0
    wrapper: tuple[str, float] | None = None  # a Null node above the root: (name, uniform scale)
    prefix: str = ""


def _num(x: float) -> str:
    return repr(float(x))


def _euler_deg(rot: np.ndarray, order: str) -> np.ndarray:
    """``Lcl Rotation`` (degrees about x, y, z) for rotation matrices under an FBX order."""
    with warnings.catch_warnings():  # gimbal lock: scipy picks one of the equal answers
        warnings.simplefilter("ignore", UserWarning)
        angles = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_euler(order.lower(), degrees=True)
    out = np.empty_like(angles)
    for k, axis in enumerate(order):
        out[:, "XYZ".index(axis)] = angles[:, k]
    out = out.reshape(*rot.shape[:-2], 3)
    return np.rad2deg(np.unwrap(np.deg2rad(out), axis=0)) if out.ndim == 3 else out


def write_fbx(path: str | Path, sk: FbxSkeleton) -> Path:
    """Write ``sk`` as an ASCII FBX 7.4 file; returns the path."""
    ids = iter(range(1_000_000, 1_000_000_000))
    objs: list[str] = []
    conns: list[str] = []
    order = ROTATION_ORDERS.index(sk.rotation_order)
    first = sk.takes[0] if sk.takes else None

    def model(name: str, kind: str, t: np.ndarray, r: np.ndarray, s: float, parent: int) -> int:
        mid = next(ids)
        objs.extend([
            f'\tModel: {mid}, "Model::{name}", "{kind}" {{', "\t\tVersion: 232",
            "\t\tProperties70:  {",
            f'\t\t\tP: "RotationOrder", "enum", "", "",{order}',
            f'\t\t\tP: "Lcl Translation", "Lcl Translation", "", "A",{",".join(map(_num, t))}',
            f'\t\t\tP: "Lcl Rotation", "Lcl Rotation", "", "A",{",".join(map(_num, r))}',
            f'\t\t\tP: "Lcl Scaling", "Lcl Scaling", "", "A",{_num(s)},{_num(s)},{_num(s)}',
            "\t\t}", "\t}",
        ])  # fmt: skip
        conns.append(f'\tC: "OO",{mid},{parent}')
        return mid

    top = 0
    if sk.wrapper is not None:
        wname, wscale = sk.wrapper
        aid = next(ids)
        objs.extend([f'\tNodeAttribute: {aid}, "NodeAttribute::{wname}", "Null" {{', "\t}"])
        top = model(wname, "Null", np.zeros(3), np.zeros(3), wscale, 0)
        conns.append(f'\tC: "OO",{aid},{top}')
    model_ids: list[int] = []
    rest_rot = (
        first.rotations[0] if first is not None else np.tile(np.eye(3), (len(sk.names), 1, 1))
    )
    for j, name in enumerate(sk.names):
        aid = next(ids)
        objs.extend([f'\tNodeAttribute: {aid}, "NodeAttribute::{sk.prefix}{name}", "LimbNode" {{',
                     '\t\tTypeFlags: "Skeleton"', "\t}"])  # fmt: skip
        root = sk.parents[j] < 0
        t = first.root_translation[0] if root and first is not None else sk.offsets[j]
        parent = top if root else model_ids[sk.parents[j]]
        mid = model(sk.prefix + name, "LimbNode", t, _euler_deg(rest_rot[j], sk.rotation_order),
                    1.0, parent)  # fmt: skip
        conns.append(f'\tC: "OO",{aid},{mid}')
        model_ids.append(mid)

    for take in sk.takes:
        T = take.rotations.shape[0]
        times = np.round(np.arange(T) * KTIME_PER_SECOND / take.fps).astype(np.int64)
        stack, layer = next(ids), next(ids)
        objs.extend([
            f'\tAnimationStack: {stack}, "AnimStack::{take.name}", "" {{', "\t\tProperties70:  {",
            f'\t\t\tP: "LocalStop", "KTime", "Time", "",{times[-1]}',
            "\t\t}", "\t}", f'\tAnimationLayer: {layer}, "AnimLayer::BaseLayer", "" {{', "\t}",
        ])  # fmt: skip
        conns.append(f'\tC: "OO",{layer},{stack}')

        def curves(
            kind: str, owner: int, prop: str, values: np.ndarray, layer: int, times: np.ndarray
        ) -> None:
            T = len(times)
            node = next(ids)
            objs.extend([f'\tAnimationCurveNode: {node}, "AnimCurveNode::{kind}", "" {{',
                         "\t\tProperties70:  {"])  # fmt: skip
            objs.extend(f'\t\t\tP: "d|{a}", "Number", "", "A",{_num(values[0, i])}'
                        for i, a in enumerate("XYZ"))  # fmt: skip
            objs.extend(["\t\t}", "\t}"])
            conns.extend([f'\tC: "OO",{node},{layer}', f'\tC: "OP",{node},{owner}, "{prop}"'])
            for i, a in enumerate("XYZ"):
                cid = next(ids)
                objs.extend([
                    f'\tAnimationCurve: {cid}, "AnimCurve::", "" {{',
                    f"\t\tDefault: {_num(values[0, i])}", "\t\tKeyVer: 4008",
                    f"\t\tKeyTime: *{T} {{", "\t\t\ta: " + ",".join(str(int(x)) for x in times),
                    "\t\t}", f"\t\tKeyValueFloat: *{T} {{",
                    "\t\t\ta: " + ",".join(_num(x) for x in values[:, i]), "\t\t}",
                    "\t\tKeyAttrFlags: *1 {", "\t\t\ta: 260", "\t\t}",  # linear
                    "\t\tKeyAttrDataFloat: *4 {", "\t\t\ta: 0,0,0,0", "\t\t}",
                    "\t\tKeyAttrRefCount: *1 {", f"\t\t\ta: {T}", "\t\t}", "\t}",
                ])  # fmt: skip
                conns.append(f'\tC: "OP",{cid},{node}, "d|{a}"')

        eul = _euler_deg(take.rotations, sk.rotation_order)  # (T, J, 3)
        for j, mid in enumerate(model_ids):
            curves("R", mid, "Lcl Rotation", eul[:, j], layer, times)
            if sk.parents[j] < 0:
                curves("T", mid, "Lcl Translation", take.root_translation, layer, times)

    front = 2 if sk.up_axis == 1 else 1
    lines = [
        "; FBX 7.4.0 project file", "FBXHeaderExtension:  {", "\tFBXHeaderVersion: 1003",
        "\tFBXVersion: 7400", "}", "GlobalSettings:  {", "\tVersion: 1000", "\tProperties70:  {",
        f'\t\tP: "UpAxis", "int", "Integer", "",{sk.up_axis}',
        '\t\tP: "UpAxisSign", "int", "Integer", "",1',
        f'\t\tP: "FrontAxis", "int", "Integer", "",{front}',
        '\t\tP: "FrontAxisSign", "int", "Integer", "",1',
        f'\t\tP: "CoordAxis", "int", "Integer", "",{0 if sk.up_axis != 0 else 2}',
        '\t\tP: "CoordAxisSign", "int", "Integer", "",1',
        f'\t\tP: "UnitScaleFactor", "double", "Number", "",{_num(sk.unit_scale_cm)}',
        "\t}", "}", "Objects:  {", *objs, "}", "Connections:  {", *conns, "}", "",
    ]  # fmt: skip
    p = Path(path)
    p.write_text("\n".join(lines))
    return p


def skeleton_from_clip(
    names: tuple[str, ...],
    parents: tuple[int, ...],
    positions: np.ndarray,
    rotations: np.ndarray,
    fps: float,
    *,
    to_file: np.ndarray,
    scale: float,
) -> FbxSkeleton:
    """An FBX skeleton with one take from world joint positions (T, J, 3) and rotations
    (T, J, 3, 3) in metres, z up: ``to_file`` turns the world into the file's axes,
    ``scale`` makes file units (100: centimetres)."""
    pos = positions @ to_file.T * scale
    rot = np.einsum("ij,tkjl->tkil", to_file, rotations)
    par = np.array(parents)
    T, J = pos.shape[:2]
    local = np.empty((T, J, 3, 3))
    offsets = np.zeros((J, 3))
    for j in range(J):
        if par[j] < 0:
            local[:, j] = rot[:, j]
        else:
            local[:, j] = np.einsum("tji,tjk->tik", rot[:, par[j]], rot[:, j])
            offsets[j] = rot[0, par[j]].T @ (pos[0, j] - pos[0, par[j]])
    take = Take(
        name="Take 001",
        fps=fps,
        rotations=local,
        root_translation=pos[:, int(np.flatnonzero(par < 0)[0])],
    )
    return FbxSkeleton(names=list(names), parents=list(parents), offsets=offsets, takes=[take])
