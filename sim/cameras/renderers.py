"""Pick an image renderer of the simulated camera by name (``capture.renderer``).

- ``mujoco``: :class:`sim.cameras.mujoco_renderer.MujocoRenderer`, MuJoCo's OpenGL rasteriser through the camera rig
  (glass as grey alpha blending);
- ``pbr``: :class:`sim.render.MitsubaRenderer`, Mitsuba 3 path tracing (:mod:`sim.render`).

It sits above both: the MuJoCo renderer is built on :mod:`sim.cameras.rig`, which itself uses the
rendering package's camera types (:mod:`sim.render.base`), so neither package names the other's renderer.
"""

from __future__ import annotations

from typing import Any

from sim.render.base import Renderer
from torm.capture.render_settings import PbrSettings
from torm.errors import UnknownNameError
from torm.vocabulary import RENDERERS


def make_renderer(name: str, world: Any, settings: PbrSettings | None = None, **kwargs: Any) -> Renderer:
    """The renderer ``name`` (``mujoco`` | ``pbr``) bound to ``world``; ``settings`` apply to ``pbr``."""
    if name == "mujoco":
        from sim.cameras.mujoco_renderer import MujocoRenderer

        return MujocoRenderer(world, **kwargs)
    if name == "pbr":
        from sim.render.mitsuba_renderer import MitsubaRenderer

        return MitsubaRenderer(world, settings, **kwargs)
    raise UnknownNameError("capture.renderer", name, RENDERERS)


__all__ = ["make_renderer"]
