"""Physics files: parsing, what they change in the training model, delays across steps."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np
import pytest

from humimic.errors import InputError
from humimic.sim.backend import MujocoCpuBackend
from humimic.sim.physics import SHIPPED, load_physics, parse_physics, write_physics
from humimic.tracking.config import g1_tracking
from humimic.tracking.env import tracking_backend, tracking_model


@pytest.fixture(scope="module")
def nominal() -> mujoco.MjModel:
    return tracking_model(g1_tracking("none"))


def test_shipped_files_load_and_compile() -> None:
    for name in SHIPPED:
        ph = load_physics(name)
        assert ph.name == name and ph.description and ph.robot == "g1" and ph.effects
        model = tracking_model(replace(g1_tracking("none"), physics=ph))
        assert model.nu == 29


def test_every_change_reaches_the_model(nominal: mujoco.MjModel, tmp_path: Path) -> None:
    data = {
        "floor_friction": 0.4,
        "mass_scale": {"pelvis": 1.2},
        "com_offset": {"torso_link": [0.01, -0.02, 0.03]},
        "kp_scale": 0.8,
        "kd_scale": {"left_knee_joint": 1.5},
        "armature_scale": 2.0,
        "effects": ["coulomb_friction:right_knee_joint=2.5", "payload_mass:torso_link=3"],
    }
    ph = parse_physics(data, "test", "test")
    m = tracking_model(replace(g1_tracking("none"), physics=ph))
    n = nominal
    colliders = np.flatnonzero((n.geom_contype | n.geom_conaffinity) != 0)
    np.testing.assert_allclose(m.geom_friction[colliders, 0], 0.4)
    pelvis, torso = n.body("pelvis").id, n.body("torso_link").id
    assert m.body_mass[pelvis] == pytest.approx(1.2 * n.body_mass[pelvis])
    np.testing.assert_allclose(m.body_inertia[pelvis], 1.2 * n.body_inertia[pelvis], rtol=1e-9)
    assert m.body_mass[torso] == pytest.approx(n.body_mass[torso] + 3.0)
    np.testing.assert_allclose(m.body_ipos[torso] - n.body_ipos[torso], [0.01, -0.02, 0.03])
    np.testing.assert_allclose(m.actuator_gainprm[:, 0], 0.8 * n.actuator_gainprm[:, 0])
    np.testing.assert_allclose(m.actuator_biasprm[:, 1], 0.8 * n.actuator_biasprm[:, 1])
    knee = next(a for a in range(n.nu) if n.actuator(a).name.startswith("left_knee"))
    kd = m.actuator_biasprm[:, 2] / n.actuator_biasprm[:, 2]
    assert kd[knee] == pytest.approx(1.5) and np.delete(kd, knee) == pytest.approx(1.0)
    hinges = np.arange(6, n.nv)
    np.testing.assert_allclose(m.dof_armature[hinges], 2.0 * n.dof_armature[hinges])
    rk = m.jnt_dofadr[m.joint("right_knee_joint").id]
    assert m.dof_frictionloss[rk] == pytest.approx(n.dof_frictionloss[rk] + 2.5)
    # Written and read back: the same physics.
    path = write_physics(ph, tmp_path / "p.yaml")
    assert load_physics(path).as_dict() == ph.as_dict()


def test_dr_varies_a_physics_files_friction_instead_of_replacing_it(
    nominal: mujoco.MjModel,
) -> None:
    """DR draws a friction for the robot's own colliders (the G1's foot spheres 0.6, its other
    colliders and the floor 1.0); on a physics file whose floor is slippery, the same draw is
    scaled by the file's change, so the file's floor stays under DR (it used to be replaced
    by the draw). Without a file the draw is set as before."""
    cfg = g1_tracking("default")
    colliders = np.flatnonzero((nominal.geom_contype | nominal.geom_conaffinity) != 0)
    feet = colliders[nominal.geom_priority[colliders] > 0]
    for physics, expect_feet, expect_rest in ((None, 0.9, 0.9), ({"floor_friction": 0.3},
                                              0.9 * 0.3 / 0.6, 0.9 * 0.3 / 1.0)):  # fmt: skip
        c = cfg if physics is None else replace(cfg, physics=parse_physics(physics, "t", "t"))
        backend = tracking_backend(c, 2)
        assert isinstance(backend, MujocoCpuBackend)
        params = backend.nominal_params(2)
        params = replace(params, friction=np.array([0.9, 0.45]))
        backend.set_params(np.arange(2), params)
        m = backend.model_of(0)
        assert feet.size == 8
        np.testing.assert_allclose(m.geom_friction[feet, 0], expect_feet)
        np.testing.assert_allclose(np.delete(m.geom_friction[colliders, 0],
                                             np.searchsorted(colliders, feet)), expect_rest)  # fmt: skip
        np.testing.assert_allclose(backend.model_of(1).geom_friction[feet, 0], expect_feet / 2)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"gravity": 1}, "unknown field 'gravity'"),
        ({"kp_scale": -1}, "must be positive"),
        ({"kp_scale": {"no_joint": 1.1}}, "no actuated joint 'no_joint'"),
        ({"floor_friction": "slippery"}, "expected a number"),
        ({"com_offset": {"torso_link": [0, 0]}}, "expected [x, y, z]"),
        ({"effects": ["rust:left_knee_joint=1"]}, "unknown effect 'rust'"),
        ({"effects": ["payload_mass:no_body=1"]}, "no body 'no_body'"),
        ({"robot": "t1"}, "written for 't1', not 'g1'"),
        ({"kp_scale": {"*": 0.9, "left_knee_joint": 1.1}}, "or name them, not both"),
    ],
)
def test_bad_files_are_refused(data: dict, message: str) -> None:
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        tracking_model(replace(g1_tracking("none"), physics=parse_physics(data, "bad", "bad")))


def test_a_dr_draw_as_a_delta_builds_the_models_the_batched_path_sets(
    nominal: mujoco.MjModel,
) -> None:
    """Two renderings of the same draws, computed apart: the backends write the DR fields into
    copies of the compiled model (arrays, ``ModelLayout.fields``), a delta edits the spec that
    MuJoCo then compiles. Both give the same model, constants derived from the inertia too."""
    from humimic.robots.registry import get_robot
    from humimic.sim.models import training_model
    from humimic.sim.params import ModelLayout, physics_copies
    from humimic.sim.randomization import dr_profile, sample

    setup = g1_tracking("none").sim_setup()
    layout = ModelLayout.of(nominal, setup.body_names, setup.contact_body_names, setup.feet,
                            com_body=setup.com_body)  # fmt: skip
    dr = replace(dr_profile("wide"), kp_scale=(0.7, 1.3), armature_scale=(0.5, 2.0))
    draws = sample(dr, 2, num_bodies=len(layout.robot_bodies), num_joints=nominal.nu,
                   rng=np.random.default_rng(3), com_column=layout.com_column).physics  # fmt: skip
    for k, batched in enumerate(physics_copies(nominal, layout, draws)):
        delta = layout.delta(draws, k, nominal)
        assert len(delta.items) == 1 + len(layout.robot_bodies) + 1 + 3 * nominal.nu
        spec_built = training_model(get_robot("g1"), body_names=setup.body_names,
                                    contact_body_names=setup.contact_body_names,
                                    foot_body_names=setup.feet, edit=delta.on_spec)  # fmt: skip
        assert not np.array_equal(batched.body_mass, nominal.body_mass)
        for name in ("geom_friction", "body_mass", "body_inertia", "body_ipos", "actuator_gainprm",
                     "actuator_biasprm", "dof_armature", "dof_invweight0", "body_invweight0",
                     "actuator_acc0", "body_subtreemass"):  # fmt: skip
            np.testing.assert_allclose(getattr(spec_built, name), getattr(batched, name),
                                       rtol=1e-9, atol=1e-12, err_msg=name)  # fmt: skip


def test_missing_file_names_the_shipped_ones() -> None:
    with pytest.raises(InputError, match=r"not a shipped one .*worn_knees"):
        load_physics("no_such_physics.yaml")


@pytest.mark.parametrize("method", ["rollout", "threads"])
def test_transport_delay_starts_full_of_the_first_command_and_survives_steps(
    nominal: mujoco.MjModel, method: Literal["rollout", "threads"]
) -> None:
    """A 30 ms delay on the left knee. After a reset the delay line holds the first command
    (a controller had been sending it: no sag towards the joint angles), and a change of
    command 10 ms later reaches the drive 30 ms after it was sent, across several stepping
    calls and a push (the delay line is part of each env's state); without the delay the knee
    follows the change at once."""
    ph = parse_physics({"effects": ["delay:left_knee_joint=0.03"]}, "delay", "delay")
    delayed = tracking_model(replace(g1_tracking("none"), physics=ph))
    knee = delayed.jnt_qposadr[delayed.joint("left_knee_joint").id]
    pose = nominal.key_qpos[0].copy()
    pose[knee] = 0.4  # Bent: a drive holding the joint angles differs from one holding 0.9.

    def knee_after(model: mujoco.MjModel, calls: int, change: float, push: bool = False) -> float:
        """The knee after ``calls`` 10 ms stepping calls: the first sends the pose with the
        knee target 0.5 rad further bent, the later ones add ``change`` to it."""
        be = tracking_backend(replace(g1_tracking("none"), step_method=method), 1, model=model)
        assert isinstance(be, MujocoCpuBackend)
        be.set_ctrl(np.zeros((1, model.nu)))  # Whatever the previous episode commanded.
        be.reset_to(np.array([0]), pose[None], np.zeros((1, model.nv)))
        ctrl = pose[None, 7:].copy()
        ctrl[0, knee - 7] += 0.5
        for c in range(calls):
            if c == 1:
                ctrl[0, knee - 7] += change
            be.set_ctrl(ctrl)
            be.step(2)
            if push and c == 1:  # A push of nothing: the delay line must carry on.
                be.push(np.array([0]), np.zeros((1, model.nv)))
        be.close()
        return float(be.read().qpos[0, knee])

    # The first command acts at once: the delayed knee moves as the undelayed one does.
    assert knee_after(delayed, 1, 0.0) == pytest.approx(knee_after(nominal, 1, 0.0), abs=1e-9)
    assert abs(knee_after(delayed, 1, 0.0) - 0.4) > 1e-3  # It moved towards 0.9 rad.
    for calls in (2, 3, 4):  # The change, sent at 10 ms, has not arrived by 40 ms.
        held = knee_after(nominal, calls, 0.0)
        assert knee_after(delayed, calls, -0.5) == pytest.approx(held, abs=1e-9)
    assert knee_after(delayed, 6, 0.0) - knee_after(delayed, 6, -0.5) > 1e-3  # 60 ms: it has.
    assert knee_after(nominal, 2, 0.0) - knee_after(nominal, 2, -0.5) > 1e-4
    unpushed = knee_after(delayed, 6, -0.5)
    assert knee_after(delayed, 6, -0.5, push=True) == pytest.approx(unpushed, abs=1e-6)
