"""Streaming a joint trajectory to a trajectory controller in short chunks that end at rest.

Why: a FollowJointTrajectory goal holding the whole motion keeps the arm moving to its end after the
link or the process dies, and the stop (a cancel) would have to travel over the dead link. Instead
:class:`StreamPlan` cuts the motion into chunks that each end **at rest**: a chunk sent at plan time
``t`` carries the nominal motion up to ``t + horizon_s`` followed by a *braking tail* that slows down
along the same path to a stop. A new chunk replaces the running one every ``period_s`` (< horizon), so
in normal operation the arm never reaches a tail; when no new chunk arrives the controller finishes the
last one and stands still, at most :attr:`StreamPlan.stop_within_s` after the last chunk arrived.

Braking tail: with the nominal path ``q(t)`` (piecewise linear between the samples, what the
controller and the safety layer use), the tail follows ``q(tau(u))`` with ``tau(u) = t_c + u - u^2 /
(2 T_b)`` for ``u`` in [0, T_b]: the path speed falls linearly from 1 to 0, so the tail stays on the
path the safety layer checked (the nominal samples inside the tail are points of the tail too), never
moves faster than the nominal motion, and ends at rest after ``T_b`` s, ``T_b / 2`` s of nominal
motion further. ``T_b = max_j v_peak_j / (brake_fraction * a_j)`` with ``v_peak_j`` the trajectory's
peak speed of joint ``j`` and ``a_j`` its acceleration limit (the safety layer's ``speed_scale`` x
``qdd_max``): the braking deceleration term ``|q'| / T_b`` is at most ``brake_fraction * a_j``, on top
of the nominal acceleration along the slowed-down path (scaled by ``tau'^2 <= 1``).

Stop bound: ``stop_within_s = horizon_s + T_b`` after the controller received the last chunk. With the
safety layer's speed check (``v_peak_j <= (1 + tolerance) speed_scale qd_max_j``) and ``a_j = speed_scale
qdd_max_j`` the worst case over all motions is :func:`worst_case_stop_s`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torm.errors import ConfigError


@dataclass(frozen=True)
class StreamSettings:
    """How motions are streamed (times in s).

    Attributes:
        horizon_s: nominal motion each chunk commits beyond the instant it is sent.
        period_s: a new chunk is sent this often (must be below ``horizon_s - lead_s``).
        lead_s: the first point of a chunk lies this far after its send instant (the controller blends
            from where it is to it).
        brake_fraction: braking deceleration as a fraction of the acceleration limits given to the plan.
        tail_dt_s: sample spacing of the braking tail.
    """

    horizon_s: float = 0.3
    period_s: float = 0.1
    lead_s: float = 0.02
    brake_fraction: float = 1.0
    tail_dt_s: float = 0.02

    def __post_init__(self) -> None:
        if not (self.lead_s > 0 and self.period_s > 0 and self.tail_dt_s > 0):
            raise ConfigError("stream.lead_s, stream.period_s and stream.tail_dt_s must be positive (s)")
        if not self.horizon_s > self.period_s + self.lead_s:
            raise ConfigError(f"stream.horizon_s ({self.horizon_s} s) must exceed stream.period_s + stream.lead_s "
                              f"({self.period_s + self.lead_s} s): a chunk must outlast the wait for the next one")
        if not 0 < self.brake_fraction <= 1.0:
            raise ConfigError(f"stream.brake_fraction must be in (0, 1], got {self.brake_fraction}")


def worst_case_stop_s(settings: StreamSettings, qd_max: np.ndarray, qdd_max: np.ndarray,
                      tolerance: float = 0.05) -> float:
    """Longest time (s) from the last chunk's arrival to standstill for any motion the safety layer accepts.

    Speeds up to ``(1 + tolerance) * speed_scale * qd_max`` braked at ``brake_fraction * speed_scale *
    qdd_max``: the speed scale cancels, ``horizon_s + (1 + tolerance) max_j qd_max_j / (brake_fraction
    qdd_max_j)``.
    """
    ratio = (1.0 + tolerance) * np.asarray(qd_max, float) / (settings.brake_fraction * np.asarray(qdd_max, float))
    return float(settings.horizon_s + max(settings.tail_dt_s, float(np.max(ratio))))


#: Closest two points of a chunk may be in time (s); a sample this close to a path knot is merged into it.
MIN_SPACING_S = 1e-3


def _merge(samples: np.ndarray, knots: np.ndarray, eps: float = MIN_SPACING_S) -> np.ndarray:
    """Sorted union of ``samples`` and ``knots`` where a sample within ``eps`` of a knot is left out (knots win)."""
    samples = np.asarray(samples, float)
    if len(knots):
        near = np.min(np.abs(samples[:, None] - np.asarray(knots, float)[None]), axis=1) < eps
        samples = samples[~near]
    return np.unique(np.concatenate([samples, knots]))


def interp_path(knots_t: np.ndarray, knots_q: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """Joint positions of the piecewise-linear path (knots (K,) s, (K, n) rad) at plan time(s) ``t`` (clipped)."""
    t = np.atleast_1d(np.clip(np.asarray(t, float), knots_t[0], knots_t[-1]))
    return np.stack([np.interp(t, knots_t, knots_q[:, j]) for j in range(knots_q.shape[1])], axis=1)


class StreamPlan:
    """One trajectory cut into chunks that end at rest.

    Args:
        q_start: (n,) rad, where the arm is (plan time 0).
        times_s: (T,) s from now of the waypoints, strictly increasing, > 0.
        q_txn: (T, n) rad waypoints.
        accel_limits: (n,) rad/s^2 acceleration the braking is scaled from (None: each joint's peak
            finite-difference acceleration of this trajectory).
        settings: the stream settings.
    """

    def __init__(self, q_start: np.ndarray, times_s: np.ndarray, q_txn: np.ndarray,
                 accel_limits: np.ndarray | None, settings: StreamSettings) -> None:
        self.settings = settings
        self.knots_t = np.concatenate([[0.0], np.asarray(times_s, float)])
        self.knots_q = np.vstack([np.asarray(q_start, float)[None], np.atleast_2d(np.asarray(q_txn, float))])
        self.duration_s = float(self.knots_t[-1])
        vel = np.diff(self.knots_q, axis=0) / np.diff(self.knots_t)[:, None]
        v_peak = np.max(np.abs(vel), axis=0)
        if accel_limits is None:
            dt_mid = 0.5 * (np.diff(self.knots_t)[1:] + np.diff(self.knots_t)[:-1])
            acc = np.abs(np.diff(vel, axis=0)) / dt_mid[:, None] if len(vel) > 1 else np.zeros((1, len(v_peak)))
            accel_limits = np.maximum(np.max(acc, axis=0, initial=0.0), 1e-3)
        a = settings.brake_fraction * np.asarray(accel_limits, float)
        #: Duration (s) of a braking tail: the slowest joint comes to rest within it.
        self.brake_s = float(max(settings.tail_dt_s, np.max(v_peak / a)))
        #: Longest time (s) the arm keeps moving after the controller received the last chunk.
        self.stop_within_s = float(settings.horizon_s + self.brake_s)

    def chunk(self, t_now: float) -> tuple[np.ndarray, np.ndarray, bool]:
        """The chunk to send at plan time ``t_now`` (s): (times (m,) s from the send instant, joints (m, n) rad,
        whether it is the last chunk, which runs to the end of the trajectory)."""
        s = self.settings
        t0 = t_now + s.lead_s
        final = t_now + s.horizon_s >= self.duration_s
        t_c = self.duration_s if final else t_now + s.horizon_s
        if t0 >= t_c:  # less than lead_s of motion left: one point at the end
            return np.array([max(s.lead_s, t_c - t_now)]), self.knots_q[-1:].copy(), True
        knots = self.knots_t[(self.knots_t >= t0 - MIN_SPACING_S) & (self.knots_t <= t_c)]  # never beyond t_c
        ts = _merge(np.array([t0, t_c]), knots)
        t_c = float(ts[-1])  # a knot just below t_c replaces it: the chunk never outlasts stop_within_s
        qs = interp_path(self.knots_t, self.knots_q, ts)
        rel = ts - t_now
        if final:
            return rel, qs, True
        u, tau = self._tail_times(t_c)
        if len(u):
            rel = np.concatenate([rel, (t_c - t_now) + u])
            qs = np.vstack([qs, interp_path(self.knots_t, self.knots_q, tau)])
        return rel, qs, False

    def _tail_times(self, t_c: float) -> tuple[np.ndarray, np.ndarray]:
        """Tail sample times ``u`` (s after ``t_c``) and the plan times ``tau(u)`` they reach (module docstring)."""
        Tb, dt = self.brake_s, self.settings.tail_dt_s
        n = max(1, int(np.ceil(Tb / dt - 1e-9)))
        u = np.linspace(Tb / n, Tb, n)
        reach = min(t_c + 0.5 * Tb, self.duration_s)  # tau(Tb), or the end of the path inside the tail
        inner = self.knots_t[(self.knots_t > t_c) & (self.knots_t <= reach)]
        if reach < t_c + 0.5 * Tb and (not len(inner) or inner[-1] < reach):
            inner = np.append(inner, reach)
        u_inner = Tb * (1.0 - np.sqrt(np.clip(1.0 - 2.0 * (inner - t_c) / Tb, 0.0, 1.0)))  # tau(u) = knot
        u = _merge(u, u_inner)
        u = u[(u > MIN_SPACING_S) & (u <= (u_inner[-1] if reach < t_c + 0.5 * Tb else Tb) + 1e-12)]
        tau = np.minimum(t_c + u - u**2 / (2.0 * Tb), reach)
        return u, tau


__all__ = ["StreamPlan", "StreamSettings", "interp_path", "worst_case_stop_s"]
