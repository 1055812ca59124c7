"""``stereo``: an active-stereo D455 simulated end to end (projected dots, two IR cameras, SGBM).

Per view: the left IR camera sits at the colour camera's optical centre with the colour camera's orientation,
the right one ``baseline_m`` (95 mm) along the camera x axis, both at the D455's depth-stream resolution and
FOV; a projector between them casts a fixed random-dot pattern. Both IR images are path traced by the
physically based renderer of ``sim.render`` (Mitsuba 3: glass as a refracting dielectric, so the dots are bent
and reflected by glass as on the real sensor), with the room lights dimmed to ``ambient_scale`` (the IR pass
sees mostly the projector). IR sensor noise follows SAPIEN's simsense: multiplicative speckle (Gamma,
shape 1333.33) and additive thermal noise (sigma 0.25 grey levels). The pair is matched by OpenCV SGBM
(:mod:`sim.depth.stereo_match`, SAPIEN's settings), depth = f B / d, readings outside the D455 range dropped,
and the depth is registered to the colour camera (nearest surface per colour pixel).

Parameters and their sources: ``sim/depth/README.md`` (table "stereo").
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sim.depth.base import DepthScene
from sim.depth.d455 import D455Sensor
from sim.depth.stereo_match import SGBMSettings, depth_from_disparity, disparity, register_depth
from torm.errors import CaptureError, ConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StereoDepthConfig:
    """Active-stereo settings (sources in the module docstring).

    Attributes:
        sensor: the D455 depth imager (baseline, FOV, resolution, range).
        sgbm: the matcher's settings.
        spp: path-tracing samples per pixel of each IR image (Mitsuba's low-discrepancy sampler rounds up to a
            square power of two: 4, 16, 64...).
        max_depth: light bounces (solid glass needs >= 8 for the way through and back).
        dot_density: probability that a texel of the projector pattern is a dot.
        pattern_scale: projector pattern resolution relative to the IR image.
        pattern_blur_px: Gaussian blur of the dots (texels).
        projector_scale: projector irradiance scale (Mitsuba units) and ``ambient_scale`` the room lights' factor.
        exposure: fixed linear gain of both IR images (the same for left and right).
        speckle_shape: Gamma shape of the multiplicative speckle noise (0 = off).
        thermal_sigma: additive Gaussian noise (8-bit grey levels; 0 = off).
        pattern_seed: seed of the dot pattern (one fixed pattern per sensor, like the real projector).
    """

    sensor: D455Sensor = field(default_factory=D455Sensor)
    sgbm: SGBMSettings = field(default_factory=SGBMSettings)
    spp: int = 16
    max_depth: int = 8
    dot_density: float = 0.02
    pattern_scale: float = 2.0
    pattern_blur_px: float = 0.7
    projector_scale: float = 4.0
    ambient_scale: float = 0.05
    exposure: float = 1.0
    speckle_shape: float = 1333.33
    thermal_sigma: float = 0.25
    pattern_seed: int = 455

    def __post_init__(self) -> None:
        if self.spp < 1 or self.max_depth < 1:
            raise ConfigError("stereo.spp and stereo.max_depth must be >= 1")
        side = math.isqrt(self.spp)
        if side * side != self.spp or side & (side - 1):
            raise ConfigError(f"stereo.spp must be a square power of two (4, 16, 64, 256) for the low-discrepancy "
                              f"sampler, got {self.spp}")
        if not 0 < self.dot_density < 1 or not self.pattern_scale > 0 or self.pattern_blur_px < 0:
            raise ConfigError("stereo: dot_density in (0, 1), pattern_scale > 0 and pattern_blur_px >= 0 are required")
        if not (self.projector_scale > 0 and self.ambient_scale >= 0 and self.exposure > 0):
            raise ConfigError("stereo: projector_scale > 0, ambient_scale >= 0 and exposure > 0 are required")
        if self.speckle_shape < 0 or self.thermal_sigma < 0:
            raise ConfigError("stereo: speckle_shape and thermal_sigma must be >= 0 (0 = off)")


def dot_pattern(width: int, height: int, density: float, blur_px: float, seed: int) -> np.ndarray:
    """(H, W, 3) float32 projector irradiance: random dots (1.0) on black, Gaussian-blurred by ``blur_px``."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    img = (rng.random((height, width)) < density).astype(np.float32)
    if blur_px > 0:
        img = gaussian_filter(img, blur_px)
        img /= max(float(img.max()), 1e-6)
    return np.repeat(img[..., None], 3, axis=2)


