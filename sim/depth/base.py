"""The depth-model interface: one capture view plus what the simulator knows -> a sensor depth image.

A :class:`DepthModel` turns a :class:`DepthScene` (the exact geometry of one view, from the simulator) into
the depth image a D455 would report: float32 z-depth in metres along the colour camera's optical axis,
registered to the colour pixel grid, 0 = no reading (docs/architecture.md data contract). Models are pure
functions of the scene and a ``numpy.random.Generator``; the rig seeds that generator from the trial seed,
the capture index and the view index, so a trial is reproducible.

Frames: ``T_world_cam`` (4, 4) OpenCV axes (x right, y down, z forward), world = robot base, z up, m.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from torm.errors import CaptureError


@dataclass(frozen=True, eq=False)
class DepthScene:
    """What the simulator knows about one view, on the colour camera's pixel grid (H, W).

    Attributes:
        K: (3, 3) colour intrinsics (pixel centres at integer + 0.5).
        T_world_cam: (4, 4) camera-to-world pose, OpenCV axes (m).
        depth_first: (H, W) float32 exact z-depth (m) of the first surface hit, glass included; 0 = nothing.
        depth_opaque: (H, W) float32 exact z-depth (m) of the first *opaque* surface (glass removed); 0 = nothing.
        glass: (H, W) bool, the first surface hit is glass.
        instance: (H, W) int32 instance id of the first surface (0 = not an object).
        renderer: optional handle a model may use to render more of the scene (the stereo model's IR pair).
    """

    K: np.ndarray
    T_world_cam: np.ndarray
    depth_first: np.ndarray
    depth_opaque: np.ndarray
    glass: np.ndarray
    instance: np.ndarray
    renderer: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        hw = self.depth_first.shape
        for name in ("depth_opaque", "glass", "instance"):
            if getattr(self, name).shape != hw:
                raise CaptureError(f"DepthScene.{name} has shape {getattr(self, name).shape}, depth_first {hw}; "
                                   "render every channel at the same size")
        if self.K.shape != (3, 3) or self.T_world_cam.shape != (4, 4):
            raise CaptureError("DepthScene needs K (3, 3) and T_world_cam (4, 4)")

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return self.depth_first.shape  # type: ignore[return-value]


@runtime_checkable
class DepthModel(Protocol):
    """A simulated depth sensor.

    ``name`` is the ``capture.depth_model`` value; ``needs_first_surface`` tells the rig whether to render the
    first-surface depth and ids (the ideal model only needs the opaque pass).
    """

    name: str
    needs_first_surface: bool

    def sensor_depth(self, scene: DepthScene, rng: np.random.Generator) -> np.ndarray:
        """(H, W) float32 sensor z-depth (m), 0 = no reading."""
        ...

    def record(self) -> dict[str, Any]:
        """Every parameter with its source (JSON-ready), for trial records."""
        ...
