"""Interaction meshes (Laplacian coordinates) and scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from humimic.datasets.scene import load_scene
from humimic.errors import InputError, RetargetError
from humimic.retarget.interaction_mesh import (
    build_mesh,
    laplacian_coordinates,
    laplacian_operator,
    tetra_neighbors,
)

CUBE = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)


def _cloud(n: int = 20, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, size=(n, 3))


def test_neighbors_of_a_cube_centre_are_its_corners() -> None:
    pts = np.vstack([CUBE, [[0.5, 0.5, 0.5]]])
    nb = tetra_neighbors(pts)
    assert nb[8].tolist() == list(range(8))
    for i, ns in enumerate(nb):  # Edges are symmetric.
        for j in ns:
            assert i in nb[j]


@pytest.mark.parametrize("weighting", ["uniform", "inverse_distance"])
def test_laplacian_coordinates_are_invariant_to_translation_and_follow_rotation_and_scale(
    weighting: str,
) -> None:
    pts = _cloud()
    op = laplacian_operator(pts, tetra_neighbors(pts), weighting)
    np.testing.assert_allclose(np.asarray(op.sum(axis=1)).ravel(), 0.0, atol=1e-12)
    d = laplacian_coordinates(op, pts)
    rot = Rotation.from_euler("xyz", [0.3, -0.7, 1.1]).as_matrix()
    moved = 1.7 * pts @ rot.T + np.array([3.0, -2.0, 0.5])
    np.testing.assert_allclose(laplacian_coordinates(op, moved), 1.7 * d @ rot.T, atol=1e-12)


def test_uniform_coordinate_of_a_cube_centre_is_zero_and_inverse_distance_prefers_near() -> None:
    pts = np.vstack([CUBE, [[0.5, 0.5, 0.5]]])
    nb = tetra_neighbors(pts)
    np.testing.assert_allclose(laplacian_coordinates(laplacian_operator(pts, nb), pts)[8], 0.0,
                               atol=1e-12)  # fmt: skip
    pts2 = np.vstack([CUBE, [[0.2, 0.5, 0.5]]])  # Off centre, nearer the x = 0 face.
    nb2 = tetra_neighbors(pts2)
    w = -laplacian_operator(pts2, nb2, "inverse_distance").toarray()[8]
    near, far = w[:4], w[4:8]  # Corners with x = 0, then x = 1.
    assert np.isclose(w[w > 0].sum(), 1.0) and near.min() > far.max()


def test_degenerate_and_tiny_point_sets() -> None:
    flat = np.column_stack([_cloud(12)[:, :2], np.zeros(12)])  # Coplanar: joggled, not an error.
    pts = np.vstack([flat, [[0.0, 0.0, 0.3]]])
    assert all(len(n) > 0 for n in tetra_neighbors(pts))
    with pytest.raises(RetargetError, match="at least 5 points"):
        tetra_neighbors(CUBE[:4])
    with pytest.raises(RetargetError, match="weighting"):
        laplacian_operator(pts, tetra_neighbors(pts), "cotangent")


def test_mesh_residual_is_zero_on_the_source_and_grows_with_deformation() -> None:
    kp, scene = _cloud(6, seed=1), _cloud(30, seed=2)
    mesh = build_mesh(kp, scene)
    assert mesh.energy(kp) < 1e-20
    assert mesh.energy(kp + np.array([0.5, 0.0, 0.0])) > 0.0  # Body moved, scene did not.
    # A body moved together with its scene keeps its coordinates.
    shifted = build_mesh(kp, scene, robot_scene=scene + 0.5)
    assert shifted.energy(kp + 0.5) < 1e-20


def test_holosoma_climb_scene_loads_as_is(shared_data: Path) -> None:
    scene = load_scene(shared_data / "holosoma_climb" / "mocap_climb_seq_0")
    tops = sorted(round(float(o.world_vertices()[:, 2].max()), 3) for o in scene.objects)
    assert [o.name for o in scene.objects] == ["box1", "box2", "box3"]
    assert tops == [0.18, 0.47, 0.95] and scene.static
    robot = scene.to_robot(scale=0.74, yaw=np.pi / 2, origin=np.array([1.0, 0.0, 0.0]),
                           ground=0.01, z_offset=0.03)  # fmt: skip
    v_h, v_r = scene.objects[0].world_vertices(), robot.objects[0].world_vertices()
    expected = 0.74 * (v_h - [1.0, 0.0, 0.0]) @ Rotation.from_euler("z", np.pi / 2).as_matrix().T
    expected[:, 2] = 0.74 * (v_h[:, 2] - 0.01) + 0.03
    np.testing.assert_allclose(v_r, expected, atol=1e-9)


def test_scene_file_boxes_meshes_trajectories_and_errors(tmp_path: Path) -> None:
    np.save(tmp_path / "lift.npy", np.array([[0, 0, 0, 1, 0, 0, 0], [0, 0, 1, 1, 0, 0, 0.0]]))
    (tmp_path / "s.yaml").write_text(
        "schema_version: 1\nfps: 10\nobjects:\n"
        "  - {name: step, box: [1.0, 0.8, 0.2], pos: [0.5, 0, 0.1]}\n"
        "  - {name: crate, box: [0.2, 0.2, 0.2], trajectory: lift.npy}\n"
    )
    scene = load_scene(tmp_path / "s.yaml")
    step = scene.objects[0].world_vertices()
    assert np.isclose(step[:, 2].max(), 0.2) and np.isclose(step[:, 0].min(), 0.0)
    mid = scene.resample(20.0, 3).objects[1]  # 20 fps: frame 1 is half way up.
    assert np.isclose(mid.pose(1)[1][2], 0.5) and not scene.static
    bad = {
        "box: [1, -1, 1]": "extents must be positive",
        "box: [1, 1]": "expected 3 numbers",
        "mesh: nowhere.obj": "no such mesh file",
        "box: [1, 1, 1], colour: red": "unknown keys",
        "box: [1, 1, 1], trajectory: lift.npy": "needs fps",
    }
    for body, message in bad.items():
        (tmp_path / "b.yaml").write_text(f"schema_version: 1\nobjects:\n  - {{{body}}}\n")
        with pytest.raises(InputError, match=message):
            load_scene(tmp_path / "b.yaml")
    with pytest.raises(InputError, match="box_models"):
        load_scene(tmp_path)
