"""The field's evaluation protocols (issue 59) judged on hand-made traces: where each rule
fires, what each metric measures, and the totals over clips (null over no clip)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from humimic.tracking.protocols import ClipTrace, beyondmimic, judge, phc, summarize

T, B = 10, 3


def _tilt(deg: float) -> np.ndarray:
    """A rotation of ``deg`` about x as (w, x, y, z)."""
    h = math.radians(deg) / 2
    return np.array([math.cos(h), math.sin(h), 0.0, 0.0])


def _trace(**kw: object) -> ClipTrace:
    """A clip where the robot is the reference exactly (three bodies on a line, walking along
    x at 10 mm per frame), every step earning half the maximum reward; ``kw`` replaces."""
    ref = np.zeros((T, B, 3))
    ref[:, :, 0] = 0.01 * np.arange(T)[:, None]
    ref[:, :, 2] = [0.8, 1.1, 0.1]  # Root (pelvis), torso, a foot.
    up = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    base = dict(anchor_pos=ref[:, 1].copy(), ref_anchor_pos=ref[:, 1].copy(),
                anchor_quat=up.copy(), ref_anchor_quat=up.copy(), body_pos=ref.copy(),
                ref_body_pos=ref, root=0, reward=np.full(T, 2.75), reward_max=5.5)  # fmt: skip
    return ClipTrace(**{**base, **kw})  # type: ignore[arg-type]


def test_beyondmimic_fails_at_the_first_step_over_either_threshold() -> None:
    perfect = beyondmimic(_trace())
    assert perfect == {"failed": False, "fail_step": None, "normalized_return": 0.5}
    # Anchor height: 0.24 m below never fails, 0.26 m from step 6 on does.
    low = _trace().anchor_pos.copy()
    low[:, 2] -= 0.24
    assert not beyondmimic(_trace(anchor_pos=low))["failed"]
    low[6:, 2] -= 0.02
    r = beyondmimic(_trace(anchor_pos=low))
    assert r["failed"] and r["fail_step"] == 6
    # Return up to and including the failing step (7 steps of 10 at half the maximum).
    assert r["normalized_return"] == pytest.approx(0.5 * 7 / 10)
    # Orientation: the rule is on projected gravity's z, 1 - cos(tilt) against an upright
    # reference: 78 degrees (0.792) holds, 79 degrees (0.809) fails.
    for deg, fails in ((78.0, False), (79.0, True)):
        assert (1 - math.cos(math.radians(deg)) > 0.8) == fails  # The rule, by hand.
        q = _trace().anchor_quat.copy()
        q[3:] = _tilt(deg)
        r = beyondmimic(_trace(anchor_quat=q))
        assert r["failed"] == fails and r["fail_step"] == (3 if fails else None)
    # A yaw, however large, is no failure (gravity does not see it).
    yaw = np.tile([math.cos(1.5), 0.0, 0.0, math.sin(1.5)], (T, 1))
    assert not beyondmimic(_trace(anchor_quat=yaw))["failed"]
    # A reference that tilts as the robot does: no error.
    tilted = np.tile(_tilt(85.0), (T, 1))
    assert not beyondmimic(_trace(anchor_quat=tilted, ref_anchor_quat=tilted))["failed"]


def test_phc_fails_on_the_mean_body_error_and_measures_errors_up_to_it() -> None:
    # One body 1.2 m off, two exact: mean 0.4 m, no failure though one body is far off.
    far = _trace().body_pos.copy()
    far[:, 2, 1] += 1.2
    r = phc(_trace(body_pos=far))
    assert not r["failed"] and r["mpjpe_global_mm"] == pytest.approx(400.0)
    assert r["vel_error_mm_per_frame"] == pytest.approx(0.0, abs=1e-9)
    # From step 4 on, two bodies 0.2 m and one 1.2 m off: mean 0.533 m > 0.5 m.
    worse = far.copy()
    worse[4:, :2, 1] += 0.2
    r = phc(_trace(body_pos=worse))
    assert r["failed"] and r["fail_step"] == 4
    # Errors over steps 0..4: four at 0.4 m mean, one at 0.533.
    assert r["mpjpe_global_mm"] == pytest.approx(1e3 * (4 * 0.4 + 1.6 / 3) / 5)


def test_phc_root_relative_velocity_and_acceleration_errors() -> None:
    ref = _trace().ref_body_pos
    # The whole robot 0.1 m to the side: global error 100 mm, root-relative 0.
    shifted = ref + np.array([0.0, 0.1, 0.0])
    r = phc(_trace(body_pos=shifted))
    assert r["mpjpe_global_mm"] == pytest.approx(100.0)
    assert r["mpjpe_root_mm"] == pytest.approx(0.0, abs=1e-9)
    # Walking 13 mm per frame instead of 10: velocity error 3 mm/frame, acceleration 0.
    fast = ref.copy()
    fast[:, :, 0] = 0.013 * np.arange(T)[:, None]
    r = phc(_trace(body_pos=fast))
    assert r["vel_error_mm_per_frame"] == pytest.approx(3.0)
    assert r["acc_error_mm_per_frame2"] == pytest.approx(0.0, abs=1e-9)
    # Accelerating by 2 mm per frame per frame: the acceleration error is 2 mm/frame^2.
    acc = ref.copy()
    acc[:, :, 0] += 0.001 * np.arange(T)[:, None] ** 2
    r = phc(_trace(body_pos=acc))
    assert r["acc_error_mm_per_frame2"] == pytest.approx(2.0)
    # The root-relative error: the foot 50 mm higher relative to the root.
    foot = ref.copy()
    foot[:, 2, 2] += 0.05
    r = phc(_trace(body_pos=foot))
    assert r["mpjpe_root_mm"] == pytest.approx(50.0 / 3)


def test_totals_over_clips_and_null_over_none() -> None:
    low = _trace().anchor_pos.copy()
    low[:, 2] -= 0.3
    gone = _trace().body_pos + np.array([0.0, 0.6, 0.0])
    clips = {"a.npz": judge(_trace()), "b.npz": judge(_trace(anchor_pos=low, body_pos=gone))}
    s = summarize(clips)
    bm, ph = s["beyondmimic"], s["phc"]
    assert bm["clips"] == 2 and bm["failed_clips"] == 1
    # b fails at step 0: one step of ten at half the maximum.
    assert bm["mean_normalized_return"] == pytest.approx((0.5 + 0.05) / 2)
    assert ph["success_rate"] == 0.5 and ph["per_clip"]["b.npz"]["fail_step"] == 0
    assert ph["all"]["mpjpe_global_mm"] == pytest.approx((0.0 + 600.0) / 2)
    assert ph["successful"]["mpjpe_global_mm"] == pytest.approx(0.0)
    # b's velocity and acceleration errors span one step: none to measure, null, and left
    # out of the mean rather than counted as perfect.
    assert ph["per_clip"]["b.npz"]["vel_error_mm_per_frame"] is None
    assert ph["all"]["vel_error_mm_per_frame"] == pytest.approx(0.0, abs=1e-9)
    only_b = summarize({"b.npz": clips["b.npz"]})["phc"]
    assert only_b["success_rate"] == 0.0 and only_b["successful"] is None
    assert only_b["all"]["vel_error_mm_per_frame"] is None
    assert summarize({})["phc"]["success_rate"] is None
    assert summarize({})["beyondmimic"]["mean_normalized_return"] is None
