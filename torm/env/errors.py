"""Errors of the gymnasium / dm_env environments."""

from __future__ import annotations

from torm.errors import TormError


class InvalidActionError(TormError, ValueError):
    """An action is outside the env's action space (wrong shape, NaN, or out of bounds); the message names the bounds.

    Also a ``ValueError`` so generic RL code that catches ``ValueError`` keeps working.
    """
