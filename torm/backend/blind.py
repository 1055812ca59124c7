"""The decision loop's view of a backend: what a real robot offers, nothing a simulator knows besides.

:class:`LoopBackend` wraps any backend and forwards only the names in :data:`LOOP_API` (cameras, the arm, the
gripper, the clock, the robot's own model and the declared calibration). Everything else, the simulator's
``ground_truth``, its ``world``, its realism record, is refused with :class:`GroundTruthAccessError`, so perception,
planning and execution cannot read the answer by accident. Ground truth belongs to the judge (``sim/judge.py``),
which scores a trial afterwards from the physics, as an observer scores a real one.

Two channels besides the backend's attributes are closed the same way:

- **captures**: every capture the loop receives passes :func:`without_ground_truth` (no instance masks, no ideal
  depth, no object ids, names or count, no table height: what a real RGB-D camera gives is colour, sensor depth and
  the calibrated poses). The full capture goes to ``truth_sink`` (the judge's), for scoring after the fact. The
  simulation-only methods that are defined on the simulator's masks are declared exceptions (``grant_masks``:
  the ``gt`` and ``noisy`` segmenters, the ``oracle`` and the depth baselines, which cut with the capture's masks);
- **the arm, gripper and clock objects**: forwarded behind :class:`PublicOnly`, which refuses their private
  attributes (``backend.gripper._sim.world`` would reach the simulator).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from torm.backend.calibration import Calibration
from torm.errors import TormError
from torm.types import Capture

#: The names the loop may use on a backend (a real backend offers all of them; optional ones may be missing).
LOOP_API: frozenset[str] = frozenset({
    "name", "arm", "gripper", "clock", "robot_config", "robot_model", "limits",
    "capture", "capture_views", "capture_poses", "operator_confirm",
})
#: Backend objects the loop receives behind :class:`PublicOnly`.
WRAPPED: frozenset[str] = frozenset({"arm", "gripper", "clock"})
#: Capture metadata keys that describe the simulator's truth (removed by :func:`without_ground_truth`).
TRUTH_METADATA: frozenset[str] = frozenset({"mask_source", "objects", "object_poses", "occlusion"})


class GroundTruthAccessError(TormError):
    """The decision loop asked a backend for something only a simulator knows.

    Deliberately not an ``AttributeError``: ``hasattr`` / ``getattr(..., default)`` on a refused name raise too,
    so no probe can fall back silently."""


def without_ground_truth(capture: Capture) -> Capture:
    """``capture`` as a real robot's camera gives it: each view keeps its colour image, sensor depth, reference
    pass, intrinsics and pose; instance masks (``mask``) and ideal depth (``depth``) are dropped, and so are the
    capture's object ids, names and table height and the metadata in :data:`TRUTH_METADATA`
    (``metadata["ground_truth"] = "withheld"`` says so).

    Raises:
        GroundTruthAccessError: a view has no colour image, so only its ground-truth channels gave it a size (a
            capture made for a simulation-only method: grant it the masks instead).
    """
    views = []
    for i, v in enumerate(capture.views):
        if v.rgb is None:
            raise GroundTruthAccessError(
                f"view {i} ({v.name!r}) has no colour image: only the simulator's masks or ideal depth describe it, "
                "which the loop may not read; capture RGB, or run a method declared to use them (gt / noisy "
                "segmenter, oracle, depth baselines)")
        views.append(dataclasses.replace(v, mask=None, depth=None))
    meta = {k: v for k, v in capture.metadata.items() if k not in TRUTH_METADATA}
    meta["ground_truth"] = "withheld"
    return dataclasses.replace(capture, views=tuple(views), object_ids=(), object_names=(), table_height=None,
                               metadata=meta)


class PublicOnly:
    """``obj`` with its private attributes (names starting with ``_``) refused: the loop's handle on a backend's arm,
    gripper or clock, whose private fields lead to the simulator. Everything public is forwarded unchanged."""

    __slots__ = ("_obj", "_what")

    def __init__(self, obj: Any, what: str) -> None:
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_what", what)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_") and not name.startswith("__"):
            raise GroundTruthAccessError(f"the decision loop may not read backend.{self._what}.{name}: private fields "
                                         "of a backend object lead to the simulator; use its public methods")
        return getattr(object.__getattribute__(self, "_obj"), name)

    def __setattr__(self, name: str, value: Any) -> None:
        raise GroundTruthAccessError(f"the decision loop may not change backend.{self._what}.{name}")

    def __repr__(self) -> str:
        return f"PublicOnly({object.__getattribute__(self, '_obj')!r})"


class LoopBackend:
    """A backend as the decision loop sees it (see the module docstring).

    Args:
        backend: the simulated or real backend.
        calibration: the cell's declared calibration (default: ``backend.calibration()`` when it offers one, else
            a table at z = 0 with no fixtures, stated as such).
        grant_masks: hand captures over with the simulator's masks and ideal depth (the declared simulation-only
            methods, :func:`torm.loop.grants_masks`); False strips them (:func:`without_ground_truth`).
        truth_sink: called with every full capture before the loop gets its copy (the judge's record of what the
            cameras saw, for scoring after the fact); None = nobody keeps it.
    """

    def __init__(self, backend: Any, calibration: Calibration | None = None, *, grant_masks: bool = False,
                 truth_sink: Callable[[Capture], None] | None = None) -> None:
        object.__setattr__(self, "_backend", backend)
        if calibration is None:
            declare = getattr(backend, "calibration", None)
            calibration = declare() if callable(declare) else Calibration(source="default: table at z = 0")
        object.__setattr__(self, "calibration", calibration)
        object.__setattr__(self, "grant_masks", bool(grant_masks))
        object.__setattr__(self, "_sink", truth_sink)

    def _hand_over(self, capture: Capture) -> Capture:
        sink = object.__getattribute__(self, "_sink")
        if sink is not None:
            sink(capture)
        return capture if object.__getattribute__(self, "grant_masks") else without_ground_truth(capture)

    def capture(self, *args: Any, **kwargs: Any) -> Capture:
        """The backend's capture, as the loop may see it (module docstring)."""
        return self._hand_over(object.__getattribute__(self, "_backend").capture(*args, **kwargs))

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in LOOP_API:  # dunders: Python's own protocol probes (copy, pickle)
            value = getattr(object.__getattribute__(self, "_backend"), name)  # AttributeError when it lacks one
            if name == "capture_views":
                return lambda *a, **k: self._hand_over(value(*a, **k))
            return PublicOnly(value, name) if name in WRAPPED and value is not None else value
        raise GroundTruthAccessError(
            f"the decision loop may not read backend.{name}: it sees only what a real robot offers "
            f"({', '.join(sorted(LOOP_API | {'calibration'}))}); ground truth is the judge's (sim/judge.py)")

    def __setattr__(self, name: str, value: Any) -> None:
        raise GroundTruthAccessError(f"the decision loop may not change backend.{name}")

    def __dir__(self) -> list[str]:
        b = object.__getattribute__(self, "_backend")
        return sorted(n for n in LOOP_API if hasattr(b, n)) + ["calibration"]
