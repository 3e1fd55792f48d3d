"""Where a student distilled around another action base than its teacher's misses the
teacher's labels (``humimic distill --student-base``): the student acts on nominal physics
(16 envs from random frames, 140 policy steps), the teacher labels each state, and the
script prints JSON with the labels' variance, the student's error (MSE, and as a fraction of
that variance), the error regressed on the base offset (``k``: -0.3 means the student applies
70 % of the offset), and, for a ``feedback`` teacher, the variance of each state block's part
of the unclipped LQR correction (in action units).

Usage:
  .venv/bin/python benchmarks/distill_diagnosis.py STUDENT_RUN
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    from humimic.tracking.distill import StudentView
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.export import load_policy_runner
    from humimic.tracking.runs import run_config
    from humimic.tracking.task import load_reference, task_config

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("run", type=Path)
    p.add_argument("--teacher-base", default="feedback")
    p.add_argument("--steps", type=int, default=140)
    args = p.parse_args()
    runner, probe, _ = load_policy_runner(args.run, None)
    probe.close()
    settings = run_config(args.run)[1]
    task = task_config(settings.robot, "none", 0, settings=settings.task)
    motion = load_reference(settings.motion, settings.robot, 1.0 / task.step_dt)
    env = TrackingEnv(task, motion, 16)
    view = StudentView(env, args.teacher_base)
    student, teacher = runner.alg.student, runner.alg.teacher
    err, lab, off = [], [], []
    nv = env.backend.nv
    blocks = {"root_pos": slice(0, 3), "root_rot": slice(3, 6), "joint_pos": slice(6, nv),
              "root_lin_vel": slice(nv, nv + 3), "root_ang_vel": slice(nv + 3, nv + 6),
              "joint_vel": slice(nv + 6, 2 * nv)}  # fmt: skip
    parts: dict[str, list[np.ndarray]] = {k: [] for k in blocks}
    obs = view.get_observations()
    with torch.inference_mode():
        for _ in range(args.steps):
            a, y = student(obs), teacher(obs)
            err.append((a - y).numpy())
            lab.append(y.numpy())
            off.append(obs["teacher_offset"].numpy())
            if args.teacher_base == "feedback":
                _, fb = env.bases.others["feedback"]
                assert fb is not None  # The feedback base has its gains.
                K, ref_q, ref_v = fb
                f = env.state.frame
                dx = env.bases.state_deviation(ref_q[f], ref_v[f])
                for name, s in blocks.items():
                    part = torch.einsum("nij,nj->ni", K[f][:, :, s], dx[:, s]) / env.action_scale
                    parts[name].append(part.numpy())
            obs, *_ = view.step(a)
    view.close()
    e, y, o = np.array(err), np.array(lab), np.array(off)
    k = float((o.ravel() @ e.ravel()) / (o.ravel() @ o.ravel()))
    out = {
        "benchmark": "distill_diagnosis", "run": str(args.run), "teacher_base": args.teacher_base,
        "label_var": float(y.var()), "offset_var": float(o.var()),
        "teacher_residual_var": float((y - o).var()), "mse": float((e**2).mean()),
        "mse_over_label_var": float((e**2).mean() / y.var()), "error_on_offset_k": k,
        "error_explained_by_offset": 1.0 - float(((e - k * o) ** 2).mean() / (e**2).mean()),
        "correction_block_var": {n: float(np.array(v).var()) for n, v in parts.items() if v},
    }  # fmt: skip
    print(json.dumps(out))


if __name__ == "__main__":
    main()
