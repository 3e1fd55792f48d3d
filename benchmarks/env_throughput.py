"""G1 tracking env throughput on the CPU against raw ``mujoco.rollout`` stepping of the same model.

For each env count, the env runs ``--steps`` policy steps (50 Hz, 4 physics steps each) with
random actions while the benchmark records, before every step, the physics state and the PD
targets of every env. Right after each env step, the baseline replays exactly that step's
physics with raw ``mujoco.rollout`` (one call from the recorded states and targets, same
models, same thread count, separate MjData): the same contacts, resets and DR models, with none
of the env's work (observations, rewards, terminations, resets, DR sampling, torch). Timing the
two step by step keeps drifts of the machine's speed out of the ratio. The ratio
``env / raw`` is the share of raw stepping throughput the env keeps; the issue's goal is 0.7.

A second baseline, ``raw_single_call``, runs all steps of the recorded start states in one
``mujoco.rollout`` call (no per-step return to Python at all; physics differs after resets,
so it is indicative only).

The env loop runs torch on one thread, as ``humimic train`` does while it collects rollouts
(``humimic.tracking.rsl.torch_threads``); ``env_torch_all_threads_steps_per_s`` is the same loop
with torch on all cores, for comparison.

``compiled_*``: the same measurement for the env with ``torch_compile=True`` (its tensor math
compiled by ``torch.compile``), alternating with the eager env repeat by repeat;
``compile_s`` is its construction time (compilation included; inductor caches it on disk).

Also reported: the ``threads`` stepping method (Python thread pool over ``mj_step``) for the
same env, to back the choice of ``rollout`` as the default.

Usage: .venv/bin/python benchmarks/env_throughput.py [--num-envs 64 256 1024] [--steps 100]
    [--dr default] [--repeats 3] [--no-threads] [--no-compile]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

from humimic.motion import motion_from_qpos
from humimic.sim.backend import MujocoCpuBackend
from humimic.tracking.config import g1_tracking
from humimic.tracking.env import TrackingEnv, tracking_model
from humimic.tracking.rsl import torch_threads


def arm_swing(model: mujoco.MjModel):
    """A 5 s reference: the home pose with the arms swinging (no data files needed)."""
    fps, T = 50.0, 250
    q = np.tile(model.key_qpos[0], (T, 1))
    for name, amp in (("left_shoulder_pitch_joint", 0.4), ("right_shoulder_pitch_joint", -0.4)):
        adr = model.jnt_qposadr[model.joint(name).id]
        q[:, adr] += amp * np.sin(2 * np.pi * np.arange(T) / fps)
    return motion_from_qpos(model, q, fps, "g1")


class _Interleaved:
    """Times each env step and, right after it, raw ``mujoco.rollout`` stepping of the same
    physics: the states and PD targets the env's backend started that step from, on the same
    models, with separate MjData. Interleaving step by step keeps drifts of the machine's speed
    out of the ratio."""

    def __init__(self, env: TrackingEnv) -> None:
        backend = env.backend
        assert isinstance(backend, MujocoCpuBackend)
        self.env, self.backend, self.decimation = env, backend, env.cfg.decimation
        n = backend.num_envs
        self.models = backend._models if backend._per_env else [backend._model] * n
        self.datas = [mujoco.MjData(backend._model) for _ in range(backend.nthread)]
        nstate = mujoco.mj_stateSize(backend._model, int(mujoco.mjtState.mjSTATE_FULLPHYSICS))
        self.out_state = np.zeros((n, self.decimation, nstate))
        self.out_sens = np.zeros((n, self.decimation, backend._model.nsensordata))
        self.ctrl_seq = np.zeros((n, self.decimation, backend.nu))
        self.rollout = mj_rollout.Rollout(nthread=backend.nthread)
        self.states: list[np.ndarray] = []
        self.ctrls: list[np.ndarray] = []
        self._step = backend.step
        backend.step = self._record  # type: ignore[method-assign]

    def _record(self, n_substeps: int) -> None:
        self.states.append(self.backend._state.copy())
        self.ctrls.append(self.backend._ctrl.copy())
        self._step(n_substeps)

    def raw_step(self, state: np.ndarray, ctrl: np.ndarray) -> None:
        self.ctrl_seq[:] = ctrl[:, None, :]
        self.rollout.rollout(
            self.models, self.datas, state, self.ctrl_seq,
            control_spec=int(mujoco.mjtState.mjSTATE_CTRL), skip_checks=True,
            nstep=self.decimation, state=self.out_state, sensordata=self.out_sens,
        )  # fmt: skip

    def rates(self, actions: list[torch.Tensor]) -> tuple[float, float]:
        """Env and raw steps per second over ``actions``, interleaved step by step."""
        t_env = t_raw = 0.0
        with torch.inference_mode(), torch_threads(1):  # As humimic's runner collects rollouts.
            for a in actions:
                t0 = time.perf_counter()
                self.env.step(a)
                t1 = time.perf_counter()
                self.raw_step(self.states[-1], self.ctrls[-1])
                t_raw += time.perf_counter() - t1
                t_env += t1 - t0
        steps = self.env.num_envs * len(actions)
        return steps / t_env, steps / t_raw

    def single_call_rate(self) -> float:
        """All recorded steps from the first recorded states in one rollout call."""
        n, d = self.backend.num_envs, self.decimation
        seq = np.repeat(np.stack(self.ctrls, axis=1), d, axis=1)
        nstep = seq.shape[1]
        big_state = np.zeros((n, nstep, self.out_state.shape[2]))
        big_sens = np.zeros((n, nstep, self.out_sens.shape[2]))
        t0 = time.perf_counter()
        self.rollout.rollout(
            self.models, self.datas, self.states[0], seq,
            control_spec=int(mujoco.mjtState.mjSTATE_CTRL), skip_checks=True, nstep=nstep,
            state=big_state, sensordata=big_sens,
        )  # fmt: skip
        return n * (nstep // d) / (time.perf_counter() - t0)

    def close(self) -> None:
        self.backend.step = self._step  # type: ignore[method-assign]
        self.rollout.close()


def _env_rate(env: TrackingEnv, actions: list[torch.Tensor]) -> float:
    with torch.inference_mode(), torch_threads(1):
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        return env.num_envs * len(actions) / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--dr", default="default")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-threads", action="store_true", help="skip the thread-pool method")
    parser.add_argument(
        "--no-compile", action="store_true", help="skip the env with torch.compile'd math"
    )
    args = parser.parse_args()
    out = {
        "benchmark": "env_throughput",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()},
        "torch_threads": torch.get_num_threads(),
        "mujoco": mujoco.__version__,
        "dr": args.dr,
        "steps": args.steps,
        "results": [],
    }
    model = tracking_model(g1_tracking("none"))
    motion = arm_swing(model)
    for n in args.num_envs:
        # A kinematic motion: the action base of the measurements before issue 25 (no LQR).
        cfg = replace(g1_tracking(args.dr), episode_length_s=1e3, action_base="default")
        gen = torch.Generator().manual_seed(0)
        actions = [0.3 * torch.randn(n, 29, generator=gen) for _ in range(args.steps)]
        envs = {"eager": TrackingEnv(cfg, motion, n, model=model)}
        compile_s = float("nan")
        if not args.no_compile:
            t0 = time.perf_counter()
            envs["compiled"] = TrackingEnv(replace(cfg, torch_compile=True), motion, n, model=model)
            compile_s = time.perf_counter() - t0
        for env in envs.values():
            with torch.inference_mode():
                for a in actions[:10]:  # Warm-up: leave the all-reset start.
                    env.step(a)
        rates: dict[str, dict[str, list[float]]] = {
            k: {"env": [], "raw": [], "single": [], "all_threads": []} for k in envs
        }
        for _ in range(args.repeats):  # The variants alternate: drifts hit both alike.
            for name, env in envs.items():
                r = rates[name]
                probe = _Interleaved(env)
                env_rate, raw_rate = probe.rates(actions)
                r["env"].append(env_rate)
                r["raw"].append(raw_rate)
                r["single"].append(probe.single_call_rate())
                probe.close()
                with torch.inference_mode():
                    t0 = time.perf_counter()
                    for a in actions:
                        env.step(a)
                    r["all_threads"].append(n * len(actions) / (time.perf_counter() - t0))
        for env in envs.values():
            env.close()
        r = rates["eager"]
        row = {
            "num_envs": n,
            "env_steps_per_s": float(np.median(r["env"])),
            "raw_rollout_steps_per_s": float(np.median(r["raw"])),
            "ratio": float(np.median(np.array(r["env"]) / np.array(r["raw"]))),
            "raw_single_call_steps_per_s": float(np.median(r["single"])),
            "physics_steps_per_s": float(np.median(r["env"])) * cfg.decimation,
            "env_torch_all_threads_steps_per_s": float(np.median(r["all_threads"])),
        }
        if "compiled" in rates:
            c = rates["compiled"]
            row |= {
                "compiled_env_steps_per_s": float(np.median(c["env"])),
                "compiled_raw_rollout_steps_per_s": float(np.median(c["raw"])),
                "compiled_ratio": float(np.median(np.array(c["env"]) / np.array(c["raw"]))),
                "compile_s": compile_s,
            }
        if not args.no_threads:
            env_t = TrackingEnv(replace(cfg, step_method="threads"), motion, n, model=model)
            with torch.inference_mode():
                for a in actions[:10]:
                    env_t.step(a)
            row["env_threads_steps_per_s"] = float(
                np.median([_env_rate(env_t, actions) for _ in range(args.repeats)])
            )
            env_t.close()
        out["results"].append(row)
        print(json.dumps(row), flush=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
