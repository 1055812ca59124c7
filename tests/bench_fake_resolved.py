"""The fake trial function of tests/bench_fake_trials.py with a ``check_overrides`` hook that resolves the
overrides into a config with defaults (``DEFAULTS``), like ``torm.bench.trial`` does with TrialConfig: a test
changes a default here to see a run refuse to resume."""

from __future__ import annotations

from typing import Any

from bench_fake_trials import _options
from bench_fake_trials import run as run  # noqa: PLC0414 - re-exported as this module's trial function

DEFAULTS: dict[str, Any] = {"pick": {"grip_force": 130.0}, "success": {"slip_tolerance": 0.02}}


def check_overrides(overrides: tuple[str, ...]) -> dict[str, Any]:
    return {**{k: dict(v) for k, v in DEFAULTS.items()}, "fake": _options(overrides)}
