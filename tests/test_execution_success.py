"""The paper's success test on hand-built pick traces."""

from __future__ import annotations

import numpy as np
import pytest

from torm.execution.success import Outcome, PickTrace, SuccessCriteria, judge_pick


def _trace(lift=0.25, move=0.20, slip=0.0, final_dz=0.0, drop_at=None):
    rest = np.array([0.5, 0.0, 0.05])
    rel0 = np.array([0.0, 0.0, -0.01])
    t = PickTrace(rest=rest)
    for k in range(20):
        t.lift.append(rel0 + np.array([0, 0, -slip * k / 19]))
    t.lift_end = rest + [0, 0, lift - slip]
    for k in range(20):
        off = np.array([0, 0, -1.0]) if (drop_at is not None and k >= drop_at) else np.zeros(3)
        t.translate.append(t.lift[-1] + off)
    t.translate_end = rest + [0, move, lift - slip] if drop_at is None else rest + [0, 0.05, 0]
    t.final = rest + [0, move, final_dz]
    return t


def test_success_and_each_failure_stage():
    assert judge_pick(_trace()).outcome is Outcome.SUCCESS
    assert judge_pick(_trace(lift=0.10)).outcome is Outcome.SLIPPED
    assert judge_pick(_trace(slip=0.05)).outcome is Outcome.SLIPPED
    assert judge_pick(_trace(drop_at=10)).outcome is Outcome.DROPPED
    assert judge_pick(_trace(move=0.05)).outcome is Outcome.DROPPED
    assert judge_pick(_trace(final_dz=0.2)).outcome is Outcome.NOT_RELEASED


def test_tolerances_are_respected():
    # 5 mm of slip is within the default 2 cm tolerance; 3 cm is not.
    assert judge_pick(_trace(slip=0.005)).outcome is Outcome.SUCCESS
    assert judge_pick(_trace(slip=0.03)).outcome is Outcome.SLIPPED
    strict = SuccessCriteria(slip_tolerance=0.001)
    assert judge_pick(_trace(slip=0.005), strict).outcome is Outcome.SLIPPED
    j = judge_pick(_trace())
    assert np.isclose(j.lift, 0.25) and np.isclose(j.translation, 0.20)
    assert j.as_dict()["outcome"] == "success"


def _with_tcp(t: PickTrace, tcp_lift: float, tcp_move: float = 0.20) -> PickTrace:
    """Attach the TCP's measured positions: rose ``tcp_lift`` during the lift, moved ``tcp_move`` sideways."""
    t.tcp_rest = t.rest + [0, 0, 0.01]
    t.tcp_lift_end = t.tcp_rest + [0, 0, tcp_lift]
    t.tcp_translate_end = t.tcp_lift_end + [0, tcp_move, 0]
    return t


def test_arm_that_falls_short_is_a_tracking_error_not_a_slip():
    # The arm sagged: the object rose only 22 cm, but so did the TCP and the object stayed in the hand.
    j = judge_pick(_with_tcp(_trace(lift=0.22), tcp_lift=0.22))
    assert j.outcome is Outcome.TRACKING and j.tcp_lift == pytest.approx(0.22)
    assert j.as_dict()["outcome"] == "arm_tracking_error"
    # Same shortfall while the TCP did rise 25 cm: the object slipped down in the hand.
    assert judge_pick(_with_tcp(_trace(lift=0.22), tcp_lift=0.25)).outcome is Outcome.SLIPPED
    # Real slip beyond the tolerance stays a slip even if the arm also fell short.
    assert judge_pick(_with_tcp(_trace(lift=0.20, slip=0.05), tcp_lift=0.20)).outcome is Outcome.SLIPPED
    # The arm did not translate far enough: tracking, not a drop.
    assert judge_pick(_with_tcp(_trace(move=0.05), tcp_lift=0.25, tcp_move=0.05)).outcome is Outcome.TRACKING
    assert judge_pick(_with_tcp(_trace(move=0.05), tcp_lift=0.25, tcp_move=0.20)).outcome is Outcome.DROPPED
    # A few mm of sag within the tolerances is still a success, and the TCP numbers are reported.
    j = judge_pick(_with_tcp(_trace(lift=0.245), tcp_lift=0.245))
    assert j.outcome is Outcome.SUCCESS and j.tcp_translation == pytest.approx(0.20)
