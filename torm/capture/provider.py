"""Image providers: anything that returns a multi-view :class:`~torm.types.Capture` of the workspace.

Implementations: :class:`RecordedProvider` (a capture folder on disk), ``sim.cameras.rig.SimCameraRig``
(MuJoCo renders) and the real-camera provider of ``torm.hardware``. The pipeline only sees this
protocol, so the image source can be swapped without touching it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from torm.capture.io import find_transforms, load_capture
from torm.errors import CaptureError
from torm.types import Capture

log = logging.getLogger(__name__)


@runtime_checkable
class ImageProvider(Protocol):
    """A source of multi-view captures (poses in the world frame, OpenCV axes, metres)."""

    def capture(self, n_views: int | None = None) -> Capture:
        """Capture the workspace from ``n_views`` views (default: the provider's own count)."""
        ...


def evenly_spaced(n_total: int, n_views: int) -> list[int]:
    """``n_views`` indices spread evenly over ``range(n_total)`` (first and last included when n_views > 1)."""
    if not 1 <= n_views <= n_total:
        raise CaptureError(f"cannot take {n_views} views from a capture of {n_total}; use 1..{n_total}")
    if n_views == 1:
        return [0]
    return [int(round(x)) for x in np.linspace(0, n_total - 1, n_views)]


class RecordedProvider:
    """Replays a capture folder (``transforms.json`` convention, see :mod:`torm.capture.io`).

    Args:
        folder: the capture folder (or its transforms JSON file).
        views: optional frame indices to keep (in that order); default all frames.

    ``capture(n_views)`` returns ``n_views`` evenly spaced views of the kept ones (all by default).
    The folder is read once, on the first call, and cached.
    """

    def __init__(self, folder: str | Path, views: Sequence[int] | None = None) -> None:
        self.folder = Path(folder)
        self.transforms = find_transforms(self.folder)  # fail early when the folder is wrong
        self.views = None if views is None else [int(i) for i in views]
        self._cache: Capture | None = None

    def _load(self) -> Capture:
        if self._cache is None:
            log.info("loading capture %s", self.transforms)
            self._cache = load_capture(self.folder, self.views)
        return self._cache

    def capture(self, n_views: int | None = None) -> Capture:
        """The recorded capture, or ``n_views`` evenly spaced views of it."""
        cap = self._load()
        if n_views is None or n_views == len(cap):
            return cap
        return cap.subset(evenly_spaced(len(cap), n_views))
