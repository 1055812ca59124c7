"""The interface a perception method implements to run in the harness like a built-in (issue 40).

A method is any object with ``name`` (str), ``version`` (str), ``needs`` (:class:`Needs`) and
``perceive(capture, context) -> Sequence[ObjectEstimate]``. The harness captures only what ``needs`` declares,
calls ``perceive`` once per perception (the first capture and every re-perception), checks the output
(:func:`torm.methods.validate.validate_estimates`) and hands it to the same grasp planner and executor as TORM.

Frames and units: everything is in the **world frame** (the robot base: x forward, z up), **metres**. A capture's
``views[i].T_world_cam`` is the camera-to-world pose in OpenCV axes (x right, y down, z forward), ``K`` pinhole
intrinsics in pixels; ``rgb`` (H, W, 3) uint8, ``sensor_depth`` (H, W) float32 metres (0 or NaN: no return; what a
real depth camera reports, glass mostly missing), ``mask`` (H, W) int32 instance ids (the capture's masks: the
simulator's in simulation, a recorded capture's otherwise), ``reference_rgb`` the empty workspace (reference pass).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from torm.types import Capture, TriMesh

#: what ``Needs.views`` may ask for
VIEW_CHOICES = ("all", "top_down")


@dataclass(frozen=True)
class Needs:
    """What a method reads from a capture; the harness captures (and pays for) nothing else.

    Attributes:
        rgb: the colour images.
        sensor_depth: the depth camera's depth (metres; glass mostly missing, as a real sensor reports it).
        masks: the capture's instance masks (the simulator's in simulation; a method that segments itself says no).
        reference: each view's reference view over the empty workspace.
        views: ``all`` (the capture layout TORM flies) or ``top_down`` (its most top-down view only).
    """

    rgb: bool = True
    sensor_depth: bool = False
    masks: bool = False
    reference: bool = False
    views: str = "all"

    def __post_init__(self) -> None:
        from torm.errors import UnknownNameError

        if self.views not in VIEW_CHOICES:
            raise UnknownNameError("Needs.views", self.views, VIEW_CHOICES)
        if not (self.rgb or self.sensor_depth or self.masks):
            from torm.errors import ConfigError

            raise ConfigError("Needs: a method must read something (rgb, sensor_depth or masks)")

    def channels(self) -> tuple[str, ...]:
        """The capture channels (``sim.cameras.rig.CHANNELS`` names) these needs translate to."""
        return tuple(c for c, on in (("rgb", self.rgb), ("sensor_depth", self.sensor_depth), ("mask", self.masks))
                     if on)

    def as_dict(self) -> dict[str, Any]:
        return {"rgb": self.rgb, "sensor_depth": self.sensor_depth, "masks": self.masks,
                "reference": self.reference, "views": self.views}


@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """One object a method found: surface points (N, 3) m in the world frame, optional outward unit normals
    (N, 3) (estimated from the points when None), an optional watertight mesh (world frame, m) and a confidence
    in [0, 1] (recorded; the planner does not use it)."""

    points_nx3: np.ndarray
    normals_nx3: np.ndarray | None = None
    mesh: TriMesh | None = None
    confidence: float = 1.0


@dataclass(frozen=True, eq=False)
class MethodContext:
    """What the harness tells a method besides the capture.

    Attributes:
        n_points: the surface samples per object the planner expects (the harness resamples to it).
        rng: the trial's random generator (use it for any randomness: trials are seeded).
        table_height: the table top (m, world z) the loop plans with (declared or fitted, never the simulator's).
        workspace_bounds: (2, 3) m, the box objects are searched in (world frame).
        options: the method's options from the trial config (``method_options``).
    """

    n_points: int
    rng: np.random.Generator
    table_height: float
    workspace_bounds: np.ndarray
    options: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class PerceptionMethod(Protocol):
    """The plug-in protocol (structural: no base class needed)."""

    name: str
    version: str
    needs: Needs

    def perceive(self, capture: Capture, context: MethodContext) -> Sequence[ObjectEstimate]: ...
