"""SMPL-family parameter files (AMASS ``.npz``: SMPL, SMPL+H, SMPL-X) as clips of body joints.

The body model files are licence-gated: humimic never ships or downloads them. The user's own
(``SMPLX_NEUTRAL.npz`` and the like, from smpl-x.is.tue.mpg.de, mano.is.tue.mpg.de or
smpl.is.tue.mpg.de) are read from ``--body-model DIR`` or ``$HUMIMIC_BODY_MODELS``, as the smplx
package lays them out (``DIR/smplx/SMPLX_NEUTRAL.npz``, or the files in ``DIR`` itself); a
``.pkl`` model (SMPL's are) is read as data only (:mod:`humimic.datapickle`: chumpy arrays and
sparse regressors become arrays, nothing in the file is run).

Only the joints are needed, so no skinning: the shaped rest joints are the joint regressor
applied to the shaped template (``J = J_regressor (v_template + shapedirs betas)``, as smplx
computes them), and the posed joints follow by forward kinematics of the axis-angle rotations
about them, the root at ``J_0 + trans``. The 22 body joints are kept (the hands' and face's
are not key points). AMASS is z up, in metres. Arrays are read without pickle.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

from humimic.datasets.clip import HumanClip
from humimic.errors import InputError, MotionDataError
from humimic.npyio import npz_keys, read_npz_members

BODY_MODELS_ENV = "HUMIMIC_BODY_MODELS"
"""Environment variable naming the folder of the user's SMPL-family body model files."""

SMPL_BODY_JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)  # fmt: skip
"""The body joints of every SMPL-family model, in their order (the smplx package's names)."""

FAMILIES = {"smpl": (24, 72), "smplh": (52, 156), "smplx": (55, 165)}
"""Family -> (joints in its model, width of an AMASS ``poses`` row)."""
MAX_BYTES = 2 * 1024**3
"""Most bytes read from one file (an SMPL-X model is about 100 MB, an AMASS clip a few MB)."""


SMPL_KEYS = ("poses", "root_orient", "pose_body", "trans", "betas", "gender", "mocap_framerate",
             "mocap_frame_rate", "surface_model_type")  # fmt: skip
"""The keys of an SMPL-family motion file this reader uses (others are ignored)."""


