"""The MuJoCo rasteriser behind the :class:`~sim.render.base.Renderer` interface (today's camera-rig path).

RGB is MuJoCo's OpenGL render (glass = alpha blending, no refraction); instance ids are its segmentation pass
mapped through ``geom_to_instance``. One :class:`sim.cameras.rig.SimCameraRig` (one GL context) per image size.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import mujoco

from sim.cameras.rig import CameraRigConfig, SimCameraRig
from sim.render.base import RenderCamera, RenderedView


class MujocoRenderer:
    """Renders a world with MuJoCo's offscreen rasteriser (robot and collision geoms hidden, like the rig).

    Args:
        world: a ``sim.world.World`` (``model``, ``data``, ``geom_to_instance``...).
        rig_config: base ``CameraRigConfig`` (shadows, reflections); the image size comes from each camera.
    """

    name = "mujoco"

    def __init__(self, world: Any, rig_config: Any = None) -> None:
        self.world = world
        self.rig_config = rig_config
        self._rigs: dict[tuple[int, int], Any] = {}

    def _rig(self, width: int, height: int) -> Any:
        rig = self._rigs.get((width, height))
        if rig is None:
            base = self.rig_config or CameraRigConfig()
            cfg = replace(base, width=width, height=height, scale=1.0)
            rig = self._rigs[(width, height)] = SimCameraRig.from_world(self.world, cfg)
        return rig

    def render(self, cameras: Sequence[RenderCamera], *, rgb: bool = True, instance: bool = True
               ) -> list[RenderedView]:
        """One view per camera: MuJoCo RGB and instance masks of the world's current state."""
        chans = (["rgb"] if rgb else []) + (["mask"] if instance else [])
        out = []
        for cam in cameras:
            arrays = self._rig(cam.width, cam.height).render_arrays(cam.T_world_cam, cam.K, chans) if chans else {}
            out.append(RenderedView(arrays.get("rgb"), arrays.get("mask"),
                                    {"renderer": "mujoco", "mujoco": mujoco.__version__}))
        return out

    def describe(self) -> str:
        return f"mujoco {mujoco.__version__} offscreen"

    def close(self) -> None:
        for rig in self._rigs.values():
            rig.close()
        self._rigs.clear()
