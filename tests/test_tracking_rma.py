"""Rapid Motor Adaptation: ``humimic train --variant rma`` and ``humimic distill --student rma``.

The models and the latent's regression on small fake observations; the commands on the G1 with
tiny budgets (8 envs, a few iterations of 8 steps): machinery, not what the policy learns.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from rsl_rl.modules import EmpiricalNormalization
from tensordict import TensorDict

from humimic.cli.main import main

GAUSS = {"class_name": "GaussianDistribution", "init_std": 0.1, "std_type": "scalar"}


def _train_args(motion: Path, out: Path, iterations: int, *extra: str) -> list[str]:
    return ["train", "--motion", str(motion), "--out", str(out), "--num-envs", "8",
            "--max-iterations", str(iterations), "--num-steps-per-env", "8", "--dr", "default",
            "--checkpoint-every", "1", "--task.action-base", "default", "--quiet",
            *extra]  # fmt: skip


def _obs(n: int, gen: torch.Generator) -> TensorDict:
    return TensorDict(
        {
            "policy": torch.randn(n, 6, generator=gen),
            "proprio_history": torch.randn(n, 12, generator=gen),
            "physics": torch.rand(n, 4, generator=gen) * 2 - 1,
        },
        batch_size=[n],
    )


def _actor(obs: TensorDict, seed: int = 0):
    from humimic.tracking.rma import RmaActor

    torch.manual_seed(seed)
    return RmaActor(obs, {"actor": ["policy", "physics"]}, "actor", 3, hidden_dims=[16],
                    obs_normalization=True, distribution_cfg=GAUSS, encoder_groups=["physics"],
                    latent_dim=2, encoder_hidden_dims=[8])  # fmt: skip


def _student(obs: TensorDict, seed: int = 1):
    from humimic.tracking.rma import RmaStudent

    torch.manual_seed(seed)
    return RmaStudent(obs, {"student": ["policy", "proprio_history"]}, "student", 3,
                      hidden_dims=[16], obs_normalization=True, distribution_cfg=GAUSS,
                      base_groups=["policy"], latent_dim=2,
                      adapter_hidden_dims=[32])  # fmt: skip


def _normalizer(m: torch.nn.Module) -> EmpiricalNormalization:
    assert isinstance(m, EmpiricalNormalization)
    return m


def test_rma_actor_reads_the_physics_only_through_its_latent() -> None:
    """The base policy's input is the normalized ``policy`` group and z (not e); e's that give
    the same z give the same action, and another z another action."""
    gen = torch.Generator().manual_seed(0)
    obs = _obs(5, gen)
    actor = _actor(obs)
    assert actor.mlp[0].in_features == 6 + 2
    assert _normalizer(actor.obs_normalizer).mean.shape == (6,)
    with torch.no_grad():
        first = actor.encoder[0]
        assert isinstance(first, torch.nn.Linear)
        first.weight[:, 1:] = 0.0  # z now depends on e[:, 0] alone.
        _normalizer(actor.obs_normalizer).update(obs["policy"] * 3 + 1)
        same = obs.clone()
        same["physics"][:, 1:] = torch.rand(5, 3, generator=gen) * 2 - 1
        other = obs.clone()
        other["physics"][:, 0] = -obs["physics"][:, 0]
        torch.testing.assert_close(actor.encode(same), actor.encode(obs))
        torch.testing.assert_close(actor(same), actor(obs))
        assert not torch.allclose(actor.encode(other), actor.encode(obs))
        assert (actor(other) - actor(obs)).abs().max() > 1e-4


def test_rma_distillation_regresses_the_student_latent_onto_the_teachers() -> None:
    """RMA's phase 2 on fake rollouts: loading a PPO checkpoint gives the student the teacher's
    base policy exactly; the update's ``latent`` loss is the MSE of phi(h) from the teacher's
    mu(e) on the stored states; it trains phi alone and lowers that MSE."""
    from rsl_rl.storage import RolloutStorage

    from humimic.tracking.rma import RmaDistillation

    gen = torch.Generator().manual_seed(2)
    n, steps = 16, 4
    obs = _obs(n, gen)
    teacher, student = _actor(obs, 0), _student(obs, 1)
    trained = _actor(obs, 5)  # The checkpoint's actor: other weights, other statistics.
    with torch.no_grad():
        _normalizer(trained.obs_normalizer).update(obs["policy"] * 2 - 1)
    storage = RolloutStorage("distillation", n, steps, obs, [3], "cpu")
    alg = RmaDistillation(student, teacher, storage, num_learning_epochs=1,
                          gradient_length=steps, learning_rate=1e-2)  # fmt: skip
    alg.load({"actor_state_dict": trained.state_dict(), "iter": 3}, None, True)
    for k, v in trained.state_dict().items():
        if k.startswith(("mlp.", "obs_normalizer.")):
            torch.testing.assert_close(student.state_dict()[k], v, rtol=0, atol=0)
    assert all(not p.requires_grad for p in student.mlp.parameters())
    params = {id(p) for g in alg.optimizer.param_groups for p in g["params"]}
    assert params == {id(p) for p in student.adapter.parameters()}

    batches = [_obs(n, gen) for _ in range(steps)]
    alg.train_mode()
    for b in batches:
        alg.act(b)
        alg.process_env_step(b, torch.zeros(n), torch.zeros(n, dtype=torch.long), {})

    def latent_mse() -> float:
        with torch.no_grad():
            return float(np.mean([torch.mean((student.adapt(b) - teacher.encode(b)) ** 2).item()
                                  for b in batches]))  # fmt: skip

    before = latent_mse()
    base = {k: v.clone() for k, v in student.state_dict().items() if k.startswith("mlp.")}
    adapter = {k: v.clone() for k, v in student.adapter.state_dict().items()}
    encoder = {k: v.clone() for k, v in teacher.state_dict().items()}
    losses = alg.update()
    assert losses["latent"] == pytest.approx(before, rel=1e-5)
    for k, v in base.items():
        torch.testing.assert_close(student.state_dict()[k], v, rtol=0, atol=0)
    for k, v in encoder.items():
        torch.testing.assert_close(teacher.state_dict()[k], v, rtol=0, atol=0)
    assert any(not torch.equal(student.adapter.state_dict()[k], v) for k, v in adapter.items())
    assert latent_mse() < before


def test_rma_student_onnx_matches_torch(tmp_path: Path) -> None:
    """The student's ONNX graph (adaptation module, then the base policy on its slice of the
    input) gives the torch student's deterministic actions."""
    from onnx.reference import ReferenceEvaluator

    from humimic.tracking.export import onnx_bytes

    gen = torch.Generator().manual_seed(3)
    obs = _obs(5, gen)
    student = _student(obs)
    with torch.no_grad():
        h = torch.cat([obs["policy"], obs["proprio_history"]], -1)
        _normalizer(student.adapter_normalizer).update(h)
        _normalizer(student.obs_normalizer).update(obs["policy"] * 2 + 1)
        want = student(obs).numpy()
    path = tmp_path / "s.onnx"
    path.write_bytes(onnx_bytes(student.as_onnx(verbose=False).eval()))
    x = torch.cat([obs["policy"], obs["proprio_history"]], dim=-1).numpy()
    (got,) = ReferenceEvaluator(str(path)).run(None, {"obs": x})
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-5)


