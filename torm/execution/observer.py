"""Hooks through which an observer (the simulator's judge, a logger) watches a pick without steering it.

:func:`torm.execution.pick.execute_pick` calls these as it moves, the way a person scoring a real trial watches the
robot: it learns when each phase starts and ends, nothing flows back into the decision loop.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from torm.types import Grasp


@runtime_checkable
class PickObserver(Protocol):
    """Receives the pick's events in order: ``attempt_started``, then ``phase_started`` / ``phase_ended`` for each
    phase (``open``, ``pre_grasp``, ``approach``, ``close``, ``lift``, ``translate``, ``lower``, ``release``,
    ``retreat``), then ``attempt_ended`` with the loop's :class:`~torm.execution.pick.PickResult`."""

    def attempt_started(self, grasp: Grasp) -> None: ...

    def phase_started(self, name: str) -> None: ...

    def phase_ended(self, name: str) -> None: ...

    def attempt_ended(self, result: Any) -> None: ...


class ObserverGroup:
    """Several observers as one: every event goes to each observer that has a method for it, in order (the judge
    first, then loggers). One-way, like any observer."""

    _EVENTS = ("attempt_started", "phase_started", "phase_ended", "attempt_ended", "perceived")

    def __init__(self, *observers: Any) -> None:
        self.observers = tuple(o for o in observers if o is not None)

    def __getattr__(self, name: str) -> Any:
        if name not in self._EVENTS or not any(hasattr(o, name) for o in self.observers):
            raise AttributeError(name)

        def forward(*args: Any) -> None:
            for o in self.observers:
                fn = getattr(o, name, None)
                if fn is not None:
                    fn(*args)

        return forward