def _pickle_members(
    path: Path,
    keys: tuple[str, ...],
    kinds: str,
    error: type[InputError],
    required: tuple[str, ...],
) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of a pickled dict of data (:func:`humimic.datapickle.read_data_pickle`:
    nothing in it is run), as :func:`humimic.npyio.read_npz_members` gives those of an npz."""
    from humimic.datapickle import read_data_pickle

    data = read_data_pickle(path)
    if not isinstance(data, dict):
        raise error(f"{path}: expected a dict of arrays, got a {type(data).__name__}")
    missing = [k for k in required if k not in data]
    if missing:
        raise error(f"{path}: missing key(s) {missing}")
    out = {}
    for k in keys:
        if k not in data:
            continue
        arr = np.asarray(data[k])
        if arr.dtype.kind not in kinds:
            raise error(f"{path}: {k}: expected numbers, got {arr.dtype} values")
        out[k] = arr
    return out


def is_smpl_file(path: Path) -> bool:
    """Whether an ``.npz`` holds SMPL-family parameters (``poses`` or ``pose_body``), not joint
    positions (whose reader would name the wrong missing key)."""
    keys = npz_keys(path)
    return "poses" in keys or "pose_body" in keys


def _rotations(aa: np.ndarray) -> np.ndarray:
    """Rotation matrices of axis-angle vectors (Rodrigues). Shape: (..., 3) -> (..., 3, 3)."""
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(theta, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    z = np.zeros_like(kx)
    K = np.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], axis=-1).reshape(*aa.shape[:-1], 3, 3)
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + s * K + (1 - c) * (K @ K)


def body_model_file(family: str, gender: str, folder: Path | None, source: Path) -> Path:
    """The body model file of a family and gender, from ``folder`` or ``$HUMIMIC_BODY_MODELS``.

    Raises:
        InputError: No folder given, or no such file in it, naming the motion file and its
            gender (the message says where users get the files and what to pass).
    """
    where = folder if folder is not None else os.environ.get(BODY_MODELS_ENV)
    name = f"{family.upper()}_{gender.upper()}.npz"  # or .pkl (read as data only)
    get = ("the body model files are licence-gated and not shipped: register and download "
           f"them ({family.upper()}: smpl-x.is.tue.mpg.de for SMPL-X, mano.is.tue.mpg.de for "
           "SMPL+H, smpl.is.tue.mpg.de for SMPL), then pass --body-model DIR (the folder "
           f"holding {family}/{name}, or the .pkl) or set {BODY_MODELS_ENV}")  # fmt: skip
    if not where:
        raise InputError(f"{source}: no body model folder for {name}: {get}")
    base = Path(where)
    pkl = name[: -len(".npz")] + ".pkl"
    for cand in (base / family / name, base / name, base / family / pkl, base / pkl):
        if cand.is_file():
            return cand
    raise InputError(f"{source}: gender {gender!r}: {base} has no {family}/{name} or {name} "
                     f"(nor .pkl): {get}")  # fmt: skip


def rest_joints(model: Path, family: str, betas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The shaped rest positions of the body joints and their parents.

    Returns:
        (22, 3) joint positions, (22,) parent indices (-1 for the root).

    Raises:
        InputError: A model file of another family, or with bad arrays (names file and key).
    """
    keys = ("v_template", "shapedirs", "J_regressor", "kintree_table")
    if model.suffix.lower() == ".pkl":
        a = _pickle_members(model, keys, "iuf", InputError, required=keys)
    else:
        a = read_npz_members(model, keys, max_bytes=MAX_BYTES, kinds="iuf", error=InputError,
                             required=keys)  # fmt: skip
    v, dirs, reg, tree = a["v_template"], a["shapedirs"], a["J_regressor"], a["kintree_table"]
    n_joints = FAMILIES[family][0]
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{model}: v_template: expected (V, 3), got {v.shape}")
    V = v.shape[0]
    if dirs.ndim != 3 or dirs.shape[:2] != (V, 3):
        raise InputError(f"{model}: shapedirs: expected ({V}, 3, B), got {dirs.shape}")
    if reg.shape != (n_joints, V):
        raise InputError(f"{model}: J_regressor: expected ({n_joints}, {V}) for "
                         f"{family.upper()}, got {reg.shape}: a model of another family?")  # fmt: skip
    if tree.ndim != 2 or tree.shape[0] != 2 or tree.shape[1] != n_joints:
        raise InputError(f"{model}: kintree_table: expected (2, {n_joints}), got {tree.shape}")
    for key, arr in (("v_template", v), ("shapedirs", dirs), ("J_regressor", reg)):
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{model}: {key}: NaN or infinite values")
    nb = min(betas.shape[0], dirs.shape[2])
    shaped = v + dirs[:, :, :nb] @ betas[:nb]
    joints = reg[:22] @ shaped
    parents = tree[0, :22].astype(np.int64)
    parents[0] = -1
    if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, 22)):
        raise InputError(
            f"{model}: kintree_table: the body joints' parents are not a tree in order"
        )
    return joints, parents


def _floats(a: dict[str, np.ndarray], key: str, p: Path) -> np.ndarray:
    """``a[key]`` as floats, or refused naming the file and key (text where numbers belong)."""
    arr = np.asarray(a[key])
    if arr.dtype.kind not in "iuf":
        raise MotionDataError(f"{p}: {key}: expected numbers, got {arr.dtype} values")
    return arr.astype(float)


