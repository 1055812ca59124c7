"""The paper's success test on hand-built pick traces."""

from __future__ import annotations

import numpy as np

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