def _column(run: Path, name: str) -> list[float]:
    with open(run / "progress.csv", newline="") as f:
        return [float(r[name]) for r in csv.DictReader(f)]


def test_rma_trains_distills_evaluates_and_exports(motion_file: Path, tmp_path: Path) -> None:
    """``--variant rma`` trains its encoder with PPO, resumes and evaluates but is neither
    exported nor deployed by the loop; ``distill --student rma`` keeps the teacher's base policy weight for weight,
    lowers the latent loss, resumes, and gives a student that evaluates and exports to an
    ONNX file that matches torch on the env's observations."""
    from onnx.reference import ReferenceEvaluator

    from humimic.tracking.export import load_policy_runner

    teacher = tmp_path / "rma"
    assert main(_train_args(motion_file, teacher, 2, "--variant", "rma")) == 0
    assert "variant: rma" in (teacher / "config.yaml").read_text()
    blobs = [torch.load(teacher / "checkpoints" / f"model_{i:06d}.pt", weights_only=True)
             for i in (1, 2)]  # fmt: skip
    actors = [b["actor_state_dict"] for b in blobs]
    assert actors[0]["mlp.0.weight"].shape[1] == 160 + 8  # policy and z, not e
    assert actors[0]["encoder.0.weight"].shape[1] > 8  # e
    # PPO's gradient reaches the encoder (its weights, with e varying under DR).
    assert not torch.equal(actors[0]["encoder.0.weight"], actors[1]["encoder.0.weight"])
    assert main(_train_args(motion_file, teacher, 3, "--variant", "rma", "--resume")) == 0
    assert main(["eval", str(teacher), "--episodes", "2"]) == 0
    assert main(["export", str(teacher), "--out", str(tmp_path / "t.onnx")]) == 2
    assert not (tmp_path / "t.onnx").exists()
    loop = ["loop", "--run", str(teacher), "--real", "worn_knees", "--out", str(tmp_path / "l")]
    assert main([*loop, "--quiet"]) == 2  # Not deployable: the loop refuses it too.
    assert not (tmp_path / "l").exists()

    # Distilled without DR: e = 0, so z is one constant, which a few updates learn (under DR a
    # tiny run's loss varies more from rollout to rollout than it falls; the regression
    # itself is tested above on fixed data).
    student = tmp_path / "student"
    args = ["distill", "--teacher", str(teacher), "--out", str(student), "--student", "rma",
            "--num-envs", "8", "--max-iterations", "10", "--checkpoint-every", "5",
            "--dr", "none", "--quiet"]  # fmt: skip
    assert main(args) == 0
    t_actor = torch.load(teacher / "checkpoints" / "model_000003.pt", weights_only=True)
    t_actor = t_actor["actor_state_dict"]
    s_blob = torch.load(student / "checkpoints" / "model_000010.pt", weights_only=True)
    base = [k for k in t_actor if k.startswith(("mlp.", "obs_normalizer."))]
    assert base
    for k in base:
        torch.testing.assert_close(s_blob["student_state_dict"][k], t_actor[k], rtol=0, atol=0)
    for k, v in t_actor.items():
        torch.testing.assert_close(s_blob["teacher_state_dict"][k], v, rtol=0, atol=0)
    assert s_blob["student_state_dict"]["adapter.0.weight"].shape[1] == 160 + 5 * 160
    latent = _column(student, "loss_latent")
    assert len(latent) == 10 and len(_column(student, "loss_behavior")) == 10
    assert np.mean(latent[-3:]) < 0.8 * np.mean(latent[:3])
    resumed = [*args, "--resume"]
    resumed[resumed.index("--max-iterations") + 1] = "11"
    assert main(resumed) == 0
    s_blob = torch.load(student / "checkpoints" / "model_000011.pt", weights_only=True)
    for k in base:
        torch.testing.assert_close(s_blob["student_state_dict"][k], t_actor[k], rtol=0, atol=0)
    assert main(["eval", str(student), "--episodes", "2"]) == 0

    path = tmp_path / "s.onnx"
    assert main(["export", str(student), "--out", str(path)]) == 0
    runner, env, _ = load_policy_runner(student, None)
    try:
        policy = runner.get_inference_policy(device="cpu")
        obs = env.get_observations().expand(4).clone()
        gen = torch.Generator().manual_seed(0)
        for g in ("policy", "proprio_history"):
            obs[g] = obs[g] + 0.1 * torch.randn(obs[g].shape, generator=gen)
        with torch.inference_mode():
            want = policy(obs).numpy()
    finally:
        env.close()
    x = torch.cat([obs["policy"], obs["proprio_history"]], dim=-1).numpy()
    (got,) = ReferenceEvaluator(str(path)).run(None, {"obs": x})
    assert np.asarray(got).shape == want.shape == (4, 29)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-5)


def test_rma_student_needs_an_rma_teacher(
    motion_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--student rma`` under a teacher of another variant: exit 2, naming the flag and the
    variant, nothing written."""
    from humimic.errors import InputError
    from humimic.tracking.distill import DistillConfig, distill_cfg
    from humimic.tracking.rsl import tracking_ppo, train_cfg

    with pytest.raises(InputError, match="--student rma"):
        distill_cfg(train_cfg(tracking_ppo("teacher")), "rma", DistillConfig())
    assert distill_cfg(train_cfg(tracking_ppo("rma")), "rma", DistillConfig())["student"]
    teacher = tmp_path / "teacher"
    assert main(_train_args(motion_file, teacher, 1, "--variant", "teacher")) == 0
    bad = tmp_path / "bad"
    assert main(_train_args(motion_file, bad, 1, "--variant", "rma", "--ppo.rma-latent-dim",
                            "0")) == 2  # fmt: skip
    assert not bad.exists()
    capsys.readouterr()
    out = tmp_path / "student"
    args = ["distill", "--teacher", str(teacher), "--out", str(out), "--student", "rma",
            "--num-envs", "8", "--quiet"]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--student rma" in err and "--variant teacher" in err, err
    assert not out.exists()
