"""Minimum-jerk joint-space motions that respect velocity and acceleration limits.

A minimum-jerk segment from ``q0`` to ``q1`` over duration ``T`` follows
``q(t) = q0 + (q1 - q0) * s(t / T)`` with ``s(u) = 10u^3 - 15u^4 + 6u^5``; its peak speed is
``1.875 |dq| / T`` and its peak acceleration ``10 / sqrt(3) |dq| / T^2`` (at u = 1/2 -+ sqrt(3)/6).
"""

from __future__ import annotations

import numpy as np

#: Peak of ds/du for the minimum-jerk polynomial.
PEAK_VEL = 1.875
#: Peak of |d2s/du2| for the minimum-jerk polynomial (10 / sqrt(3)).
PEAK_ACC = 10.0 / np.sqrt(3.0)


def min_jerk(u: np.ndarray) -> np.ndarray:
    """The minimum-jerk blend ``s(u)`` for ``u`` in [0, 1] (clipped outside)."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 + u * (-15.0 + 6.0 * u))


def min_jerk_duration(
    q0: np.ndarray, q1: np.ndarray, qd_max: np.ndarray, qdd_max: np.ndarray, speed_scale: float = 1.0,
    min_duration: float = 0.05,
) -> float:
    """Shortest duration (s) of a minimum-jerk move ``q0 -> q1`` (rad) within ``speed_scale`` x the limits.

    ``qd_max`` (rad/s) and ``qdd_max`` (rad/s^2) are per joint. ``speed_scale`` in (0, 1].
    """
    if not 0.0 < speed_scale <= 1.0:
        raise ValueError(f"speed_scale must be in (0, 1], got {speed_scale}")
    d = np.abs(np.asarray(q1, float) - np.asarray(q0, float))
    v = np.asarray(qd_max, float) * speed_scale
    a = np.asarray(qdd_max, float) * speed_scale
    t_v = PEAK_VEL * d / v
    t_a = np.sqrt(PEAK_ACC * d / a)
    return float(max(min_duration, np.max(t_v), np.max(t_a)))


def min_jerk_segment(q0: np.ndarray, q1: np.ndarray, duration: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample a minimum-jerk move: times (T,) s from ``dt`` to ``duration`` inclusive and joints (T, n) rad.

    The start point itself (t = 0) is not included, so segments chain without repeated samples.
    """
    if duration <= 0 or dt <= 0:
        raise ValueError("duration and dt must be positive (s)")
    n = max(1, int(np.ceil(duration / dt - 1e-9)))
    times = np.linspace(duration / n, duration, n)
    s = min_jerk(times / duration)[:, None]
    q0 = np.asarray(q0, float)
    return times, q0 + (np.asarray(q1, float) - q0) * s


def chain_waypoints(
    q_start: np.ndarray, waypoints_wxn: np.ndarray, qd_max: np.ndarray, qdd_max: np.ndarray,
    speed_scale: float = 1.0, dt: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Rest-to-rest minimum-jerk segments through joint waypoints (W, n); returns times (T,) s and joints (T, n)."""
    times: list[np.ndarray] = []
    qs: list[np.ndarray] = []
    t0 = 0.0
    q_prev = np.asarray(q_start, float)
    for q_next in np.atleast_2d(waypoints_wxn):
        dur = min_jerk_duration(q_prev, q_next, qd_max, qdd_max, speed_scale)
        t, q = min_jerk_segment(q_prev, q_next, dur, dt)
        times.append(t + t0)
        qs.append(q)
        t0 += dur
        q_prev = np.asarray(q_next, float)
    return np.concatenate(times), np.concatenate(qs)
