"""Execution errors that any backend may raise (backend-agnostic, so the pick sequence can catch them)."""

from __future__ import annotations

from torm.errors import ExecutionError


class PhysicsError(ExecutionError):
    """The simulation became invalid (NaN state, MuJoCo warnings, exploding contact forces); the trial aborts.

    Real hardware never raises it. The message names the first symptom seen and the simulated time (s).
    """
