"""Physically based rendering of the simulated camera, and the renderer interface both renderers implement.

One interface (:class:`Renderer`): a renderer is bound to a world and renders its *current* state (objects
where physics put them) for a list of :class:`RenderCamera` (``K`` (3, 3) px, ``T_world_cam`` (4, 4) OpenCV axes
in metres, ``width``, ``height``), returning one :class:`RenderedView` per camera: ``rgb`` (H, W, 3) uint8 and
``instance`` (H, W) int32 (0 background, k = object k). ``capture.renderer`` picks one for the camera rig
(:func:`sim.cameras.renderers.make_renderer`):

- ``mujoco`` (:class:`sim.cameras.mujoco_renderer.MujocoRenderer`, built on the camera rig, so it lives above this
  package): MuJoCo's OpenGL rasteriser (glass as grey alpha blending).
- ``pbr`` (:class:`MitsubaRenderer`): Mitsuba 3 path tracing on the CPU (``llvm_ad_rgb`` with Debian's
  ``libllvm19``, ``scalar_rgb`` fallback): glass as a smooth dielectric (IOR per object), diffuse opaque
  objects, a table texture and lighting randomised from the layout seed, an exact first-hit instance-id
  pass, and an on-disk render cache. Settings: :class:`torm.capture.render_settings.PbrSettings`.

With ``renderer=pbr`` the rig still takes depth and the capture's instance masks from MuJoCo's segmentation
pass; only the RGB images come from the path tracer.

Extending the PBR scene (e.g. an IR projector for active stereo)::

    import mitsuba as mi
    from sim.render import MitsubaRenderer, PbrSettings, RenderCamera, cv_to_mitsuba

    r = MitsubaRenderer(world, PbrSettings(spp=64, denoise="none"))
    projector = {"type": "projector", "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(dots_hxwx3),
                                                     "raw": True},
                 "fov": 87.0, "scale": 50.0, "to_world": cv_to_mitsuba(T_world_projector)}  # OpenCV pose
    left, right = r.render([cam_left, cam_right], extra_emitters={"projector": projector},
                           env_scale=0.05, area_scale=0.0, exposure=1.0)
    ir = left.rgb.mean(axis=2)          # monochrome

Lower-level pieces: :func:`describe_world` (plain description of the rendered geoms; its digest keys the
cache), :func:`build_scene_dict` (the Mitsuba dict: keys ``integrator``, ``env``, ``area_light_<i>``,
``table_top``, ``table_body``, ``geom_<name>``; edit it before ``mi.load_dict``), :func:`sensor_dict` (the
OpenCV -> Mitsuba camera conversion; :func:`cv_to_mitsuba` for any other OpenCV-posed sensor or projector),
:func:`render_linear` (float32 linear radiance of one camera),
:func:`tone_map`, :func:`denoise`, :func:`instance_ids`, :func:`sample_lighting` / :data:`LIGHTING_RANGES`,
:func:`table_texture`, :class:`RenderCache`. Transforms for Mitsuba: an OpenCV pose ``T`` becomes
``T @ diag(-1, -1, 1, 1)`` (see :mod:`sim.render.mitsuba_renderer`).
"""

from __future__ import annotations

from typing import Any

from sim.render.base import RenderCamera, RenderedView, Renderer, RenderError
from sim.render.cache import RenderCache, cache_key, cache_root
from sim.render.lighting import LIGHTING_RANGES, Lighting, sample_lighting
from sim.render.textures import TABLE_RANGES, table_texture
from torm.capture.render_settings import PbrSettings

__all__ = [
    "LIGHTING_RANGES", "Lighting", "MitsubaRenderer", "PbrSettings", "RenderCache", "RenderCamera",
    "RenderError", "RenderedView", "Renderer", "TABLE_RANGES", "auto_exposure_gain", "build_scene_dict", "cache_key",
    "cache_root", "cv_to_mitsuba", "denoise", "describe_world", "instance_ids", "render_linear",
    "sample_lighting", "sensor_dict", "table_texture", "tone_map",
]

_LAZY = {
    "MitsubaRenderer": "sim.render.mitsuba_renderer", "render_linear": "sim.render.mitsuba_renderer",
    "cv_to_mitsuba": "sim.render.mitsuba_renderer", "auto_exposure_gain": "sim.render.mitsuba_renderer",
    "sensor_dict": "sim.render.mitsuba_renderer", "tone_map": "sim.render.mitsuba_renderer",
    "denoise": "sim.render.mitsuba_renderer", "instance_ids": "sim.render.mitsuba_renderer",
    "describe_world": "sim.render.scene",
    "build_scene_dict": "sim.render.scene",
}


def __getattr__(name: str) -> Any:  # lazy: importing sim.render does not import MuJoCo GL or Mitsuba
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sim.render' has no attribute {name!r}")
