"""``humimic loop``: deploy on the "real" robot, find what the simulator lacks, fine-tune, redeploy.

:func:`loop` runs the stages; :func:`deploy`, :func:`deployment_session` and
:func:`gantry_session` are those that read the "real" robot.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from humimic.configs.jobs import EvalSettings, LoopSettings
from humimic.configs.runs import TrainSettings
from humimic.errors import InputError, OutputPathError
from humimic.io import atomic_write_text, check_writable, json_ready

MAX_DEPLOY_EPISODES = 64
"""Most episodes in one deployment log."""
_METRICS = ("success_rate", "mean_steps", "mpjpe_global_mm", "mpjpe_root_mm", "joint_error_rad")


def deploy(s: LoopSettings, run: Path, out: Path) -> dict:
    """Run ``run``'s policy on the real robot; write its metrics, MCAP and robot log (the
    first episode).

    Returns:
        The evaluation results (policy and open loop).
    """
    from humimic.real2sim.robotlog import write_robot_log
    from humimic.tracking.evaluate import run_evaluation, write_eval_mcap

    settings = EvalSettings(run=run, episodes=s.episodes, motion=s.motion, physics=s.real,
                            device=s.device, seed=s.seed)  # fmt: skip
    ev = run_evaluation(settings)
    out.mkdir(parents=True, exist_ok=True)
    write_eval_mcap(out / "eval.mcap", ev.motion, ev.joint_names, ev.step_dt, ev.policy,
                    ev.open_loop, ev.results)  # fmt: skip
    results = dict(ev.results)
    if len(ev.policy.qpos) >= 2:
        (log,) = _robot_logs(run, ev.joint_names, ev.step_dt, [ev.policy])
        results["robot_log"] = str(write_robot_log(log, out / "robot_log.mcap"))
    atomic_write_text(out / "eval.json", json.dumps(json_ready(results), indent=2) + "\n")
    return results


def _robot_logs(run: Path, names: tuple[str, ...], dt: float, traces: list[Any]) -> list[Any]:
    """Each episode's trace as a floating-base robot log: states every control step, and the
    PD targets each step applied, stamped when that step began."""
    from humimic.real2sim.robotlog import ImuLog, PoseTrack, RobotLog
    from humimic.robots import get_robot
    from humimic.robots.model import nominal_spec
    from humimic.tracking.runs import read_run_settings
    from humimic.transforms import quat_mul, quat_to_matrix

    robot = get_robot(read_run_settings(run).robot)
    drives = nominal_spec(robot)[1]
    kp = np.array([drives[n].kp for n in names])
    kd = np.array([drives[n].kd for n in names])
    site = _imu_site(robot)
    # A floating base has no fixed pose: the identity (a unit quaternion) stands in for it.
    identity = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    logs = []
    for tr in traces:
        qpos, qvel = np.stack(tr.qpos), np.stack(tr.qvel)
        t = np.arange(len(qpos)) * dt
        # The trace's targets[k] drove the step that ended at t[k]: sent at t[k - 1].
        cmd = np.stack(tr.targets)[1:]
        zeros = np.zeros_like(cmd)
        imu = None
        if site is not None:  # Orientation, gyro and accelerometer at the IMU's site.
            name, q_bs, p_bs, gravity = site
            quat_ws = quat_mul(qpos[:, 3:7], np.broadcast_to(q_bs, (len(t), 4)))
            R_wb = quat_to_matrix(qpos[:, 3:7])
            omega_w = np.einsum("nij,nj->ni", R_wb, qvel[:, 3:6])
            v_site = qvel[:, :3] + np.cross(omega_w, R_wb @ p_bs)
            # A sampled accelerometer reads the mean specific force between its neighbouring
            # samples (as a low-pass filter before sampling would): the site's velocity
            # differenced, gravity taken out, in the IMU's axes.
            f_w = np.gradient(v_site, t, axis=0) - gravity
            acc_b = np.einsum("nji,nj->ni", quat_to_matrix(quat_ws), f_w)
            imu = ImuLog(site=name, t=t, quat_w=quat_ws,
                         gyro_b=qvel[:, 3:6] @ quat_to_matrix(q_bs), acc_b=acc_b)  # fmt: skip
        logs.append(RobotLog(
            robot=robot.name, base="floating", base_pose=identity, joint_names=names, t=t,
            q=qpos[:, 7:], qd=qvel[:, 6:], effort=None, t_cmd=t[:-1], cmd_q=cmd,
            cmd_qd=zeros, cmd_tau=zeros, kp=np.tile(kp, (len(cmd), 1)),
            kd=np.tile(kd, (len(cmd), 1)), imu=imu,
            mocap=PoseTrack(t=t, pos_w=qpos[:, :3], quat_w=qpos[:, 3:7]),
        ))  # fmt: skip
    return logs


def deployment_session(s: LoopSettings, run: Path, path: Path) -> dict:
    """Log the policy performing the clip on the real robot, episode after episode, as one
    deployment log (floating base, IMU, motion capture; 1 s between episodes), about
    ``--sysid-duration`` seconds of it. Each episode starts from the training's reset noise
    about the first frame (``humimic eval --start-noise``), so that the episodes differ; one
    that falls ends there.

    Returns:
        What was logged: ``episodes``, ``falls``, ``seconds`` (of robot motion), ``log``.
    """
    from humimic.motion import load_motion
    from humimic.real2sim.robotlog import join_logs, write_robot_log
    from humimic.tracking.evaluate import run_evaluation
    from humimic.tracking.runs import recorded_motion
    from humimic.tracking.task import is_library

    motion = s.motion
    clip_path = motion or recorded_motion(run)
    if is_library(clip_path):
        raise InputError(
            f"{clip_path}: a library of clips; the loop deploys one: pass --motion CLIP.npz"
        )
    clip = load_motion(clip_path)
    seconds = (clip.num_frames - 1) / clip.fps
    n = int(min(MAX_DEPLOY_EPISODES, max(1, np.ceil(s.sysid_duration / max(seconds, 0.1)))))
    # Another seed than the deploy stage's evaluation: other reset-noise draws.
    settings = EvalSettings(run=run, episodes=n, motion=motion, physics=s.real,
                            device=s.device, seed=s.seed + 1, start_noise=True)  # fmt: skip
    ev = run_evaluation(settings, open_loop=False, traces=n, protocols=False)
    lived = [tr for tr in ev.policy_traces if len(tr.qpos) >= 2]
    logs = _robot_logs(run, ev.joint_names, ev.step_dt, lived)
    if not logs:
        raise InputError(f"{run}: the policy fell at once in every episode on the real robot; "
                         "no deployment log to diagnose (use --sysid-log gantry)")  # fmt: skip
    write_robot_log(join_logs(logs, pause=1.0), path)
    p = ev.results["policy"]
    return {"log": str(path), "episodes": n,
            "falls": round(n * (1.0 - p["success_rate"])),
            "seconds": float(sum(lg.duration for lg in logs))}  # fmt: skip


def _imu_site(robot: Any) -> tuple[str, np.ndarray, np.ndarray, np.ndarray] | None:
    """The root body's ``*imu*`` site, where a deployed robot's IMU sits: its name, its
    rotation (w x y z) and position in the body, and the model's gravity [m/s^2]; ``None``
    when the root body has none."""
    from humimic.sim.models import floating_prediction_spec

    m = floating_prediction_spec(robot).compile()
    root = m.body(robot.root_body).id
    sites = [s for s in range(m.nsite)
             if m.site_bodyid[s] == root and "imu" in m.site(s).name.lower()]  # fmt: skip
    if not sites:
        return None
    s = sites[0]
    return (m.site(s).name, m.site_quat[s] / np.linalg.norm(m.site_quat[s]),
            m.site_pos[s].copy(), m.opt.gravity.copy())  # fmt: skip


def gantry_session(s: LoopSettings, robot: str, path: Path) -> Path:
    """Record the real robot hanging in a gantry (multi-sine PD targets) as a robot log."""
    from humimic.real2sim.robotlog import write_robot_log
    from humimic.real2sim.simulate import LogSettings, simulate_log
    from humimic.robots import get_robot
    from humimic.sim.physics import load_physics

    real = load_physics(s.real)
    settings = LogSettings(duration=s.sysid_duration, seed=s.seed)
    log = simulate_log(get_robot(robot), list(real.effects), settings,
                       edit=real.edit_parameters)  # fmt: skip
    return write_robot_log(log, path)


def _check(s: LoopSettings) -> Any:
    from humimic.sim.physics import load_physics
    from humimic.tracking.runs import resolve_checkpoint, run_config

    s.validate()
    load_physics(s.real)  # Read and checked now: a bad value fails before the first deploy.
    config, run = run_config(s.run)
    if config.get("kind") == "student":
        raise InputError(f"{s.run}: a distilled student; the loop fine-tunes PPO runs (fine-tune "
                         "its teacher, then distill again)")  # fmt: skip
    if run.variant in ("teacher", "rma"):
        raise InputError(f"{s.run}: a {run.variant} run reads simulator parameters and cannot "
                         "be deployed; run the loop on a deployable variant")  # fmt: skip
    if s.motion is not None and not s.motion.is_file():
        raise InputError(f"--motion {s.motion}: no such file")
    if s.out.resolve().is_relative_to(s.run.resolve()):
        raise InputError(f"--out {s.out}: inside the run folder {s.run}, which the loop reads; "
                         "choose a folder outside it")  # fmt: skip
    if s.out.exists() and not s.out.is_dir():
        raise InputError(f"--out {s.out}: exists and is not a folder")
    if s.out.exists() and any(s.out.iterdir()):
        raise InputError(f"--out {s.out}: exists and is not empty")
    check_writable(s.out / "loop.json")
    resolve_checkpoint(s.run, None)  # The policy deploys: a damaged or NaN one fails now.
    return run


def _finetune(s: LoopSettings, run: Any, out: Path, physics: Path | None) -> dict:
    from humimic.tracking.train import train

    t0 = time.perf_counter()
    ts = TrainSettings(motion=s.motion or run.motion, out=out, robot=run.robot,
                       num_envs=s.num_envs or run.num_envs, max_iterations=s.iterations,
                       device=s.device,
                       dr=run.dr, physics=None if physics is None else str(physics),
                       init_from=s.run, variant=run.variant, seed=s.seed,
                       checkpoint_every=s.iterations, num_steps_per_env=run.num_steps_per_env,
                       max_minutes=s.max_minutes, quiet=s.quiet, task=run.task,
                       ppo=replace(run.ppo, learning_rate=s.learning_rate, schedule="fixed"))  # fmt: skip
    last = train(ts)
    return {"run": str(out), "physics": None if physics is None else str(physics),
            "seconds": time.perf_counter() - t0, "last": last}  # fmt: skip


def _summary(r: dict) -> dict:
    return {k: {m: r[k][m] for m in _METRICS} for k in ("policy", "open_loop")}


def loop(settings: LoopSettings) -> dict:
    """Run the loop; returns ``loop.json``'s content.

    The "real" robot is a physics file (:mod:`humimic.sim.physics`). Only the deploy stage
    (:func:`deploy`, :func:`deployment_session`, :func:`gantry_session`) reads it; the
    stages after it see what a team would have from a real robot: logs.

    1. **Deploy** the run's policy on the real robot: closed-loop metrics against the open
       loop (``before/eval.json``, ``before/eval.mcap``) and the first episode as a robot log
       in the real2sim format (``before/robot_log.mcap``, floating base).
    2. **The sysid log** (``--sysid-log``): by default a **deployment session**, the policy
       performing the clip on the real robot episode after episode (each from the
       training's reset noise), logged as a robot on the floor would log itself: joints,
       commands, IMU, motion capture (``deployment.mcap``, :func:`deployment_session`). Or a
       **gantry session** (``gantry``): the robot hangs in a gantry and follows multi-sine PD
       targets (``gantry.mcap``, the log ``humimic sysid simulate`` writes).
    3. **Sysid**: ``humimic sysid diagnose`` on that log (``sysid/``); its claimed effects
       become a physics file, ``corrected.yaml``.
    4. **Fine-tune** the policy in the corrected model, under the run's DR and PPO settings
       but at ``--learning-rate`` on a fixed schedule (``finetune/``);
       with ``--control``, also in the nominal model for the same iterations
       (``finetune_nominal/``), to tell the correction's gain from that of more training.
    5. **Redeploy** on the real robot (``after/``, ``after_nominal/``) and report before and
       after (``loop.json``, ``loop.md``).

    What can be checked comes before the first deployment (the settings, the physics file,
    the run's checkpoint, ``--out`` empty and outside the run); a loop that fails later
    removes what it wrote.
    """
    s = settings
    out = s.out
    created = not out.exists()
    run = _check(s)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(f"--out {out}: cannot create the folder: {e.strerror or e}") from None
    try:
        return _stages(s, run, out)
    except (Exception, KeyboardInterrupt):
        # A loop that fails takes away what it wrote: a folder it made, or what it put in
        # the empty one it was given.
        if created:
            shutil.rmtree(out, ignore_errors=True)
        else:
            for entry in out.iterdir():
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)
        raise


def _stages(s: LoopSettings, run: Any, out: Path) -> dict:
    """The loop's five stages into ``out`` (made, empty); returns ``loop.json``'s content."""
    from humimic.real2sim.report import run_diagnosis
    from humimic.sim.physics import write_physics

    t0 = time.perf_counter()
    report: dict[str, Any] = {"run": str(s.run), "motion": str(s.motion or run.motion),
                              "real": s.real, "iterations": s.iterations}  # fmt: skip

    print(f"[1/5] deploying {s.run} on the real robot")
    before = deploy(s, s.run, out / "before")
    report["before"] = _summary(before)
    if s.sysid_log == "gantry":
        print(f"[2/5] gantry session on the real robot ({s.sysid_duration:.0f} s)")
        sysid_log = gantry_session(s, run.robot, out / "gantry.mcap")
    else:
        print(f"[2/5] deployment session on the real robot (~{s.sysid_duration:.0f} s)")
        session = deployment_session(s, s.run, out / "deployment.mcap")
        report["deployment_log"] = session
        sysid_log = Path(session["log"])

    print(f"[3/5] sysid diagnose on the {s.sysid_log} log")
    diag = run_diagnosis(sysid_log, out / "sysid")
    corrected = diag.physics(name="corrected", robot=run.robot)
    write_physics(corrected, out / "corrected.yaml")
    report["sysid"] = {
        "log": s.sysid_log,
        "claimed": corrected.as_dict().get("effects", []),
        "kstep_rmse_mrad_before": 1e3 * diag.before_rad,
        "kstep_rmse_mrad_after": 1e3 * diag.after_rad,
        "unexplained": diag.unexplained,
        # Claims whose joints stay far above their noise floor (sysid/report.md): right but
        # incomplete, or stand-ins for an effect outside the vocabulary.
        "partial": [f"{e.effect} on {e.where}" for e in diag.claims if e.partial],
        "residual_model_used": False,  # The training model holds the effects alone.
        "not_identifiable": len(diag.not_identifiable),
        "seconds": diag.seconds,
    }

    print(f"[4/5] fine-tuning {s.iterations} iterations in the corrected model")
    report["finetune"] = _finetune(s, run, out / "finetune", out / "corrected.yaml")
    if s.control:
        print(f"      control: {s.iterations} iterations in the nominal model")
        report["finetune_nominal"] = _finetune(s, run, out / "finetune_nominal", None)

    print("[5/5] redeploying on the real robot")
    report["after"] = _summary(deploy(s, out / "finetune", out / "after"))
    if s.control:
        report["after_nominal"] = _summary(
            deploy(s, out / "finetune_nominal", out / "after_nominal")
        )
    report["seconds"] = time.perf_counter() - t0
    atomic_write_text(out / "loop.json", json.dumps(json_ready(report), indent=2) + "\n")
    atomic_write_text(out / "loop.md", _markdown(report))
    return report


def _done(finetune: dict) -> str:
    return str(finetune["last"].get("iteration", "?"))


def _markdown(r: dict) -> str:
    rows = [("before", r["before"]), ("after (corrected model)", r["after"])]
    if "after_nominal" in r:
        rows.append(("after (nominal model, control)", r["after_nominal"]))
    lines = [
        f"# humimic loop: {r['run']} on the real robot `{r['real']}`",
        "",
        f"Motion `{r['motion']}`. Fine-tuning: {_done(r['finetune'])} PPO iterations in the "
        "corrected model"
        + (
            f", {_done(r['finetune_nominal'])} in the nominal model (control)."
            if "finetune_nominal" in r
            else "."
        ),
        "",
        "| policy | success | mean steps | global MPJPE mm | root-relative MPJPE mm | joint error rad |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in rows:
        p = m["policy"]
        lines.append(f"| {name} | {100 * p['success_rate']:.0f}% | {p['mean_steps']:.1f} | "
                     f"{p['mpjpe_global_mm']:.1f} | {p['mpjpe_root_mm']:.1f} | "
                     f"{p['joint_error_rad']:.3f} |")  # fmt: skip
    o = r["before"]["open_loop"]
    lines.append(f"| open loop | {100 * o['success_rate']:.0f}% | {o['mean_steps']:.1f} | "
                 f"{o['mpjpe_global_mm']:.1f} | {o['mpjpe_root_mm']:.1f} | "
                 f"{o['joint_error_rad']:.3f} |")  # fmt: skip
    sy = r["sysid"]
    claimed = "\n".join(f"- `{e}`" for e in sy["claimed"]) or "- nothing claimed"
    lines += [
        "",
        f"## What sysid found ({sy.get('log', 'gantry')} log)",
        "",
        claimed,
        "",
        f"k-step prediction error on held-out data: {sy['kstep_rmse_mrad_before']:.2f} mrad "
        f"(nominal) -> {sy['kstep_rmse_mrad_after']:.2f} mrad (corrected); unexplained: "
        f"{sy['unexplained']}. Details: `sysid/report.md`.",
        "",
    ]
    if sy.get("partial"):
        lines += ["Partial explanations (their joints stay far above their noise floor): "
                  + "; ".join(sy["partial"]) + ".", ""]  # fmt: skip
    return "\n".join(lines)


__all__ = ["deploy", "deployment_session", "gantry_session", "loop"]
