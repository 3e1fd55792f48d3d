"""Dataset retargeting throughput: clips per minute on a folder of clips, 1 worker against N, in
the same run (ratios; this machine is noisy). Prints one JSON object.

The folder: the CMU clips of ../shared/data/cmu and copies of them cut to other lengths (a
quarter, a half, three quarters of their frames), ``--clips`` in all, written to a temporary
folder. Each configuration retargets the whole folder into its own fresh output folder through
``humimic.pipeline.dataset.run_dataset`` (manifest and all), G1, default settings. Wall time
includes the workers' start-up (forked from this process, which has imported the retargeting
code before any timing; each builds its robot model).

With ``--ray``, a third configuration: the same folder as Ray tasks on a local Ray instance of
``--workers`` CPUs (needs ``pip install ray==2.60.0``); the instance's start is timed apart
(``ray_init_seconds``), its workers' start-up is in the wall time as the pool's is.

Usage: .venv/bin/python benchmarks/dataset_speed.py [--clips 50] [--workers 2] [--repeats 1] [--ray]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import humimic.retarget  # noqa: F401 - imported before any timing: no configuration pays it
from humimic.pipeline.batch import ClipOptions
from humimic.pipeline.dataset import run_dataset

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu"


def _cut(src: Path, dst: Path, fraction: float) -> None:
    lines = src.read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(lines) if line.startswith("Frames:"))
    body = lines[i + 2 :]
    n = max(20, int(len(body) * fraction))
    dst.write_text("".join([*lines[:i], f"Frames: {n}\n", lines[i + 1], *body[:n]]))


def make_folder(root: Path, clips: int) -> list[Path]:
    sources = sorted(CMU.glob("*.bvh"))
    if not sources:
        raise SystemExit(f"no CMU clips in {CMU} (../shared/data/cmu)")
    made = []
    k = 0
    while len(made) < clips:
        src = sources[k % len(sources)]
        fraction = (1.0, 0.25, 0.5, 0.75)[(k // len(sources)) % 4]
        dst = root / f"{src.stem}_{k:03d}.bvh"
        _cut(src, dst, fraction)
        made.append(dst)
        k += 1
    return made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clips", type=int, default=50)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--ray", action="store_true", help="also on a local Ray instance")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "clips"
        folder.mkdir()
        made = make_folder(folder, args.clips)
        for rep in range(args.repeats):
            configs = [("pool", 1), ("pool", args.workers)]
            if args.ray:
                configs.append(("ray", args.workers))
            for engine, workers in configs:
                out = Path(tmp) / f"out_{engine}_{workers}_{rep}"
                extra = {}
                ray = None
                if engine == "ray":
                    ray = importlib.import_module("ray")  # the ray extra

                    t0 = time.perf_counter()
                    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
                    extra["ray_init_seconds"] = time.perf_counter() - t0
                t0 = time.perf_counter()
                s = run_dataset((folder,), out, ClipOptions(robot="g1"), workers=workers,
                                ray="local" if engine == "ray" else None, quiet=True)  # fmt: skip
                wall = time.perf_counter() - t0
                if ray is not None:
                    ray.shutdown()
                frames = sum(int(r["headline"]["frames"]) for r in s.done)
                rows.append({"engine": engine, "workers": workers, "repeat": rep,
                             "clips_done": len(s.done), "clips_failed": len(s.failed),
                             "wall_seconds": wall, "clips_per_minute": 60 * len(s.done) / wall,
                             "output_frames_per_second": frames / wall, **extra})  # fmt: skip
    one = [r for r in rows if r["workers"] == 1]
    many = [r for r in rows if r["engine"] == "pool" and r["workers"] == args.workers]
    on_ray = [r for r in rows if r["engine"] == "ray"]
    ratios = [b["clips_per_minute"] / a["clips_per_minute"] for a, b in zip(one, many, strict=True)]
    ray_vs_pool = [
        r["wall_seconds"] / p["wall_seconds"] for p, r in zip(many, on_ray, strict=False)
    ]
    print(json.dumps({
        "benchmark": "dataset_speed",
        "clips": len(made),
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "python": platform.python_version()},
        "rows": rows,
        "speedup": ratios,
        "ray_wall_over_pool_wall": ray_vs_pool,
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
