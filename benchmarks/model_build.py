"""Building the models humimic simulates, against building them the way it did before.

The mesh-free models (training, floating-base predictions) and the fixed-base prediction model
are made by deleting elements (mesh geoms, meshes, textures, sensors) from the robot's nominal
spec, after compiling it once to read the meshes' bounding boxes and the resting contacts.
MuJoCo deletes an element from a spec that was compiled far more slowly than from one that was
not, so humimic compiles a copy. The baseline here is the old order (compile the spec itself,
then delete), on the same elements, alternating with the new one repeat by repeat; both are
timed after a warm-up (MuJoCo's mesh cache holds the robot's meshes after the first compile).

Prints one JSON object: per robot, the seconds of each builder (median over the repeats) and
of the two ways of deleting, and their ratio.

Usage: .venv/bin/python benchmarks/model_build.py [--robots g1 t1] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import mujoco
import numpy as np

from humimic.robots import get_robot
from humimic.robots.model import nominal_spec
from humimic.sim.models import floating_prediction_spec, prediction_spec, training_model

BASE_POSE = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def _delete_after(compile_copy: bool, robot) -> float:
    spec, _ = nominal_spec(robot)
    t = time.perf_counter()
    (spec.copy() if compile_copy else spec).compile()
    for mat in spec.materials:
        mat.textures = [""] * len(mat.textures)
    # The elements the mesh-free model removes: mesh geoms, meshes, textures.
    for geom in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH][::-1]:
        spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    for tex in list(spec.textures):
        spec.delete(tex)
    spec.compile()
    return time.perf_counter() - t


def _time(f) -> float:
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description="Model building, new against old")
    parser.add_argument("--robots", nargs="+", default=["g1", "t1"])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    out: dict = {"benchmark": "model_build", "machine": {"cpu": platform.processor() or
                 platform.machine(), "cores": os.cpu_count()}, "mujoco": mujoco.__version__,
                 "repeats": args.repeats, "robots": {}}  # fmt: skip
    for name in args.robots:
        robot = get_robot(name)
        nominal_spec(robot)[0].compile()  # Warm-up: MuJoCo's mesh cache.
        times: dict[str, list[float]] = {}
        for _ in range(args.repeats):
            for key, f in (
                ("delete_after_compiling_the_spec_s", lambda r=robot: _delete_after(False, r)),
                ("delete_after_compiling_a_copy_s", lambda r=robot: _delete_after(True, r)),
            ):
                times.setdefault(key, []).append(f())
            times.setdefault("training_model_s", []).append(_time(
                lambda r=robot: training_model(r, body_names=[r.root_body])))  # fmt: skip
            times.setdefault("prediction_spec_compiled_s", []).append(_time(
                lambda r=robot: prediction_spec(r, BASE_POSE).compile()))  # fmt: skip
            times.setdefault("floating_prediction_spec_compiled_s", []).append(_time(
                lambda r=robot: floating_prediction_spec(r).compile()))  # fmt: skip
        row = {k: round(float(np.median(v)), 3) for k, v in times.items()}
        row["old_over_new"] = round(
            row["delete_after_compiling_the_spec_s"] / row["delete_after_compiling_a_copy_s"], 1
        )
        out["robots"][name] = row
    print(json.dumps(out))


if __name__ == "__main__":
    main()
