"""SMPL-family parameter files (issue 56) on a synthetic SMPL-X body model the tests write in the
smplx file layout (no licence-gated data): joints checked against hand computations (the rest
pose with a shape, one rotated joint, a root turn, a translation); bad files exit 2 naming the
file and the key; a clip from the synthetic model retargets with the quality bar."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from humimic.cli.main import main
from humimic.datasets import load_clip
from humimic.datasets.smpl import BODY_MODELS_ENV, SMPL_BODY_JOINTS
from humimic.errors import HumimicError
from test_hostile_cli import _refused

# A standing human's 22 body joints, z up, facing -y as AMASS's are (metres).
REST = {
    "pelvis": (0, 0, 0.95), "left_hip": (0.09, 0, 0.9), "right_hip": (-0.09, 0, 0.9),
    "spine1": (0, 0, 1.05), "left_knee": (0.1, 0, 0.5), "right_knee": (-0.1, 0, 0.5),
    "spine2": (0, 0, 1.18), "left_ankle": (0.1, 0.03, 0.08), "right_ankle": (-0.1, 0.03, 0.08),
    "spine3": (0, 0, 1.3), "left_foot": (0.1, -0.1, 0.02), "right_foot": (-0.1, -0.1, 0.02),
    "neck": (0, 0, 1.5), "left_collar": (0.08, 0, 1.42), "right_collar": (-0.08, 0, 1.42),
    "head": (0, 0, 1.62), "left_shoulder": (0.18, 0, 1.42), "right_shoulder": (-0.18, 0, 1.42),
    "left_elbow": (0.2, 0, 1.14), "right_elbow": (-0.2, 0, 1.14), "left_wrist": (0.21, 0, 0.9),
    "right_wrist": (-0.21, 0, 0.9),
}  # fmt: skip
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
"""SMPL's body tree (the smplx kintree's first 22)."""
N_JOINTS, N_BETAS = 55, 10


def _model(folder: Path, family: str = "smplx", gender: str = "NEUTRAL", joints: int = N_JOINTS,
           seed: int = 0) -> Path:  # fmt: skip
    """A synthetic body model: two vertices about each joint (the regressor averages them),
    the hands' and face's joints on the wrists and head, random shape directions."""
    rng = np.random.default_rng(seed)
    rest = np.array([REST[n] for n in SMPL_BODY_JOINTS], dtype=float)
    extra = rest[[20] * 15 + [21] * 15 + [15] * (joints - 52)][: joints - 22]
    centres = np.vstack([rest, extra])
    v = np.repeat(centres, 2, axis=0) + np.tile([[0.01, 0, 0], [-0.01, 0, 0]], (joints, 1))
    reg = np.zeros((joints, 2 * joints))
    for j in range(joints):
        reg[j, 2 * j : 2 * j + 2] = 0.5
    parents = np.array([*PARENTS, *([20] * 15 + [21] * 15 + [15] * 3)][:joints], dtype=np.int64)
    parents[0] = 4294967295  # As the files store the root's "no parent".
    tree = np.stack([parents, np.arange(joints)])
    path = folder / family / f"{family.upper()}_{gender}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, v_template=v, shapedirs=0.01 * rng.standard_normal((2 * joints, 3, N_BETAS)),
             J_regressor=reg, kintree_table=tree, f=np.zeros((1, 3), dtype=np.int64))  # fmt: skip
    return path


def _clip(path: Path, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray,
          gender: str = "neutral", **extra: object) -> Path:  # fmt: skip
    np.savez(path, poses=poses, trans=trans, betas=betas, gender=np.array(gender),
             mocap_frame_rate=np.array(120.0), surface_model_type=np.array("smplx"),
             **extra)  # type: ignore[arg-type]  # fmt: skip
    return path


def _rx(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.fixture
def models(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "body_models"
    _model(folder)
    monkeypatch.setenv(BODY_MODELS_ENV, str(folder))
    return folder


def test_joints_by_hand_rest_shape_rotation_turn_and_translation(
    models: Path, tmp_path: Path
) -> None:
    data = np.load(models / "smplx" / "SMPLX_NEUTRAL.npz")
    betas = np.linspace(-1.0, 1.0, 16)  # More than the model's 10: the first 10 are used.
    shaped = data["v_template"] + data["shapedirs"] @ betas[:N_BETAS]
    rest = (data["J_regressor"] @ shaped)[:22]
    poses = np.zeros((4, 165))
    trans = np.zeros((4, 3))
    poses[1, 4 * 3] = np.pi / 2  # Frame 1: the left knee turned 90 degrees about x.
    poses[2, 2] = np.pi / 2  # Frame 2: the root turned 90 degrees about z.
    trans[3] = [0.3, -0.2, 0.1]  # Frame 3: moved.
    clip = load_clip(_clip(tmp_path / "c.npz", poses, trans, betas))
    assert clip.names == SMPL_BODY_JOINTS and clip.fps == 120.0 and clip.skeleton == "smpl"
    np.testing.assert_allclose(clip.positions_w[0], rest, atol=1e-12)
    knee, ankle, foot = 4, 7, 10
    turned = rest.copy()
    for j in (ankle, foot):
        turned[j] = rest[knee] + _rx(np.pi / 2) @ (rest[j] - rest[knee])
    np.testing.assert_allclose(clip.positions_w[1], turned, atol=1e-12)
    np.testing.assert_allclose(clip.positions_w[2], rest[0] + (rest - rest[0]) @ _rz(np.pi / 2).T,
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(clip.positions_w[3], rest + trans[3], atol=1e-12)


def test_root_orient_and_pose_body_as_the_poses_row(models: Path, tmp_path: Path) -> None:
    """The split layout (``root_orient``, ``pose_body``) gives the joints ``poses`` gives."""
    rng = np.random.default_rng(1)
    poses = np.zeros((3, 165))
    poses[:, :66] = 0.3 * rng.standard_normal((3, 66))
    trans, betas = rng.standard_normal((3, 3)), np.zeros(10)
    a = load_clip(_clip(tmp_path / "a.npz", poses, trans, betas))
    b_path = tmp_path / "b.npz"
    np.savez(b_path, root_orient=poses[:, :3], pose_body=poses[:, 3:66], trans=trans,
             betas=betas, gender=np.array("neutral"), mocap_framerate=np.array(60.0))  # fmt: skip
    b = load_clip(b_path)
    np.testing.assert_allclose(b.positions_w, a.positions_w, atol=1e-12)
    assert b.fps == 60.0


@pytest.mark.parametrize(
    ("change", "expect"),
    [
        ({"poses": np.zeros((3, 10))}, "poses: expected (T=3, 72 | 156 | 165)"),
        ({"trans": np.full((3, 3), np.nan)}, "trans: NaN or infinite at frame 0"),
        ({"trans": None}, "missing key(s) ['trans']"),
        ({"gender": "female"}, "SMPLX_FEMALE.npz"),
        ({"mocap_frame_rate": -1.0}, "frame rate -1.0 is not positive"),
    ],
)
def test_bad_files_exit_2_naming_file_and_key(
    change: dict, expect: str, models: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fields = {"poses": np.zeros((3, 165)), "trans": np.zeros((3, 3)), "betas": np.zeros(10),
              "gender": "neutral", "mocap_frame_rate": 120.0,
              "surface_model_type": "smplx"} | change  # fmt: skip
    path = tmp_path / "bad.npz"
    arrays = {k: np.asarray(v) for k, v in fields.items() if v is not None}
    np.savez(path, **arrays)  # pyright: ignore[reportArgumentType]
    _refused(["retarget", str(path), "--out", str(tmp_path / "o.npz")], capsys, "bad.npz"
             if "SMPLX_FEMALE" not in expect else "gender 'female'", expect)  # fmt: skip
    assert not (tmp_path / "o.npz").exists()


def test_a_body_model_of_another_family_or_none_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    clip = _clip(tmp_path / "c.npz", np.zeros((2, 165)), np.zeros((2, 3)), np.zeros(10))
    monkeypatch.delenv(BODY_MODELS_ENV, raising=False)
    _refused(["retarget", str(clip), "--out", str(tmp_path / "o.npz")], capsys,
             "--body-model DIR", "licence-gated", "smpl-x.is.tue.mpg.de")  # fmt: skip
    wrong = tmp_path / "wrong"
    _model(wrong, joints=24)  # An SMPL model's 24 joints, in an SMPL-X file name.
    _refused(["retarget", str(clip), "--out", str(tmp_path / "o.npz"), "--body-model",
              str(wrong)], capsys, "J_regressor: expected (55,", "another family")  # fmt: skip


def test_a_synthetic_smplx_walk_retargets_with_the_quality_bar(
    models: Path, tmp_path: Path
) -> None:
    """Two seconds of a stepping gait on the synthetic model (hips and knees swinging in
    turn, the body moving forward, -y as AMASS faces): the G1 follows it with 0 limit
    violations, <= 5 mm penetration and 0 self-collision frames."""
    T = 240
    t = np.arange(T) / 120.0
    phase = 2 * np.pi * 1.0 * t
    poses = np.zeros((T, 165))
    poses[:, 1 * 3] = -0.35 * np.sin(phase)  # Left hip about x (flexion swings the leg -y).
    poses[:, 2 * 3] = 0.35 * np.sin(phase)
    poses[:, 4 * 3] = 0.6 * np.clip(np.sin(phase), 0, None)  # Knees bend on their swing.
    poses[:, 5 * 3] = 0.6 * np.clip(-np.sin(phase), 0, None)
    poses[:, 16 * 3 + 1] = -1.2  # Arms down from the T-pose.
    poses[:, 17 * 3 + 1] = 1.2
    trans = np.zeros((T, 3))
    trans[:, 1] = -0.5 * t
    trans[:, 2] = -0.02 * (1 - np.cos(2 * phase))
    clip = _clip(tmp_path / "walk.npz", poses, trans, np.zeros(10))
    report = tmp_path / "walk.json"
    assert main(["retarget", str(clip), "--out", str(tmp_path / "g1.npz"), "--report",
                 str(report), "--quiet"]) == 0  # fmt: skip
    r = json.loads(report.read_text())
    assert r["skeleton"] == "smpl"
    assert r["joint_limit_violations"] == 0
    assert r["max_ground_penetration_mm"] <= 5.0
    assert r["self_collision_frames"] == 0


def test_error_types_are_humimic_errors(models: Path, tmp_path: Path) -> None:
    path = tmp_path / "x.npz"
    np.savez(path, poses=np.zeros((2, 165)), trans=np.zeros((2, 3)))
    with pytest.raises(HumimicError, match="mocap_framerate"):
        load_clip(path)


def test_mutated_smpl_files_are_read_or_refused(models: Path, tmp_path: Path) -> None:
    """Keys dropped, arrays reshaped, cut, made text or non-finite: a clip, or a humimic error
    naming the file; never another exception."""
    rng = np.random.default_rng(3)
    base = {"poses": 0.1 * rng.standard_normal((5, 165)), "trans": rng.standard_normal((5, 3)),
            "betas": rng.standard_normal(10), "gender": np.array("neutral"),
            "mocap_frame_rate": np.array(120.0), "surface_model_type": np.array("smplx")}  # fmt: skip
    for case in range(60):
        fields = dict(base)
        key = str(rng.choice(list(fields)))
        kind = case % 6
        if kind == 0:
            del fields[key]
        elif kind == 1:
            fields[key] = np.asarray(fields[key]).reshape(-1)[: max(1, int(rng.integers(8)))]
        elif kind == 2:
            fields[key] = np.array("x")
        elif kind == 3 and np.asarray(fields[key]).dtype.kind == "f":
            a = np.array(fields[key], dtype=float)
            a.reshape(-1)[int(rng.integers(a.size))] = rng.choice([np.nan, np.inf, 1e308])
            fields[key] = a
        elif kind == 4:
            fields[key] = np.zeros((0, 3))
        else:
            fields[key] = np.asarray(fields[key]).astype(np.int64) if np.asarray(
                fields[key]).dtype.kind == "f" else fields[key]  # fmt: skip
        path = tmp_path / f"m{case}.npz"
        np.savez(path, **fields)  # pyright: ignore[reportArgumentType]
        try:
            clip = load_clip(path)
            assert np.all(np.isfinite(clip.positions_w)), (case, key)
        except HumimicError as e:
            assert str(path) in str(e) or "body model" in str(e), (case, key, e)


def _gvhmr(path: Path, body_pose: object, global_orient: object, transl: object,
           betas: object) -> Path:  # fmt: skip
    """A file as GVHMR writes its result (``hmr4d_results.pt``): float32 tensors."""
    import torch

    def t(a: object) -> object:
        return torch.as_tensor(np.asarray(a), dtype=torch.float32) if a is not None else None

    params = {"body_pose": t(body_pose), "global_orient": t(global_orient), "transl": t(transl),
              "betas": t(betas)}  # fmt: skip
    params = {k: v for k, v in params.items() if v is not None}
    torch.save({"smpl_params_global": params, "smpl_params_incam": dict(params)}, path)
    return path


def test_a_gvhmr_result_is_the_amass_layout_turned_from_y_up(models: Path, tmp_path: Path) -> None:
    """The same parameters as an AMASS file (z up) and as GVHMR's result (y up, 30 fps, neutral
    SMPL-X, per-frame betas): the same joints, turned by the y-up-to-z-up rotation."""
    from humimic.transforms import Y_UP_TO_Z_UP

    rng = np.random.default_rng(4)
    T = 5
    body = (0.3 * rng.standard_normal((T, 66))).astype(np.float32).astype(np.float64)
    trans = rng.standard_normal((T, 3)).astype(np.float32).astype(np.float64)
    betas = np.linspace(-1, 1, 10).astype(np.float32).astype(np.float64)
    amass = tmp_path / "a.npz"
    np.savez(amass, root_orient=body[:, :3], pose_body=body[:, 3:], trans=trans, betas=betas,
             gender=np.array("neutral"), mocap_framerate=np.array(30.0))  # fmt: skip
    ref = load_clip(amass)
    path = _gvhmr(tmp_path / "hmr4d_results.pt", body[:, 3:], body[:, :3], trans,
                  np.tile(betas, (T, 1)))  # fmt: skip
    clip = load_clip(path)
    assert clip.fps == 30.0 and clip.names == SMPL_BODY_JOINTS and clip.skeleton == "smpl"
    np.testing.assert_allclose(clip.positions_w, ref.positions_w @ Y_UP_TO_Z_UP.T, atol=1e-12)
    # The rest frame by hand: the regressed joints, y up turned to z up.
    zero = load_clip(_gvhmr(tmp_path / "z.pt", np.zeros((1, 63)), np.zeros((1, 3)),
                            np.zeros((1, 3)), np.zeros((1, 10))))  # fmt: skip
    data = np.load(models / "smplx" / "SMPLX_NEUTRAL.npz")
    rest = (data["J_regressor"] @ data["v_template"])[:22]
    np.testing.assert_allclose(zero.positions_w[0], rest @ Y_UP_TO_Z_UP.T, atol=1e-12)


@pytest.mark.parametrize(
    ("make", "expect"),
    [
        ("text", "not a readable GVHMR result"),
        ("no_params", "no smpl_params_global"),
        ("no_transl", "smpl_params_global.transl: missing"),
        ("bad_pose", "smpl_params_global.body_pose: expected (3, 63)"),
        ("nan", "smpl_params_global.global_orient: NaN or infinite"),
        ("code", "not a readable GVHMR result"),
    ],
)
def test_bad_gvhmr_files_exit_2_naming_file_and_field(
    make: str, expect: str, models: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import pickle

    import torch

    path = tmp_path / "bad.pt"
    ok = {"body_pose": np.zeros((3, 63)), "global_orient": np.zeros((3, 3)),
          "transl": np.zeros((3, 3)), "betas": np.zeros((3, 10))}  # fmt: skip
    if make == "text":
        path.write_text("not a torch file\n")
    elif make == "no_params":
        torch.save({"smpl_params_incam": {}}, path)
    elif make == "no_transl":
        _gvhmr(path, ok["body_pose"], ok["global_orient"], None, ok["betas"])
    elif make == "bad_pose":
        _gvhmr(path, np.zeros((3, 60)), ok["global_orient"], ok["transl"], ok["betas"])
    elif make == "nan":
        _gvhmr(path, ok["body_pose"], np.full((3, 3), np.nan), ok["transl"], ok["betas"])
    else:  # A pickle that would run code on loading: weights_only refuses it.
        path.write_bytes(pickle.dumps({"smpl_params_global": Path("x")}))
    _refused(["retarget", str(path), "--out", str(tmp_path / "o.npz")], capsys, "bad.pt", expect)
    assert not (tmp_path / "o.npz").exists()


def test_mutated_gvhmr_files_are_read_or_refused(models: Path, tmp_path: Path) -> None:
    """Bytes of a GVHMR result flipped, cut or put in (a zip of pickled tensors): a clip, or a
    humimic error; never another exception."""
    from byte_mutants import byte_mutants, read_or_refused

    base = _gvhmr(tmp_path / "base.pt", np.zeros((4, 63)), np.zeros((4, 3)), np.zeros((4, 3)),
                  np.zeros((4, 10))).read_bytes()  # fmt: skip
    seen = read_or_refused(byte_mutants(base, 3, 60, edits=4, cut=200), tmp_path / "m.pt",
                           load_clip, HumimicError)  # fmt: skip
    assert seen["refused"] > 0, seen


def test_a_pickled_body_model_and_a_pickled_motion_read_as_their_npz(
    models: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SMPL's ``.pkl`` model layout (chumpy arrays, a sparse CSC ``J_regressor``; read as data,
    chumpy absent) gives the joints its ``.npz`` gives; so does a motion pickled as GMR's OMOMO
    split writes it (``poses`` padded to 165, object keys beside it)."""
    import pickle
    import sys
    import types

    import scipy.sparse as sp

    from test_datapickle import _Ch

    rng = np.random.default_rng(2)
    poses = np.zeros((3, 165))
    poses[:, :66] = 0.3 * rng.standard_normal((3, 66))
    trans, betas = rng.standard_normal((3, 3)), np.linspace(-1, 1, 16)
    ref = load_clip(_clip(tmp_path / "ref.npz", poses, trans, betas))

    data = dict(np.load(models / "smplx" / "SMPLX_NEUTRAL.npz"))
    mod = types.ModuleType("chumpy.ch")
    mod.Ch = _Ch  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch", mod)
    pkl_model = {"v_template": _Ch(data["v_template"]), "shapedirs": _Ch(data["shapedirs"]),
                 "J_regressor": sp.csc_matrix(data["J_regressor"]),
                 "kintree_table": data["kintree_table"], "f": data["f"], "bs_style": "lbs"}  # fmt: skip
    pkl_folder = tmp_path / "pkl_models" / "smplx"
    pkl_folder.mkdir(parents=True)
    (pkl_folder / "SMPLX_NEUTRAL.pkl").write_bytes(pickle.dumps(pkl_model, protocol=2))
    monkeypatch.delitem(sys.modules, "chumpy.ch")
    monkeypatch.delitem(sys.modules, "chumpy")
    monkeypatch.setenv(BODY_MODELS_ENV, str(tmp_path / "pkl_models"))
    a = load_clip(tmp_path / "ref.npz")
    np.testing.assert_allclose(a.positions_w, ref.positions_w, atol=1e-12)
    assert a.meta["body_model"].endswith("SMPLX_NEUTRAL.pkl")

    monkeypatch.setenv(BODY_MODELS_ENV, str(models))
    motion = {"seq_name": "sub3_largebox_003", "poses": poses, "trans": trans, "betas": betas,
              "gender": "neutral", "mocap_frame_rate": np.array(120), "root_orient": poses[:, :3],
              "pose_body": poses[:, 3:66], "obj_rot": np.zeros((3, 3, 3))}  # fmt: skip
    path = tmp_path / "sub3_largebox_003.pkl"
    path.write_bytes(pickle.dumps(motion))
    b = load_clip(path)
    np.testing.assert_allclose(b.positions_w, ref.positions_w, atol=1e-12)
    assert b.fps == 120.0


def test_a_pickle_that_is_not_data_is_refused_by_the_cli(
    models: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "evil.pkl"
    marker = tmp_path / "ran"
    path.write_bytes(f"cos\nsystem\n(S'touch {marker}'\ntR.".encode())
    _refused(["retarget", str(path), "--out", str(tmp_path / "o.npz")], capsys, "evil.pkl",
             "refused: it names os.system")  # fmt: skip
    assert not marker.exists() and not (tmp_path / "o.npz").exists()
    no_trans = tmp_path / "no_trans.pkl"
    import pickle

    no_trans.write_bytes(pickle.dumps({"poses": np.zeros((2, 165))}))
    _refused(["retarget", str(no_trans), "--out", str(tmp_path / "o.npz")], capsys,
             "no_trans.pkl", "missing key(s) ['trans']")  # fmt: skip
