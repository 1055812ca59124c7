"""Captures on disk and image providers (no MuJoCo here; the simulated rig lives in ``sim.cameras.rig``)."""

from torm.capture.io import find_transforms, load_capture, save_capture
from torm.capture.provider import ImageProvider, RecordedProvider, evenly_spaced

__all__ = ["ImageProvider", "RecordedProvider", "evenly_spaced", "find_transforms", "load_capture", "save_capture"]