def load_smpl(path: str | os.PathLike[str], *, body_model: Path | None = None) -> HumanClip:
    """An AMASS-style ``.npz`` of SMPL-family parameters as a clip of its 22 body joints.

    Keys: ``poses`` (T, 72 | 156 | 165) or ``root_orient`` (T, 3) with ``pose_body`` (T, 63);
    ``trans`` (T, 3); ``betas``; ``gender``; ``mocap_framerate`` or ``mocap_frame_rate``;
    ``surface_model_type`` where the file says its family (else the ``poses`` width does; a
    file with ``pose_body`` and no family is SMPL-X).

    Raises:
        InputError: Naming the file and the key: a missing key, wrong shapes, NaN, a frame rate
            that is not positive, a gender with no model file, a model of another family.
    """
    p = Path(path)
    if p.suffix.lower() == ".pkl":
        a = _pickle_members(p, SMPL_KEYS, "iufUS", MotionDataError, required=("trans",))
    else:
        a = read_npz_members(p, SMPL_KEYS, max_bytes=MAX_BYTES, kinds="iufUS",
                             error=MotionDataError, required=("trans",))  # fmt: skip
    trans = _floats(a, "trans", p)
    if trans.ndim != 2 or trans.shape[1] != 3 or trans.shape[0] < 1:
        raise MotionDataError(f"{p}: trans: expected (T, 3), got {trans.shape}")
    T = trans.shape[0]
    family = str(a["surface_model_type"]).lower() if "surface_model_type" in a else None
    if "poses" in a:
        poses = _floats(a, "poses", p)
        widths = {w: f for f, (_, w) in FAMILIES.items()}
        if poses.ndim != 2 or poses.shape[0] != T or poses.shape[1] not in widths:
            raise MotionDataError(f"{p}: poses: expected (T={T}, 72 | 156 | 165), got "
                                  f"{poses.shape}")  # fmt: skip
        family = family or widths[poses.shape[1]]
        body = poses[:, : 22 * 3]
    elif "root_orient" in a:
        if "pose_body" not in a:
            raise MotionDataError(f"{p}: root_orient without pose_body")
        ro, pb = _floats(a, "root_orient", p), _floats(a, "pose_body", p)
        if ro.shape != (T, 3) or pb.shape != (T, 63):
            raise MotionDataError(f"{p}: root_orient {ro.shape} and pose_body {pb.shape}: "
                                  f"expected ({T}, 3) and ({T}, 63)")  # fmt: skip
        body = np.concatenate([ro, pb], axis=1)
        family = family or "smplx"
    else:
        raise MotionDataError(f"{p}: no poses, and pose_body without root_orient")
    if family not in FAMILIES:
        raise MotionDataError(f"{p}: surface_model_type {family!r}: expected smpl, smplh or smplx")
    for key, arr in (("poses", body), ("trans", trans)):
        if not np.all(np.isfinite(arr)):
            bad = int(np.argwhere(~np.isfinite(arr))[0][0])
            raise MotionDataError(f"{p}: {key}: NaN or infinite at frame {bad}")
    rate = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in a), None)
    if rate is None:
        raise MotionDataError(f"{p}: no mocap_framerate or mocap_frame_rate: the frame rate")
    rates = _floats(a, rate, p).reshape(-1)
    if rates.size != 1:
        raise MotionDataError(f"{p}: {rate}: expected one number, got {rates.size}")
    fps = float(rates[0])
    if not math.isfinite(fps) or fps <= 0:
        raise MotionDataError(f"{p}: the frame rate {fps} is not positive")
    betas = _floats(a, "betas", p).reshape(-1) if "betas" in a else np.zeros(0)
    if not np.all(np.isfinite(betas)):
        raise MotionDataError(f"{p}: betas: NaN or infinite values")
    genders = np.asarray(a["gender"]).reshape(-1) if "gender" in a else np.array(["neutral"])
    gender = str(genders[0]) if genders.size else "neutral"
    if isinstance(gender, bytes):
        gender = gender.decode()
    gender = gender.strip().lower() or "neutral"
    if not gender.isalpha() or not gender.isascii():
        raise MotionDataError(f"{p}: gender {gender!r}: expected a word (neutral, female, male)")
    return _body_joints(p, body, trans, betas, family, gender, body_model, fps)


def _body_joints(
    p: Path,
    body: np.ndarray,
    trans: np.ndarray,
    betas: np.ndarray,
    family: str,
    gender: str,
    body_model: Path | None,
    fps: float,
    turn: np.ndarray | None = None,
    meta: dict[str, str] | None = None,
) -> HumanClip:
    """The 22 body joints of checked parameters: the regressed, shaped rest joints, then forward
    kinematics of the axis-angle rotations ``body`` (T, 66: root first) about them, the root at
    ``J_0 + trans``; ``turn`` (3, 3) rotates the result into z up."""
    T = trans.shape[0]
    model = body_model_file(family, gender, body_model, p)
    rest, parents = rest_joints(model, family, betas)
    rot = _rotations(body.reshape(T, 22, 3))  # Local rotations (T, 22, 3, 3).
    glob = np.zeros_like(rot)
    pos = np.zeros((T, 22, 3))
    glob[:, 0] = rot[:, 0]
    pos[:, 0] = rest[0] + trans
    for j in range(1, 22):
        q = int(parents[j])
        glob[:, j] = glob[:, q] @ rot[:, j]
        pos[:, j] = pos[:, q] + glob[:, q] @ (rest[j] - rest[q])
    if turn is not None:
        pos = pos @ turn.T
    info = {"start_frame": "0", "body_model": str(model), "family": family, "gender": gender}
    return HumanClip(names=SMPL_BODY_JOINTS, parents=tuple(int(x) for x in parents),
                     positions_w=pos, fps=fps, source=str(p), skeleton="smpl",
                     meta={**info, **(meta or {})})  # fmt: skip


