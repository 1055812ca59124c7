"""``ideal``: exact z-depth of every opaque surface; glass is invisible (the camera sees straight through it).

This is the simulator's behaviour before the depth models existed: no noise, no range limits, no missing
pixels, and a glass object contributes nothing, so its pixels read the table (or whatever opaque surface
lies behind it along the same ray, without refraction). No real sensor behaves like this.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.depth.base import DepthScene


class IdealDepth:
    """Opaque surfaces exact, glass invisible (see the module docstring)."""

    name = "ideal"
    needs_first_surface = False

    def sensor_depth(self, scene: DepthScene, rng: np.random.Generator) -> np.ndarray:
        """(H, W) float32: ``scene.depth_opaque`` unchanged (``rng`` unused)."""
        return np.asarray(scene.depth_opaque, dtype=np.float32).copy()

    def record(self) -> dict[str, Any]:
        return {"name": self.name, "description": "exact z-depth of opaque surfaces; glass invisible; no noise, "
                "no range limits"}
