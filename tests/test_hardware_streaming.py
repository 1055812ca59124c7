"""Chunks that end at rest (torm.hardware.streaming): on the checked path, at rest at the end, within the bound."""

from __future__ import annotations

import numpy as np
import pytest

from torm.errors import ConfigError
from torm.execution.trajectory import chain_waypoints
from torm.hardware.streaming import StreamPlan, StreamSettings, worst_case_stop_s

QD = np.array([1.8, 1.8, 2.5])
QDD = np.array([3.0, 4.0, 7.0])
SCALE = 0.25


def _plan(settings: StreamSettings | None = None) -> tuple[StreamPlan, np.ndarray, np.ndarray]:
    settings = settings or StreamSettings()
    q0 = np.zeros(3)
    t, q = chain_waypoints(q0, np.array([[0.8, -0.4, 0.6], [0.2, 0.3, -0.2]]), QD, QDD, SCALE * 0.95, dt=0.02)
    return StreamPlan(q0, t, q, SCALE * QDD, settings), t, q


def _dist_to_path(p: np.ndarray, knots_q: np.ndarray) -> float:
    """Exact distance (rad, Euclidean) from ``p`` to the piecewise-linear path through ``knots_q``."""
    a, d = knots_q[:-1], np.diff(knots_q, axis=0)
    s = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-30), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + s[:, None] * d - p, axis=1)))


def test_every_chunk_lies_on_the_path_and_ends_at_rest_within_the_bound():
    plan, t, q = _plan()
    a = plan.settings.brake_fraction * SCALE * QDD
    n_chunks = 0
    for t_now in np.arange(0.0, plan.duration_s, 0.1):
        rel, qs, final = plan.chunk(float(t_now))
        n_chunks += 1
        assert rel[0] > 0 and np.all(np.diff(rel) >= 1e-3 - 1e-12)  # strictly increasing, 1 ms apart at least
        assert max(_dist_to_path(p, plan.knots_q) for p in qs) < 1e-9  # every point lies on the checked path
        # no knot of the path lies strictly between two points of the nominal part (nor of the tail, see the
        # next test), so the controller's straight line between consecutive points is the path itself
        ts = t_now + rel[rel <= plan.settings.horizon_s + 1e-9]
        inner = plan.knots_t[(plan.knots_t > ts[0] + 1e-9) & (plan.knots_t < ts[-1] - 1e-9)]
        assert all(np.min(np.abs(ts - k)) < 1e-9 for k in inner)
        assert rel[-1] <= plan.stop_within_s + 1e-9
        if final:
            np.testing.assert_allclose(qs[-1], q[-1])
            break
        # the last step of the braking tail is slow enough to stop within the braking deceleration
        v = np.abs(np.diff(qs, axis=0)) / np.diff(rel)[:, None]
        assert np.all(v[-1] <= a * (rel[-1] - rel[-2]) + 1e-9)
    assert n_chunks > 20


def test_braking_tail_is_a_linear_slow_down_along_the_path():
    """tau(u) = t_c + u - u^2 / (2 T_b): plan time moves forward at a rate falling linearly from 1 to 0, every
    path knot it passes is a tail point, and the deceleration term |q'| / T_b is within brake_fraction x a."""
    plan, _, _ = _plan(StreamSettings(brake_fraction=0.5))
    Tb = plan.brake_s
    t_c = 1.3
    u, tau = plan._tail_times(t_c)
    np.testing.assert_allclose(tau, t_c + u - u**2 / (2 * Tb), atol=1e-12)
    assert u[-1] == pytest.approx(Tb) and np.all(np.diff(u) > 0) and np.all(np.diff(tau) > 0)
    rate = 1 - u / Tb
    assert np.all(np.diff(rate) < 0) and rate[-1] == pytest.approx(0.0, abs=1e-12)
    passed = plan.knots_t[(plan.knots_t > t_c) & (plan.knots_t < tau[-1])]
    assert all(np.min(np.abs(tau - k)) < 1e-9 for k in passed)
    vel = np.diff(plan.knots_q, axis=0) / np.diff(plan.knots_t)[:, None]
    assert np.all(np.max(np.abs(vel), axis=0) / Tb <= 0.5 * SCALE * QDD + 1e-12)
    # a tail that reaches the end of the path stops there
    u, tau = plan._tail_times(plan.duration_s - 0.05)
    assert tau[-1] == pytest.approx(plan.duration_s) and np.all(tau <= plan.duration_s + 1e-12)


def test_stop_bound_and_worst_case():
    plan, _, _ = _plan()
    vel = np.diff(plan.knots_q, axis=0) / np.diff(plan.knots_t)[:, None]
    expected = np.max(np.max(np.abs(vel), axis=0) / (SCALE * QDD))
    assert plan.brake_s == pytest.approx(expected) and plan.stop_within_s == pytest.approx(0.3 + expected)
    worst = worst_case_stop_s(StreamSettings(), QD, QDD)
    assert worst == pytest.approx(0.3 + 1.05 * 0.6) and plan.stop_within_s <= worst


def test_short_motion_is_one_final_chunk():
    plan = StreamPlan(np.zeros(2), np.array([0.1, 0.2]), np.array([[0.01, 0.0], [0.02, 0.0]]), None, StreamSettings())
    rel, qs, final = plan.chunk(0.0)
    assert final and rel[-1] == pytest.approx(0.2) and np.allclose(qs[-1], [0.02, 0.0])
    rel, qs, final = plan.chunk(0.195)  # less than lead_s left: one point at the end
    assert final and len(rel) == 1 and np.allclose(qs[0], [0.02, 0.0])


def test_stream_settings_validation():
    with pytest.raises(ConfigError, match="horizon_s"):
        StreamSettings(horizon_s=0.1, period_s=0.1)
    with pytest.raises(ConfigError, match="brake_fraction"):
        StreamSettings(brake_fraction=0.0)
    from torm.hardware.config import HardwareConfig

    with pytest.raises(ConfigError, match="speed_scale"):
        HardwareConfig(host="h", speed_scale=0.6)  # 0.6 x (1.05 + 1.0) > 1: braking could exceed the limits
    HardwareConfig(host="h", speed_scale=0.6, stream=StreamSettings(brake_fraction=0.5))