GVHMR_FPS = 30.0
"""GVHMR's output rate: it runs on the video at 30 frames/s (GMR reads its files at 30 too)."""


def _tensor_array(value: object, p: Path, key: str) -> np.ndarray:
    """A float array from a tensor or array of a GVHMR result, or MotionDataError naming it."""
    try:
        if hasattr(value, "detach"):
            value = value.detach().cpu().double().numpy()  # type: ignore[union-attr]
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, RuntimeError):
        raise MotionDataError(f"{p}: {key}: not an array of numbers") from None
    if not np.all(np.isfinite(a)):
        raise MotionDataError(f"{p}: {key}: NaN or infinite values")
    return a


def load_gvhmr(path: str | os.PathLike[str], *, body_model: Path | None = None) -> HumanClip:
    """A GVHMR result (``hmr4d_results.pt``: ``smpl_params_global`` with ``body_pose`` (T, 63),
    ``global_orient`` (T, 3), ``transl`` (T, 3), ``betas`` (T, 10)) as a clip of the 22 body
    joints of the neutral SMPL-X model, at :data:`GVHMR_FPS`, turned from GVHMR's y up to z up.

    The file is read by ``torch.load(..., weights_only=True)``: tensors and containers only,
    no code (a file that needs more is refused). The shape is frame 0's ``betas``.

    Raises:
        InputError: Naming the file and the field.
    """
    import torch

    from humimic.transforms import Y_UP_TO_Z_UP

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if p.stat().st_size > MAX_BYTES:
        raise MotionDataError(f"{p}: larger than {MAX_BYTES} bytes")
    try:
        with warnings.catch_warnings():  # torch's notes on the pickle protocol: the error says it
            warnings.simplefilter("ignore")
            data = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # An unpickler's errors are many; all mean the same here.
        detail = " ".join(str(e).split())[:200] or type(e).__name__
        raise InputError(
            f"{p}: not a readable GVHMR result (torch.load with weights_only: {detail})"
        ) from None
    params = data.get("smpl_params_global") if isinstance(data, dict) else None
    if not isinstance(params, dict):
        raise MotionDataError(f"{p}: no smpl_params_global: not a GVHMR result (hmr4d_results.pt)")
    arrays = {}
    for key in ("body_pose", "global_orient", "transl", "betas"):
        if key not in params:
            raise MotionDataError(f"{p}: smpl_params_global.{key}: missing")
        arrays[key] = _tensor_array(params[key], p, f"smpl_params_global.{key}")
    trans = arrays["transl"]
    if trans.ndim != 2 or trans.shape[1] != 3 or trans.shape[0] < 1:
        raise MotionDataError(f"{p}: smpl_params_global.transl: expected (T, 3), got "
                              f"{trans.shape}")  # fmt: skip
    T = trans.shape[0]
    for key, width in (("body_pose", 63), ("global_orient", 3)):
        if arrays[key].shape != (T, width):
            raise MotionDataError(f"{p}: smpl_params_global.{key}: expected ({T}, {width}), "
                                  f"got {arrays[key].shape}")  # fmt: skip
    betas = arrays["betas"]
    betas = betas.reshape(-1) if betas.ndim == 1 else betas.reshape(betas.shape[0], -1)[0]
    body = np.concatenate([arrays["global_orient"], arrays["body_pose"]], axis=1)
    return _body_joints(p, body, trans, betas, "smplx", "neutral", body_model, GVHMR_FPS,
                        turn=Y_UP_TO_Z_UP, meta={"layout": "gvhmr", "up": "y (GVHMR)"})  # fmt: skip