class StereoDepth:
    """The active-stereo D455 model (see the module docstring). Needs the rig's world (``scene.renderer.world``)."""

    name = "stereo"
    needs_first_surface = False

    def __init__(self, config: StereoDepthConfig | None = None) -> None:
        self.config = config or StereoDepthConfig()
        s = self.config.sensor
        self._pattern = dot_pattern(int(round(s.depth_width * self.config.pattern_scale)),
                                    int(round(s.depth_height * self.config.pattern_scale)),
                                    self.config.dot_density, self.config.pattern_blur_px, self.config.pattern_seed)
        self._renderer: Any = None
        self._world: Any = None
        self.last_timing: dict[str, float] = {}

    # ------------------------------------------------------------------------------------------- geometry
    def ir_K(self) -> np.ndarray:
        """(3, 3) intrinsics of both IR cameras (square pixels, centred principal point)."""
        s = self.config.sensor
        f = s.focal_px
        return np.array([[f, 0.0, s.depth_width / 2], [0.0, f, s.depth_height / 2], [0.0, 0.0, 1.0]])

    def ir_poses(self, T_world_col: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(left, right, projector) camera-to-world poses (OpenCV axes, m) for a colour camera pose."""
        x = T_world_col[:3, 0]
        left = np.asarray(T_world_col, dtype=np.float64).copy()
        right = left.copy()
        right[:3, 3] += self.config.sensor.baseline_m * x
        proj = left.copy()
        proj[:3, 3] += 0.5 * self.config.sensor.baseline_m * x
        return left, right, proj

    def _renderer_for(self, world: Any) -> Any:
        if self._renderer is None or self._world is not world:
            from sim.render.mitsuba_renderer import MitsubaRenderer
            from torm.capture.render_settings import PbrSettings

            self._renderer = MitsubaRenderer(world, PbrSettings(spp=self.config.spp, max_depth=self.config.max_depth,
                                                                denoise="none", exposure=self.config.exposure,
                                                                sampler="ldsampler", integrator="glass_path",
                                                                cache=False))
            self._world = world
        return self._renderer

    def _projector(self, T_world_proj: np.ndarray) -> dict[str, Any]:
        import mitsuba as mi

        from sim.render import cv_to_mitsuba

        s = self.config.sensor
        hfov = 2 * math.degrees(math.atan(0.5 * self._pattern.shape[1] / (s.focal_px * self.config.pattern_scale)))
        return {"type": "projector", "fov": hfov, "scale": float(self.config.projector_scale),
                "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(self._pattern), "raw": True},
                "to_world": cv_to_mitsuba(T_world_proj)}

    # ------------------------------------------------------------------------------------------- images
    def ir_pair(self, world: Any, T_world_col: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The rectified (left, right) uint8 IR images (depth-stream size) of ``world`` with sensor noise."""
        from sim.render.base import RenderCamera

        s = self.config.sensor
        left, right, proj = self.ir_poses(np.asarray(T_world_col, dtype=np.float64))
        K = self.ir_K()
        cams = [RenderCamera(K, left, s.depth_width, s.depth_height, "ir_left"),
                RenderCamera(K, right, s.depth_width, s.depth_height, "ir_right")]
        r = self._renderer_for(world)
        views = r.render(cams, rgb=True, instance=False, extra_emitters={"ir_projector": self._projector(proj)},
                         env_scale=self.config.ambient_scale, area_scale=self.config.ambient_scale,
                         exposure=self.config.exposure)
        out = []
        for v in views:
            g = v.rgb.astype(np.float64).mean(axis=2)
            if self.config.speckle_shape > 0:
                k = self.config.speckle_shape
                g = g * rng.gamma(k, 1.0 / k, size=g.shape)
            if self.config.thermal_sigma > 0:
                g = g + rng.normal(0.0, self.config.thermal_sigma, size=g.shape)
            out.append(np.clip(np.round(g), 0, 255).astype(np.uint8))
        return out[0], out[1]

    def depth_ir(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """(H, W) float32 z-depth (m) on the left IR grid: SGBM, f B / d, range limits."""
        s = self.config.sensor
        z = depth_from_disparity(disparity(left, right, self.config.sgbm), s.focal_px, s.baseline_m)
        z[(z < s.min_range_m) | (z > s.max_range_m)] = 0.0
        return z

    def sensor_depth(self, scene: DepthScene, rng: np.random.Generator) -> np.ndarray:
        """(H, W) float32 sensor z-depth (m) registered to the colour camera of ``scene``; 0 = no reading."""
        world = getattr(scene.renderer, "world", None)
        if world is None:
            raise CaptureError("depth_model 'stereo' needs the simulated world (a SimCameraRig built with from_world)")
        t0 = time.perf_counter()
        left, right = self.ir_pair(world, scene.T_world_cam, rng)
        t1 = time.perf_counter()
        z_ir = self.depth_ir(left, right)
        T_left = self.ir_poses(scene.T_world_cam)[0]
        out = register_depth(z_ir, self.ir_K(), T_left, scene.K, scene.T_world_cam, scene.shape)
        t2 = time.perf_counter()
        self.last_timing = {"render_s": t1 - t0, "match_register_s": t2 - t1}
        log.debug("stereo view: render %.2f s, match + register %.2f s", t1 - t0, t2 - t1)
        return out

    def record(self) -> dict[str, Any]:
        d = asdict(self.config)
        d["sensor"] = self.config.sensor.record()
        d["sgbm"]["P1_opencv"], d["sgbm"]["P2_opencv"] = self.config.sgbm.P1, self.config.sgbm.P2
        d["renderer"] = ("mitsuba 3 (sim.render.MitsubaRenderer), ldsampler, glass_path integrator: camera rays "
                         "refract through glass; projector light reaches what lies behind glass Fresnel-attenuated "
                         "but unbent (a path tracer cannot carry a point projector's light through refraction)")
        return {"name": self.name, **d}
