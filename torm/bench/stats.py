"""Binomial confidence intervals for success rates (k successes out of n trials).

- :func:`wilson_interval`: Wilson score interval (Wilson 1927, computed by scipy), the standard choice for
  small n and rates near 0 or 1 (it never leaves [0, 1] and is not degenerate at k = 0 or k = n).
- :func:`difference_interval`: Newcombe's hybrid score interval for the difference of two independent
  proportions (Newcombe 1998, method 10), built from the two Wilson intervals.

Both return fractions in [0, 1] (or [-1, 1] for a difference), not percent.
"""

from __future__ import annotations

import math

#: Two-sided 95 % normal quantile.
Z95 = 1.959963984540054


def _check(k: int, n: int) -> None:
    if n < 0 or k < 0 or k > n:
        raise ValueError(f"need 0 <= k <= n successes out of n trials, got k={k}, n={n}")


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval (low, high) for the rate k / n; (0.0, 1.0) when n = 0 (nothing known).

    Computed by scipy (``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")``);
    :func:`wilson_interval_reference` is the closed form it is tested against.

    Args:
        k: successes (0 <= k <= n).
        n: trials.
        z: normal quantile (1.96 for a two-sided 95 % interval).
    """
    _check(k, n)
    if n == 0:
        return 0.0, 1.0
    from scipy.stats import binomtest, norm

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=float(2 * norm.cdf(z) - 1), method="wilson")
    return (0.0 if k == 0 else float(ci.low)), (1.0 if k == n else float(ci.high))


def wilson_interval_reference(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The closed form of :func:`wilson_interval` (Wilson 1927), kept as the slow reference path of the tests."""
    _check(k, n)
    if n == 0:
        return 0.0, 1.0
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / denom
    lo, hi = max(0.0, centre - half), min(1.0, centre + half)
    return (0.0 if k == 0 else lo), (1.0 if k == n else hi)


def difference_interval(k1: int, n1: int, k2: int, n2: int, z: float = Z95) -> tuple[float, float, float]:
    """(difference, low, high) for p1 - p2 with Newcombe's hybrid score interval.

    Args:
        k1, n1: successes and trials of the first run.
        k2, n2: successes and trials of the second run.
        z: normal quantile (1.96 for 95 %).
    """
    _check(k1, n1)
    _check(k2, n2)
    if n1 == 0 or n2 == 0:
        return (float("nan"), -1.0, 1.0)
    p1, p2 = k1 / n1, k2 / n2
    l1, u1 = wilson_interval(k1, n1, z)
    l2, u2 = wilson_interval(k2, n2, z)
    d = p1 - p2
    lo = d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)
    hi = d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)
    return d, max(-1.0, lo), min(1.0, hi)


def format_rate(k: int, n: int, z: float = Z95) -> str:
    """``"k/n (p% [lo-hi%])"`` with the Wilson interval; ``"–"`` when n = 0."""
    if n == 0:
        return "–"
    lo, hi = wilson_interval(k, n, z)
    return f"{k}/{n} ({100.0 * k / n:.0f}% [{100.0 * lo:.0f}-{100.0 * hi:.0f}%])"


__all__ = ["Z95", "difference_interval", "format_rate", "wilson_interval", "wilson_interval_reference"]
