"""``humimic eval``: closed-loop evaluation of a tracking policy, and the open-loop baseline.

:func:`evaluate` runs the command (:func:`run_evaluation` measures, :func:`write_eval_mcap`
writes the rollouts for ``humimic view``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from humimic.configs.jobs import EvalSettings
from humimic.errors import InputError
from humimic.io import atomic_write_text, check_not_input, check_writable, json_ready
from humimic.motion import Motion
from humimic.sim.randomization import param_layout
from humimic.tracking.actions import stored_targets
from humimic.tracking.config import AdaptiveSampling, ResetNoise
from humimic.tracking.curve import plot_failures
from humimic.tracking.protocols import ClipTrace, judge, play_clip, summarize


@dataclass
class _Trace:
    """What one env (``env``) did, step by step, while its first episode lived."""

    qpos: list[np.ndarray] = field(default_factory=list)
    qvel: list[np.ndarray] = field(default_factory=list)
    targets: list[np.ndarray] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    env: int = 0

    def add(self, state: Any, targets: torch.Tensor, reward: float) -> None:
        """One step: ``state`` the backend's read-out, ``targets`` every env's PD targets."""
        self.qpos.append(np.array(state.qpos[self.env]))
        self.qvel.append(np.array(state.qvel[self.env]))
        self.targets.append(targets[self.env].double().cpu().numpy())
        self.reward.append(reward)


def _episodes(
    env: Any,
    act: Any,
    episodes: int,
    traces: Sequence[_Trace] = (),
    record: dict[str, np.ndarray] | None = None,
) -> dict:
    """Run one episode per env; returns the metrics. Each of ``traces`` records its env;
    ``record`` gets each episode's physics (``physics_e``, the normalized DR parameters ``e`` it ran
    under, :func:`~humimic.sim.randomization.param_layout`) and whether it ``failed``.

    An episode succeeds if no tracking failure (a termination other than the clip's end)
    happens. Errors are averaged over the steps each episode lived:

    * global MPJPE: tracked bodies' world positions against the reference [mm];
    * root-relative MPJPE: the same after subtracting each side's root position [mm];
    * joint error: mean absolute joint position error [rad];
    * per-body global errors [mm];
    * ``fail_steps``: the steps each failed episode lived, sorted (where in the clip they
      fell).
    """
    s, dev = env.state, env.device
    n = env.num_envs
    alive = torch.ones(n, dtype=torch.bool, device=dev)
    failed = torch.zeros(n, dtype=torch.bool, device=dev)
    steps = torch.zeros(n, device=dev)
    glob = torch.zeros(n, device=dev)
    root = torch.zeros(n, device=dev)
    joint = torch.zeros(n, device=dev)
    per_body = torch.zeros(n, len(s.body_names), device=dev)
    from humimic.tracking.rsl import torch_threads

    obs = env.get_observations()
    e0 = env.physics_params.clone()  # Each env plays one episode: the draw of its reset.
    if traces:
        state = env.backend.read()
        for tr in traces:
            tr.add(state, env.joint_targets, 0.0)
    threads = 1 if dev.type == "cpu" else torch.get_num_threads()  # As in training rollouts.
    with torch.inference_mode(), torch_threads(threads):
        while bool(alive.any()):
            obs, rew, dones, extras = env.step(act(obs))
            live = alive & ~dones  # Done envs were reset inside step: their state is new.
            if traces:
                state = env.backend.read()  # Once for every traced env.
                for tr in traces:
                    if bool(live[tr.env]):
                        tr.add(state, env.joint_targets, float(rew[tr.env]))
            err = (s.body_pos_w - s.ref_body_pos_w).norm(dim=-1)  # (n, B)
            r = s.root_index
            rel = (s.body_pos_w - s.body_pos_w[:, r : r + 1]) - (
                s.ref_body_pos_w - s.ref_body_pos_w[:, r : r + 1]
            )
            w = live.float()
            steps += w
            glob += w * err.mean(dim=1)
            root += w * rel.norm(dim=-1).mean(dim=1)
            joint += w * (s.joint_pos - s.ref_joint_pos).abs().mean(dim=1)
            per_body += w[:, None] * err
            failed |= alive & dones & ~extras["time_outs"].to(dev)
            alive &= ~dones
    k = torch.arange(n, device=dev) < episodes
    st = steps.clamp(min=1)[k]
    if record is not None:
        record["physics_e"] = e0[k].cpu().numpy()
        record["failed"] = failed[k].cpu().numpy()
    fail_steps = steps[k][failed[k]].long().sort().values.tolist()
    return {
        "episodes": int(k.sum()),
        "success_rate": float((~failed[k]).float().mean()),
        "fail_steps": fail_steps,
        "mean_steps": float(steps[k].mean()),
        "mpjpe_global_mm": float((glob[k] / st).mean() * 1e3),
        "mpjpe_root_mm": float((root[k] / st).mean() * 1e3),
        "joint_error_rad": float((joint[k] / st).mean()),
        "per_body_mm": {
            b: float((per_body[k, i] / st).mean() * 1e3) for i, b in enumerate(s.body_names)
        },
    }


@dataclass(frozen=True)
class Evaluation:
    """What :func:`run_evaluation` measured: the metrics and the first episodes' traces."""

    results: dict
    policy: _Trace
    open_loop: _Trace
    joint_names: tuple[str, ...]
    motion: Any
    step_dt: float
    episodes: dict[str, np.ndarray] = field(default_factory=dict)
    """The policy's episodes: ``physics_e`` (episodes, D) and ``failed`` (episodes,)."""
    param_layout: dict[str, slice] = field(default_factory=dict)
    """Where each DR quantity lies in ``physics_e``
    (:func:`~humimic.sim.randomization.param_layout`)."""
    policy_traces: list[_Trace] = field(default_factory=list)
    """The first ``traces`` policy episodes (:func:`run_evaluation`); ``policy`` is the
    first."""
    protocol_play: ClipTrace | None = None
    """The deterministic play the protocols judged (:mod:`.protocols`), if they ran."""


def eval_inputs(s: EvalSettings) -> dict[str, Any]:
    """What an evaluation reads (label -> path): no output of it may overwrite one."""
    from humimic.sim.randomization import DR_PROFILES
    from humimic.tracking.runs import read_run_settings, run_files

    run = read_run_settings(s.run)
    inputs: dict[str, Any] = {**run_files(s.run), "--checkpoint": s.checkpoint}
    inputs["the motion"] = s.motion if s.motion is not None else run.motion
    if s.dr not in DR_PROFILES:
        inputs["--dr"] = s.dr
    if s.physics is not None and Path(s.physics).is_file():
        inputs["--physics"] = s.physics
    return inputs


def evaluate(settings: EvalSettings) -> dict:
    """Evaluate a run's policy and the open-loop baseline; write JSON and MCAP if asked, and
    beside the JSON a picture of where in each clip the policy's episodes fail
    (``<out>_failures.png``, :func:`~humimic.tracking.curve.plot_failures`).

    ``--physics FILE`` evaluates on a fixed robot (a physics file, :mod:`humimic.sim.physics`):
    a "real" robot that training never saw. The first episode of both is written as MCAP with
    the reference (``--mcap``, :func:`write_eval_mcap`).

    Raises:
        InputError: Bad settings, or an output that would overwrite an input (the run's
            files, the motion, a checkpoint) or the other output; nothing is written.
    """
    s = settings
    s.validate()
    mcap = s.mcap if s.mcap is not None else (s.out.with_suffix(".mcap") if s.out else None)
    if mcap is not None and mcap.suffix != ".mcap":
        raise InputError(f"--mcap {mcap}: the file must end in .mcap")
    inputs = eval_inputs(s) if s.out is not None or mcap is not None else {}
    if inputs:
        check_not_input(s.out, inputs, "--out")
        flag = "--mcap" if s.mcap is not None else "--mcap (from --out)"
        check_not_input(mcap, {**inputs, "--out": s.out}, flag)
    png = None if s.out is None else s.out.with_name(f"{s.out.stem}_failures.png")
    if s.out is not None and png is not None:
        check_writable(s.out)
        others = {"--out": s.out} if mcap is None else {"--out": s.out, "--mcap": mcap}
        check_not_input(png, {**inputs, **others}, "--out's picture")
        check_writable(png)
    if mcap is not None:
        check_writable(mcap)
    clips = library_clips(s)
    if clips is not None:
        results, _ = evaluate_library(s, clips, mcap)
    else:
        ev = run_evaluation(s)
        results = ev.results
        if mcap is not None:
            write_eval_mcap(mcap, ev.motion, ev.joint_names, ev.step_dt, ev.policy,
                            ev.open_loop, results)  # fmt: skip
            results["mcap"] = str(mcap)
    if s.out is not None and png is not None:
        plot_failures(failure_table(results), results["step_dt"], png,
                      f"{Path(results['run']).name}: DR {results['dr']}")  # fmt: skip
        results["failures_png"] = str(png)
        atomic_write_text(s.out, json.dumps(json_ready(results), indent=2) + "\n")
    return results


def failure_table(results: dict[str, Any]) -> dict[str, tuple[int, list[int], int]]:
    """Clip -> (its frames, the steps its failed policy episodes lived, its episodes) of an
    evaluation's results (one clip or a library)."""
    clips = results.get("clips") or {Path(results["motion"]).name: results}
    return {name: (c["frames"], c["policy"]["fail_steps"], c["policy"]["episodes"])
            for name, c in clips.items()}  # fmt: skip


def run_evaluation(
    settings: EvalSettings, *, open_loop: bool = True, traces: int = 1, protocols: bool = True
) -> Evaluation:
    """Run the policy and, if ``open_loop``, the open loop, and if ``protocols``, the field's
    protocols (:mod:`.protocols`; ``results["protocols"]``); writes nothing.

    ``traces``: how many of the policy's episodes to record step by step (at most
    ``episodes``).

    Every episode plays the whole clip from its first frame (``--start-noise``: from the
    training's reset noise about it, a shove at the start), under the
    physics of the chosen DR profile (``none``: the nominal robot) and the physics file, if
    any; the metrics are those of :func:`_episodes`. The open-loop baseline replays the
    reference's joint positions as PD targets (no policy; a refined motion's stored controls,
    :func:`~humimic.tracking.actions.stored_targets`): how far the raw reference gets on this robot and these physics.
    """
    from humimic.tracking.env import TrackingEnv
    from humimic.tracking.rsl import make_runner
    from humimic.tracking.runs import load_weights, resolve_checkpoint, run_config, run_rsl_cfg

    s = settings
    s.validate()
    recorded = run_config(s.run)
    path, blob = resolve_checkpoint(s.run, s.checkpoint)
    task, motion, motion_path = _eval_task(s, recorded)
    n = s.num_envs or s.episodes
    results: dict[str, Any] = {"run": str(s.run), "checkpoint": str(path),
                               "iterations": int(blob["iter"]), "dr": s.dr,
                               "motion": str(motion_path), "frames": motion.num_frames,
                               "step_dt": task.step_dt, "start_noise": s.start_noise}  # fmt: skip
    if task.physics is not None:
        results["physics"] = {"name": task.physics.name, **task.physics.as_dict()}

    torch.manual_seed(s.seed)
    env = TrackingEnv(task, motion, n, device=s.device)
    try:
        runner = make_runner(env, run_rsl_cfg(s.run, recorded), log_dir=None, device=s.device)
        load_weights(runner, blob, path, "--checkpoint" if s.checkpoint else "checkpoint")
        policy = runner.get_inference_policy(device=s.device)
        policy_traces = [_Trace(env=k) for k in range(max(1, min(traces, s.episodes)))]
        record: dict[str, np.ndarray] = {}
        results["policy"] = _episodes(env, policy, s.episodes, policy_traces, record)
        joint_names = env.joint_names
        layout = param_layout(env.backend.num_bodies_total, len(joint_names))
    finally:
        env.close()
    open_trace = _Trace()
    if open_loop:
        env = TrackingEnv(task, motion, n, device=s.device)
        results |= _open_loop(env, motion, s.episodes, open_trace)
    played = _play_protocols(s, recorded, policy, (motion, motion_path)) if protocols else None
    if played is not None:
        results["protocols"] = summarize({motion_path.name: judge(played)})
    return Evaluation(results, policy_traces[0], open_trace, joint_names, motion, task.step_dt,
                      record, layout, policy_traces, played)  # fmt: skip


def _play_protocols(
    s: EvalSettings, recorded: tuple[dict[str, Any], Any], policy: Any,
    loaded: tuple[Motion, Path],
) -> ClipTrace:  # fmt: skip
    """One deterministic play of the clip (``loaded``: the evaluation's reference and its file)
    on the nominal robot (or the physics file), no DR, no start noise, no failure terminations:
    what the protocols of :mod:`.protocols` judge."""
    from humimic.tracking.env import TrackingEnv

    task, motion, _ = _eval_task(replace(s, dr="none", start_noise=False), recorded, loaded)
    task = replace(task, terminations={k: v for k, v in task.terminations.items() if v.time_out})
    env = TrackingEnv(task, motion, 1, device=s.device)
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()  # A recurrent policy's state, sized for the evaluation's envs, starts anew.
    try:
        return play_clip(env, policy)
    finally:
        env.close()


def library_clips(s: EvalSettings) -> list[Path] | None:
    """The clips of a library evaluation, one after the other: ``--motion`` when it names a
    library, else the run's motion when it is one (checked unchanged since the run began);
    ``None`` for one clip."""
    from humimic.tracking.runs import read_run_settings, recorded_motion
    from humimic.tracking.task import is_library, library_files

    path = s.motion if s.motion is not None else read_run_settings(s.run).motion
    if not is_library(path):
        return None  # One clip: checked where it is read (_eval_task).
    return library_files(recorded_motion(s.run) if s.motion is None else path)


def evaluate_library(
    s: EvalSettings, clips: list[Path], mcap: Path | None = None, *, protocols: bool = True
) -> tuple[dict[str, Any], list[Evaluation]]:
    """Every clip of a library evaluated as one clip is (``--episodes`` each, the same seed;
    the field's protocols if ``protocols``), with each clip's MCAP beside ``mcap``
    (``<stem>_<clip>.mcap``). Returns the results (the run's fields, ``clips``: name -> its
    frames and metrics, ``policy`` and ``open_loop``: the mean over the clips of each metric,
    ``protocols``: per clip and in total) and each clip's :class:`Evaluation`."""
    mcaps = [None if mcap is None else mcap.with_name(f"{mcap.stem}_{f.stem}.mcap")
             for f in clips]  # fmt: skip
    inputs = eval_inputs(s)
    for path in mcaps:
        if path is not None:
            check_not_input(path, inputs, "--mcap")
            check_writable(path)
    # Every clip evaluated before anything is written: a clip that fails leaves no file.
    evs = [run_evaluation(replace(s, motion=f), protocols=protocols) for f in clips]
    per_clip: dict[str, dict[str, Any]] = {}
    for f, ev, path in zip(clips, evs, mcaps, strict=True):
        r = ev.results
        entry = {k: r[k] for k in ("frames", "policy", "open_loop", "open_loop_targets") if k in r}
        if path is not None:
            write_eval_mcap(path, ev.motion, ev.joint_names, ev.step_dt, ev.policy,
                            ev.open_loop, r)  # fmt: skip
            entry["mcap"] = str(path)
        per_clip[f.name] = entry
    first = evs[0].results
    motion = s.motion if s.motion is not None else first["motion"]
    out = {k: first[k] for k in ("run", "checkpoint", "iterations", "dr", "step_dt",
                                 "start_noise", "physics") if k in first}  # fmt: skip
    out |= {"motion": str(motion), "clips": per_clip}
    for group in ("policy", "open_loop"):
        out[group] = _mean_over_clips([c[group] for c in per_clip.values()])
    if all("protocols" in ev.results for ev in evs):
        out["protocols"] = summarize({
            f.name: {p: ev.results["protocols"][p]["per_clip"][f.name] for p in ("beyondmimic", "phc")}
            for f, ev in zip(clips, evs, strict=True)
        })  # fmt: skip
    return out, evs


def _mean_over_clips(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Each metric's mean over the clips (a table of them, e.g. per body, entry by entry);
    ``episodes`` summed."""
    out: dict[str, Any] = {}
    for k, v in rows[0].items():
        if k == "episodes":
            out[k] = int(sum(r[k] for r in rows))
        elif isinstance(v, dict):
            out[k] = _mean_over_clips([r[k] for r in rows])
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[k] = float(np.mean([r[k] for r in rows]))
    return out


def _eval_task(
    s: EvalSettings, recorded: tuple[dict[str, Any], Any],
    loaded: tuple[Motion, Path] | None = None,
) -> tuple[Any, Motion, Path]:  # fmt: skip
    """The task an evaluation runs (the run's, under the chosen DR and physics, every episode
    from the clip's first frame, with the training's reset noise only for ``--start-noise``,
    no adaptive sampling, long enough for the whole clip), the reference and its file
    (``loaded`` when the caller has read them already, else read and checked here)."""
    from humimic.tracking.runs import recorded_motion
    from humimic.tracking.task import load_reference, task_config

    run = recorded[1]
    base = task_config(run.robot, s.dr, s.seed, s.physics, run.task)
    if loaded is not None:
        motion, motion_path = loaded
    else:
        if s.motion is None:
            motion_path = recorded_motion(s.run, recorded)  # There, unchanged since then.
        elif not s.motion.is_file():
            raise InputError(f"--motion {s.motion}: no such file")
        else:
            motion_path = s.motion
        motion = load_reference(motion_path, run.robot, 1.0 / base.step_dt)
    task = replace(
        base,
        start_frame=0,
        reset=base.reset if s.start_noise else
        ResetNoise(pose=((0.0, 0.0),) * 6, velocity=((0.0, 0.0),) * 6,  # type: ignore[arg-type]
                   joint_pos=(0.0, 0.0)),
        adaptive=AdaptiveSampling(enabled=False),
        episode_length_s=motion.num_frames * base.step_dt + 1.0,
    )  # fmt: skip
    return task, motion, motion_path


def _open_loop(env: Any, motion: Motion, episodes: int, trace: _Trace) -> dict[str, Any]:
    """The open loop's episodes on ``env`` (closed after): a refined motion (humimic refine)
    stores the PD targets that replay it, one per control step, held over its physics steps;
    a kinematic reference's open loop is its next frame's joint positions."""
    try:
        st, task = env.state, env.cfg
        targets = stored_targets(motion, task.sim_dt, task.decimation)
        out: dict[str, Any] = {}
        if targets is None:
            targets = env.reference_joint_pos[1:]
            out["open_loop_targets"] = "reference joint positions"
        else:
            targets = torch.as_tensor(targets, dtype=torch.float32, device=env.device)
            out["open_loop_targets"] = "stored dynamic controls"

        def replay(obs: Any) -> torch.Tensor:
            del obs
            k = st.frame.clamp(max=len(targets) - 1)
            return env.action_for_targets(targets[k])

        out["open_loop"] = _episodes(env, replay, episodes, [trace])
        return out
    finally:
        env.close()


def write_eval_mcap(
    path: Path,
    motion: Any,
    joint_names: tuple[str, ...],
    step_dt: float,
    policy: _Trace,
    open_loop: _Trace,
    results: dict,
) -> None:
    """Write the reference and the first episode's rollouts as MCAP.

    The file holds the reference topics of :func:`humimic.formats.mcap.write_motion_topics`,
    the policy's rollout on ``/qpos``, ``/joint_states``, ``/joint_commands`` (PD targets) and
    ``/reward_terms`` (the step's total reward), the open-loop rollout on ``/open_loop/qpos``,
    and the metrics as metadata ``eval``. ``humimic view EVAL.mcap`` plays the rollout against
    the reference.
    """
    from humimic.formats.mcap import McapWriter, stamp, write_motion_topics

    names = list(joint_names)
    with McapWriter(path) as w:
        write_motion_topics(w, motion)
        w.add_metadata("eval", {"results": json.dumps(json_ready(results))})
        for k in range(len(policy.qpos)):
            t = round(k * step_dt * 1e9)
            header = {"stamp": stamp(t), "frame_id": "world"}
            w.write("/qpos", t, {"header": header, "qpos": policy.qpos[k].tolist()})
            w.write("/joint_states", t, {"header": header, "name": names,
                                         "position": policy.qpos[k][7:].tolist(),
                                         "velocity": policy.qvel[k][6:].tolist()})  # fmt: skip
            w.write("/joint_commands", t, {"header": header, "name": names,
                                           "position": policy.targets[k].tolist()})  # fmt: skip
            w.write("/reward_terms", t, {"header": header, "terms": {"total": policy.reward[k]}})
        for k in range(len(open_loop.qpos)):
            t = round(k * step_dt * 1e9)
            w.write("/open_loop/qpos", t,
                    {"header": {"stamp": stamp(t), "frame_id": "world"},
                     "qpos": open_loop.qpos[k].tolist()},
                    schema="humimic.Qpos")  # fmt: skip


__all__ = [
    "Evaluation",
    "evaluate",
    "evaluate_library",
    "failure_table",
    "library_clips",
    "run_evaluation",
    "write_eval_mcap",
]
