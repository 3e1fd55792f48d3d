"""The IK's QP wrapper checks daqp's answer instead of trusting its exit flag."""

from __future__ import annotations

import numpy as np
import pytest

from humimic.retarget import kinematic
from humimic.retarget.kinematic import DAQP_SOFT, solve_qp


def _box_qp() -> tuple[np.ndarray, ...]:
    """min |x - (2, 0)|^2 with |x_i| <= 1 and the row x0 + x1 <= 0.5."""
    H = np.eye(2)
    c = -np.array([2.0, 0.0])
    A = np.array([[1.0, 1.0]])
    bu = np.array([1.0, 1.0, 0.5])
    bl = np.array([-1.0, -1.0, -1e30])
    return H, c, A, bu, bl


def test_an_optimal_solution_is_returned() -> None:
    H, c, A, bu, bl = _box_qp()
    x, flag = solve_qp(H, c, A, bu, bl, np.zeros(3, dtype=np.int32))
    assert flag == 1 and x is not None
    np.testing.assert_allclose(x, [1.0, -0.5], atol=1e-8)


def test_an_infeasible_qp_has_no_solution() -> None:
    H, c, A, bu, bl = _box_qp()
    bu[2] = -5.0  # x0 + x1 <= -5 with |x_i| <= 1: no point.
    x, flag = solve_qp(H, c, A, bu, bl, np.zeros(3, dtype=np.int32))
    assert x is None and flag < 1


def test_soft_rows_may_be_violated_hard_bounds_not() -> None:
    H, c, A, bu, bl = _box_qp()
    bu[2] = -5.0
    sense = np.array([0, 0, DAQP_SOFT], dtype=np.int32)
    x, flag = solve_qp(H, c, A, bu, bl, sense)
    assert x is not None and flag in (1, 2)
    assert np.all(np.abs(x) <= 1.0 + 1e-9) and A[0] @ x > bu[2]


@pytest.mark.parametrize("flag", [1, 2, 4])
def test_a_positive_flag_with_a_step_outside_the_bounds_is_rejected(
    monkeypatch: pytest.MonkeyPatch, flag: int
) -> None:
    """daqp 0.11 answered exit flag 4 with a step outside the trust region (where 0.10 said -1);
    the IK took it, and the interaction-mesh walk jumped 0.75 m and floated over its pad."""
    H, c, A, bu, bl = _box_qp()

    def fake_solve(*_args: object) -> tuple[np.ndarray, float, int, dict]:
        return np.array([1.74, -0.2]), 0.0, flag, {}

    monkeypatch.setattr(kinematic.daqp, "solve", fake_solve)
    x, got = solve_qp(H, c, A, bu, bl, np.zeros(3, dtype=np.int32))
    assert x is None and got == flag


def test_an_undocumented_flag_is_not_a_solution(monkeypatch: pytest.MonkeyPatch) -> None:
    H, c, A, bu, bl = _box_qp()
    monkeypatch.setattr(kinematic.daqp, "solve", lambda *_a: (np.array([0.5, -0.5]), 0.0, 4, {}))
    x, _ = solve_qp(H, c, A, bu, bl, np.zeros(3, dtype=np.int32))
    assert x is None


def test_a_non_finite_solution_is_rejected(monkeypatch: pytest.MonkeyPatch) -> None:
    H, c, A, bu, bl = _box_qp()
    monkeypatch.setattr(kinematic.daqp, "solve", lambda *_a: (np.array([np.nan, 0.0]), 0.0, 1, {}))
    assert solve_qp(H, c, A, bu, bl, np.zeros(3, dtype=np.int32))[0] is None
