"""iLQR over PD targets: the control step's Jacobians, the Riccati pass, the polish."""

from __future__ import annotations

import mujoco
import numpy as np

from humimic.retarget.dynamics.ilqr import ilqr
from humimic.sim.lqr import control_step_jacobians

ARM = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="lower" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="shoulder" kp="20" kv="1"/>
    <position joint="elbow" kp="10" kv="0.5"/>
  </actuator>
</mujoco>
"""

CART = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0" integrator="Euler"/>
  <worldbody>
    <body name="cart"><joint name="x" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="2"/></body>
  </worldbody>
  <actuator><motor joint="x" gear="1"/></actuator>
</mujoco>
"""

SPEC = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)


def _state(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    out = np.zeros(mujoco.mj_stateSize(model, SPEC))
    mujoco.mj_getState(model, data, out, SPEC)
    return out


def _step(model: mujoco.MjModel, x: np.ndarray, u: np.ndarray, decimation: int) -> np.ndarray:
    data = mujoco.MjData(model)
    nq = model.nq
    data.qpos[:], data.qvel[:], data.ctrl[:] = x[:nq], x[nq:], u
    for _ in range(decimation):
        mujoco.mj_step(model, data)
    return np.concatenate([data.qpos, data.qvel])


def test_control_step_jacobians_match_central_differences() -> None:
    model = mujoco.MjModel.from_xml_string(ARM)
    x0, u0, dec = np.array([0.4, -0.7, 1.0, -2.0]), np.array([0.2, 0.5]), 4
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = x0[:2], x0[2:]
    A, B = control_step_jacobians(model, data, u0, dec, 1e-6)
    np.testing.assert_allclose(np.r_[data.qpos, data.qvel], _step(model, x0, u0, dec))
    h = 1e-5  # Hinge joints: the tangent state is the state.
    A_fd = np.column_stack(
        [(_step(model, x0 + h * e, u0, dec) - _step(model, x0 - h * e, u0, dec)) / (2 * h)
         for e in np.eye(4)]
    )  # fmt: skip
    B_fd = np.column_stack(
        [(_step(model, x0, u0 + h * e, dec) - _step(model, x0, u0 - h * e, dec)) / (2 * h)
         for e in np.eye(2)]
    )  # fmt: skip
    np.testing.assert_allclose(A, A_fd, atol=1e-4)
    np.testing.assert_allclose(B, B_fd, atol=1e-4)
    assert np.abs(A - np.eye(4)).max() > 0.01  # Not trivially the identity.


def test_one_iteration_solves_a_linear_quadratic_problem() -> None:
    """A force-driven cart under explicit Euler is linear: one Gauss-Newton step with no
    regularization lands on the least-squares optimum of the whole plan."""
    model = mujoco.MjModel.from_xml_string(CART)
    H, dec, target, rho = 12, 2, 1.0, 1e-3
    state = _state(model, np.zeros(1), np.zeros(1))

    def simulate(u: np.ndarray) -> np.ndarray:
        x, out = np.zeros(2), []
        for t in range(H):
            x = _step(model, x, u[t], dec)
            out.append(x)
        return np.array(out)

    def stage(data: mujoco.MjData, t: int, u: np.ndarray):  # type: ignore[no-untyped-def]
        r = np.array([data.qpos[0] - target, 0.1 * data.qvel[0]])
        return r, np.array([[1.0, 0.0], [0.0, 0.1]]), 2 * rho * u, 2 * rho * np.eye(1)

    def cost(u: np.ndarray) -> float:
        x = simulate(u)
        return float(np.sum((x[:, 0] - target) ** 2 + (0.1 * x[:, 1]) ** 2) + rho * np.sum(u**2))

    out = ilqr(model, state, np.zeros(1), np.zeros((H, 1)), decimation=dec, stage=stage,
               cost=cost, lower=np.full(1, -1e3), upper=np.full(1, 1e3), iterations=1,
               mu=1e-12)  # fmt: skip
    # The optimum by batch least squares on the (linear) map from plan to states.
    x0 = simulate(np.zeros((H, 1)))
    G = np.stack([simulate(np.eye(H)[i][:, None]) - x0 for i in range(H)], axis=-1)  # (H, 2, H)
    rows = np.concatenate([G[:, 0], 0.1 * G[:, 1], np.sqrt(rho) * np.eye(H)])
    rhs = np.concatenate([target - x0[:, 0], -0.1 * x0[:, 1], np.zeros(H)])
    best = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    np.testing.assert_allclose(out.controls[:, 0], best, atol=1e-6)
    assert out.steps == (1.0,) and out.cost == cost(out.controls) < out.initial_cost


def test_polish_lowers_a_nonlinear_cost_within_bounds() -> None:
    """On the arm under gravity (nonlinear), from a plan that holds still: each iteration
    keeps the exact cost from rising, the bounds hold, and the result replays to its cost."""
    model = mujoco.MjModel.from_xml_string(ARM)
    H, dec = 20, 4
    goal = np.array([-0.8, 1.2])
    state = _state(model, np.zeros(2), np.zeros(2))
    lo, hi = np.array([-1.0, -0.5]), np.array([1.0, 1.5])

    def simulate(u: np.ndarray) -> np.ndarray:
        data = mujoco.MjData(model)
        mujoco.mj_setState(model, data, state, SPEC)
        q = []
        for t in range(H):
            data.ctrl[:] = u[t]
            for _ in range(dec):
                mujoco.mj_step(model, data)
            q.append(np.r_[data.qpos, data.qvel])
        return np.array(q)

    def stage(data: mujoco.MjData, t: int, u: np.ndarray):  # type: ignore[no-untyped-def]
        w = 1.0 + 9.0 * (t == H - 1)
        J = np.sqrt(w) * np.hstack([np.eye(2), np.zeros((2, 2))])
        return np.sqrt(w) * (data.qpos - goal), J, np.zeros(2), np.zeros((2, 2))

    def cost(u: np.ndarray) -> float:
        x = simulate(u)
        w = np.ones(H)
        w[-1] = 10.0
        return float(np.sum(w[:, None] * (x[:, :2] - goal) ** 2))

    start = np.zeros((H, 2))
    costs = [cost(start)]
    u = start
    for _ in range(4):
        out = ilqr(model, state, np.zeros(2), u, decimation=dec, stage=stage, cost=cost,
                   lower=lo, upper=hi, iterations=1)  # fmt: skip
        assert out.cost <= costs[-1]
        u = out.controls
        costs.append(out.cost)
        assert abs(cost(u) - out.cost) < 1e-12
    assert np.all(u >= lo) and np.all(u <= hi)
    assert costs[-1] < 0.05 * costs[0], costs


def test_riccati_gains_equal_the_batch_least_squares_optimum() -> None:
    """The Riccati recursion's first gain is the finite-horizon LQR optimum found another
    way: the whole problem as one least-squares solve over every control, from each unit
    initial state."""
    from humimic.sim.lqr import riccati

    rng = np.random.default_rng(2)
    nx, nu, H = 4, 2, 6
    A = np.stack([np.eye(nx) + 0.2 * rng.normal(size=(nx, nx)) for _ in range(H)])
    B = rng.normal(size=(H, nx, nu))
    qd, r = np.array([1.0, 2.0, 0.5, 3.0]), 0.7
    lxx = np.broadcast_to(np.diag(qd), (H + 1, nx, nx)).copy()
    luu = np.broadcast_to(r * np.eye(nu), (H, nu, nu)).copy()
    out = riccati(np.zeros((H + 1, nx)), lxx, np.zeros((H, nu)), luu, A, B, 0.0)
    assert out is not None
    K0 = out[1][0]
    # x_t = S_t x0 + sum_k G_tk u_k; cost sum_t x_t' Q x_t / 2 + r |u|^2 / 2 (x_0 included).
    S, G = [np.eye(nx)], [np.zeros((nx, H * nu))]
    for t in range(H):
        S.append(A[t] @ S[-1])
        g = A[t] @ G[-1]
        g[:, t * nu : (t + 1) * nu] += B[t]
        G.append(g)
    w = np.sqrt(qd)[:, None]
    M = np.vstack([w * g for g in G] + [np.sqrt(r) * np.eye(H * nu)])
    for i in range(nx):
        x0 = np.eye(nx)[i]
        rhs = -np.concatenate([w[:, 0] * (s @ x0) for s in S] + [np.zeros(H * nu)])
        u = np.linalg.lstsq(M, rhs, rcond=None)[0]
        np.testing.assert_allclose(K0 @ x0, u[:nu], atol=1e-9)


def test_delayed_gains_equal_the_batch_optimum_of_the_delayed_plant() -> None:
    """With commands that act ``d`` steps after they are issued, the first gain of the
    Riccati recursion on :func:`delayed_system` is the finite-horizon optimum found another
    way: the delayed plant written out by hand (its first ``d`` inputs are the commands in
    flight), one least-squares solve over every issued command, from each unit start."""
    from humimic.sim.lqr import delayed_system, riccati

    rng = np.random.default_rng(3)
    nx, nu, H, d = 3, 2, 7, 2
    A = np.stack([np.eye(nx) + 0.2 * rng.normal(size=(nx, nx)) for _ in range(H)])
    B = rng.normal(size=(H, nx, nu))
    qd, r = np.array([1.0, 2.0, 0.5]), 0.7
    Az, Bz = delayed_system(A, B, d)
    nz = nx + d * nu
    lxx = np.zeros((H + 1, nz, nz))
    lxx[:, :nx, :nx] = np.diag(qd)
    luu = np.broadcast_to(r * np.eye(nu), (H, nu, nu)).copy()
    out = riccati(np.zeros((H + 1, nz)), lxx, np.zeros((H, nu)), luu, Az, Bz, 0.0)
    assert out is not None
    K0 = out[1][0]
    # Unknowns: the issued commands u_0..u_{H-1}. The plant at step t takes u_{t-d}: from the
    # queue q (oldest first) while t < d. x_t = S_t z0 + G_t u.
    S, G = [np.eye(nx, nz)], [np.zeros((nx, H * nu))]
    for t in range(H):
        s, g = A[t] @ S[-1], A[t] @ G[-1]
        if t < d:
            s[:, nx + t * nu : nx + (t + 1) * nu] += B[t]
        else:
            g[:, (t - d) * nu : (t - d + 1) * nu] += B[t]
        S.append(s)
        G.append(g)
    w = np.sqrt(qd)[:, None]
    M = np.vstack([w * g for g in G] + [np.sqrt(r) * np.eye(H * nu)])
    for i in range(nz):
        z0 = np.eye(nz)[i]
        rhs = -np.concatenate([w[:, 0] * (s @ z0) for s in S] + [np.zeros(H * nu)])
        u = np.linalg.lstsq(M, rhs, rcond=None)[0]
        np.testing.assert_allclose(K0 @ z0, u[:nu], atol=1e-9)
    assert np.abs(K0[:, nx:]).max() > 1e-3  # The commands in flight matter.
    # No delay: the plant itself.
    A0, B0 = delayed_system(A, B, 0)
    assert A0 is A and B0 is B


FLOATING = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 0.3"><freejoint/>
      <geom type="box" size="0.1 0.1 0.1" mass="{mass}"/>
      <body name="arm" pos="0.1 0 0">
        <joint name="j" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" mass="0.3"/>
      </body>
    </body>
  </worldbody>
  <actuator><position joint="j" kp="20" kv="1"/></actuator>
</mujoco>
"""


def test_tvlqr_gains_are_remembered_by_the_models_content_and_the_plans() -> None:
    """The gains are cached (training and every evaluation physics ask for the same ones):
    the same request gives equal gains that the caller may change, and a model that differs
    in one mass, or another plan, gets its own."""
    from humimic.sim.lqr import tvlqr_gains

    model = mujoco.MjModel.from_xml_string(FLOATING.format(mass=2.0))
    data = mujoco.MjData(model)
    qpos, qvel = [], []
    for _ in range(4):
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
        for _ in range(2):
            mujoco.mj_step(model, data)
    qpos, qvel, ctrl = np.array(qpos), np.array(qvel), np.zeros((3, 1))
    k1 = tvlqr_gains(model, qpos, qvel, ctrl, 2)
    k1[...] = np.nan  # The caller's copy: the cache keeps its own.
    k2 = tvlqr_gains(model, qpos, qvel, ctrl, 2)
    assert np.all(np.isfinite(k2))
    np.testing.assert_array_equal(k2, tvlqr_gains(mujoco.MjModel.from_xml_string(
        FLOATING.format(mass=2.0)), qpos, qvel, ctrl, 2))  # fmt: skip
    heavier = tvlqr_gains(mujoco.MjModel.from_xml_string(FLOATING.format(mass=4.0)),
                          qpos, qvel, ctrl, 2)  # fmt: skip
    assert np.abs(heavier - k2).max() > 1e-3 * np.abs(k2).max()
    moved = tvlqr_gains(model, qpos, qvel, ctrl + 0.2, 2)
    assert np.abs(moved - k2).max() > 1e-3 * np.abs(k2).max()
