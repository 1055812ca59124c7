"""Wilson and Newcombe intervals against published worked examples and invariants."""

from __future__ import annotations

import math

import pytest

from torm.bench.stats import difference_interval, format_rate, wilson_interval


def test_wilson_matches_newcombe_1998_examples():
    # Newcombe (1998), Stat Med 17:857, Table I (method 3, Wilson score without continuity correction).
    lo, hi = wilson_interval(81, 263)
    assert lo == pytest.approx(0.2553, abs=5e-4) and hi == pytest.approx(0.3662, abs=5e-4)
    lo, hi = wilson_interval(15, 148)
    assert lo == pytest.approx(0.0624, abs=5e-4) and hi == pytest.approx(0.1605, abs=5e-4)
    lo, hi = wilson_interval(0, 20)
    assert lo == 0.0 and hi == pytest.approx(0.1611, abs=5e-4)
    lo, hi = wilson_interval(1, 29)
    assert lo == pytest.approx(0.0061, abs=5e-4) and hi == pytest.approx(0.1718, abs=5e-4)


def test_wilson_invariants():
    for n in (1, 2, 7, 10, 57):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0
            lo2, hi2 = wilson_interval(n - k, n)  # symmetric under k -> n - k
            assert lo2 == pytest.approx(1 - hi) and hi2 == pytest.approx(1 - lo)
    assert wilson_interval(10, 10)[1] == 1.0 and wilson_interval(0, 10)[0] == 0.0
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="0 <= k <= n"):
        wilson_interval(3, 2)


def test_newcombe_difference_example():
    # Newcombe (1998), Stat Med 17:873, Table II example (a): 56/70 vs 48/80 -> 0.2000 (0.0524, 0.3339).
    d, lo, hi = difference_interval(56, 70, 48, 80)
    assert d == pytest.approx(0.2)
    assert lo == pytest.approx(0.0524, abs=5e-4) and hi == pytest.approx(0.3339, abs=5e-4)
    d, lo, hi = difference_interval(5, 10, 5, 10)
    assert d == 0.0 and lo < 0 < hi and lo == pytest.approx(-hi)
    d, lo, hi = difference_interval(0, 0, 1, 2)  # nothing known about the first rate
    assert math.isnan(d) and (lo, hi) == (-1.0, 1.0)
    with pytest.raises(ValueError):
        difference_interval(1, 0, 1, 2)


def test_format_rate():
    assert format_rate(8, 10).startswith("8/10 (80% [")
    assert format_rate(0, 0) == "–"


def test_scipy_wilson_equals_the_closed_form_reference():
    from torm.bench.stats import wilson_interval_reference

    for n in (1, 2, 5, 10, 17, 43, 80, 1000):
        for k in range(0, n + 1, max(1, n // 7)):
            for z in (1.0, 1.959963984540054, 2.576):
                assert wilson_interval(k, n, z) == pytest.approx(wilson_interval_reference(k, n, z), abs=1e-12)
