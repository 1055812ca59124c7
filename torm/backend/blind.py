"""The decision loop's view of a backend: what a real robot offers, nothing a simulator knows besides.

:class:`LoopBackend` wraps any backend and forwards only the names in :data:`LOOP_API` (cameras, the arm, the
gripper, the clock, the robot's own model and the declared calibration). Everything else, the simulator's
``ground_truth``, its ``world``, its realism record, is refused with :class:`GroundTruthAccessError`, so perception,
planning and execution cannot read the answer by accident. Ground truth belongs to the judge (``sim/judge.py``),
which scores a trial afterwards from the physics, as an observer scores a real one.
"""

from __future__ import annotations

from typing import Any

from torm.backend.calibration import Calibration
from torm.errors import TormError

#: The names the loop may use on a backend (a real backend offers all of them; optional ones may be missing).
LOOP_API: frozenset[str] = frozenset({
    "name", "arm", "gripper", "clock", "robot_config", "robot_model", "limits",
    "capture", "capture_views", "capture_poses", "operator_confirm",
})


class GroundTruthAccessError(TormError):
    """The decision loop asked a backend for something only a simulator knows.

    Deliberately not an ``AttributeError``: ``hasattr`` / ``getattr(..., default)`` on a refused name raise too,
    so no probe can fall back silently."""


class LoopBackend:
    """A backend as the decision loop sees it (see the module docstring).

    Args:
        backend: the simulated or real backend.
        calibration: the cell's declared calibration (default: ``backend.calibration()`` when it offers one, else
            a table at z = 0 with no fixtures, stated as such).
    """

    def __init__(self, backend: Any, calibration: Calibration | None = None) -> None:
        object.__setattr__(self, "_backend", backend)
        if calibration is None:
            declare = getattr(backend, "calibration", None)
            calibration = declare() if callable(declare) else Calibration(source="default: table at z = 0")
        object.__setattr__(self, "calibration", calibration)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in LOOP_API:  # dunders: Python's own protocol probes (copy, pickle)
            return getattr(object.__getattribute__(self, "_backend"), name)  # AttributeError when it lacks one
        raise GroundTruthAccessError(
            f"the decision loop may not read backend.{name}: it sees only what a real robot offers "
            f"({', '.join(sorted(LOOP_API | {'calibration'}))}); ground truth is the judge's (sim/judge.py)")

    def __setattr__(self, name: str, value: Any) -> None:
        raise GroundTruthAccessError(f"the decision loop may not change backend.{name}")

    def __dir__(self) -> list[str]:
        b = object.__getattribute__(self, "_backend")
        return sorted(n for n in LOOP_API if hasattr(b, n)) + ["calibration"]
