"""Simulated image provider: a ring of virtual D455-like cameras on the upper hemisphere.

The rig renders, per view, an RGB image, the ideal metric z-depth (first surface hit, glass
included), the *sensor* depth a real depth camera would report (made by the rig's depth model,
:mod:`sim.depth`: ``ideal`` = exact opaque depth with glass invisible, the default; ``statistical`` /
``stereo`` = a D455 that fails on glass) and a ground-truth instance mask (0 background, k = object k).

RGB can come from another renderer (``rgb_renderer``: a :class:`sim.render.Renderer`, e.g. the physically based
path tracer of ``capture.renderer: pbr``); depth, sensor depth and instance masks always come from MuJoCo.

Conventions
-----------
- World frame = robot base frame, z up, metres. Poses are ``T_world_cam`` (4, 4) in **OpenCV**
  camera axes (x right, y down, z forward).
- Intrinsics ``K``: fx = fy = (W/2) / tan(hfov/2), cx = W/2, cy = H/2. Pixel ``(u, v)`` with integer
  index ``(i, j)`` covers ``[i, i+1) x [j, j+1)``: a point projecting to ``uv`` lies in pixel
  ``floor(uv)`` (pixel centres at ``i + 0.5``, the OpenGL rasterisation convention).
- Depth is z-depth along the optical axis in metres; 0 = no surface (background).
- Geom groups (see CONTEXT.md): 0 environment, 1 robot, 2 glass objects, 3 collision, 4 opaque
  objects. Every render hides groups 1 and 3; sensor depth additionally hides group 2. Sites,
  tendons, skins and flexes are never drawn.

Camera layout
-------------
Views sit on a spherical band of radius ``radius`` around ``centre``, between ``elevation_min_deg``
and ``elevation_max_deg`` above the table plane, laid out as a Fibonacci spiral (equal-area in
elevation: z spaced uniformly in ``sin(elevation)``, azimuth advancing by the golden angle). The
layout is deterministic and needs no seed. Every camera looks at ``centre + (0, 0, target_height)``
(default: the workspace centre on the table) with the image's up direction close to world +z.
Defaults: radius 0.5 m, elevations 20..80 deg (the paper's hemisphere without the grazing and
the straight-down views).

Geometry limit: at 0.5 m a 60 deg vertical FOV cannot hold the whole 0.4 x 0.4 m object workspace
from mid/high elevations (the workspace diagonal spans up to ~80 deg vertically there; no camera
roll fixes it). Objects near the centre are seen by every view; the outer corners of the object
workspace (x 0.35..0.75, y -0.2..0.2, z 0..0.15 m) are inside the image in about 56% of the default
views (:func:`workspace_coverage` computes this per view). The scenario layouts keep objects nearer
the centre: over rw3/rw4/rw6/rw7/rw8, seeds 0-2, an object touched the image border in at most 2%
of the views. Use a larger ``radius`` when objects are spread to the workspace edges.

Any pinhole ``K`` without skew can be rendered (:meth:`SimCameraRig.render_view`), including
fx != fy and an off-centre principal point, e.g. a real D455 calibration.

Speed
-----
One offscreen GL context per rig, reused for every view. ``model.vis.quality.offsamples`` is set to
0 (no multisampling) and shadows/reflections are off by default (4-7x faster RGB on llvmpipe).
Depth and mask come out of *one* segmentation pass (colour buffer = ids, depth buffer = depth);
sensor depth needs a second id pass with glass hidden. The rig mutates ``model.vis`` (offscreen
buffer size, offsamples) and, only transiently inside :meth:`SimCameraRig.render_solo_masks`,
``model.geom_group``.
"""

from __future__ import annotations

import logging
import math
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from torm.runtime import ensure_headless_gl

ensure_headless_gl()  # MuJoCo picks its GL backend when first imported: default to EGL unless MUJOCO_GL is set

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from sim.workspace import WORKSPACE_BOUNDS  # noqa: E402
from torm.errors import CaptureError, ConfigError  # noqa: E402
from torm.geometry import look_at_cv  # noqa: E402
from torm.types import CameraView, Capture  # noqa: E402

log = logging.getLogger(__name__)

#: Channels a rig can render; ``rgb`` or ``mask`` must be among the requested ones.
CHANNELS: tuple[str, ...] = ("rgb", "depth", "sensor_depth", "mask")

#: Geom groups: environment, robot, glass, collision, opaque objects (CONTEXT.md).
GROUP_ENV, GROUP_ROBOT, GROUP_GLASS, GROUP_COLLISION, GROUP_OPAQUE = 0, 1, 2, 3, 4
#: Group used transiently to isolate one object for solo renders (never used by scenes).
_GROUP_SOLO = 5


@dataclass(frozen=True)
class CameraRigConfig:
    """Layout and intrinsics of the simulated multi-view rig.

    Attributes:
        n_views: number of views.
        radius: distance (m) from each camera to ``centre``.
        centre: (3,) world point (m) the views are arranged around (workspace centre on the table).
        target_height: the cameras look at ``centre + (0, 0, target_height)`` (m).
        width, height: nominal image size in pixels (D455 colour stream 1280x720).
        hfov_deg: horizontal field of view in degrees (91.5: the paper's virtual D455; 60.0 vertical at 16:9).
        elevation_min_deg, elevation_max_deg: elevation band above the table plane (deg).
        scale: multiplies width and height (e.g. 0.5 -> 640x360); the FOV is kept.
        shadows, reflections: render shadows / reflections in RGB (slow on CPU; off by default).
        channels: default channels to render (subset of :data:`CHANNELS`).
    """

    n_views: int = 50
    radius: float = 0.5
    centre: tuple[float, float, float] = (0.55, 0.0, 0.0)
    target_height: float = 0.0
    width: int = 1280
    height: int = 720
    hfov_deg: float = 91.5
    elevation_min_deg: float = 20.0
    elevation_max_deg: float = 80.0
    scale: float = 1.0
    shadows: bool = False
    reflections: bool = False
    channels: tuple[str, ...] = CHANNELS

    def __post_init__(self) -> None:
        if self.n_views < 1:
            raise ConfigError(f"camera_rig.n_views must be >= 1, got {self.n_views}")
        if not self.radius > 0:
            raise ConfigError(f"camera_rig.radius must be > 0 m, got {self.radius}")
        if len(self.centre) != 3 or not all(math.isfinite(c) for c in self.centre):
            raise ConfigError(f"camera_rig.centre must be 3 finite numbers (m), got {self.centre}")
        object.__setattr__(self, "centre", tuple(float(c) for c in self.centre))
        if not 0 < self.hfov_deg < 170:
            raise ConfigError(f"camera_rig.hfov_deg must be in (0, 170) degrees, got {self.hfov_deg}")
        if not -89.0 <= self.elevation_min_deg <= self.elevation_max_deg <= 89.0:
            raise ConfigError(
                "camera_rig elevations must satisfy -89 <= elevation_min_deg <= elevation_max_deg <= 89, got "
                f"{self.elevation_min_deg}..{self.elevation_max_deg}"
            )
        if not self.scale > 0:
            raise ConfigError(f"camera_rig.scale must be > 0, got {self.scale}")
        if self.image_width < 8 or self.image_height < 8:
            raise ConfigError(
                f"camera_rig image size {self.image_width}x{self.image_height} is too small; use at least 8x8 pixels"
            )
        chans = tuple(self.channels)
        bad = [c for c in chans if c not in CHANNELS]
        if bad or not ({"rgb", "mask"} & set(chans)):
            raise ConfigError(
                f"camera_rig.channels {chans} must be a subset of {CHANNELS} containing 'rgb' or 'mask'"
            )
        object.__setattr__(self, "channels", chans)

    @property
    def image_width(self) -> int:
        """Rendered width in pixels (``width * scale``, rounded)."""
        return int(round(self.width * self.scale))

    @property
    def image_height(self) -> int:
        """Rendered height in pixels (``height * scale``, rounded)."""
        return int(round(self.height * self.scale))

    @property
    def fx(self) -> float:
        """Focal length in pixels (fx = fy) at the rendered size."""
        return 0.5 * self.image_width / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view in degrees at the rendered size."""
        return math.degrees(2 * math.atan(0.5 * self.image_height / self.fx))

    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsics of every view: fx = fy, principal point at the image centre."""
        f = self.fx
        return np.array([[f, 0.0, self.image_width / 2], [0.0, f, self.image_height / 2], [0.0, 0.0, 1.0]])

    def poses(self, n_views: int | None = None) -> np.ndarray:
        """(V, 4, 4) camera-to-world poses (OpenCV axes) of the Fibonacci layout; see the module docstring."""
        return hemisphere_poses(
            n_views or self.n_views, self.radius, self.centre, self.elevation_min_deg, self.elevation_max_deg,
            self.target_height,
        )


def hemisphere_poses(
    n_views: int,
    radius: float,
    centre: Sequence[float],
    elevation_min_deg: float,
    elevation_max_deg: float,
    target_height: float = 0.0,
) -> np.ndarray:
    """(V, 4, 4) OpenCV camera-to-world poses on a Fibonacci spiral over a spherical band.

    View i sits at elevation asin(z_i), z_i = sin(e_min) + (i + 0.5)/V (sin(e_max) - sin(e_min)), and
    azimuth i * golden angle, at ``radius`` (m) from ``centre`` (m); it looks at
    ``centre + (0, 0, target_height)`` with image-up close to world +z. Deterministic (no seed).
    """
    c = np.asarray(centre, dtype=np.float64)
    s0, s1 = math.sin(math.radians(elevation_min_deg)), math.sin(math.radians(elevation_max_deg))
    golden = math.pi * (3.0 - math.sqrt(5.0))
    target = c + np.array([0.0, 0.0, target_height])
    out = np.empty((n_views, 4, 4))
    for i in range(n_views):
        z = s0 + (i + 0.5) / n_views * (s1 - s0)
        el = math.asin(z)
        az = i * golden
        eye = c + radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out[i] = look_at_cv(eye, target)
    return out


def workspace_coverage(
    config: CameraRigConfig, bounds: np.ndarray | None = None, n_views: int | None = None
) -> np.ndarray:
    """(V,) bool: whether all 8 corners of the box ``bounds`` (2, 3) m project inside each view's image."""
    b = np.asarray(WORKSPACE_BOUNDS if bounds is None else bounds, dtype=np.float64)
    corners = np.array([[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    K, W, H = config.K(), config.image_width, config.image_height
    ok = []
    for T in config.poses(n_views):
        p = (corners - T[:3, 3]) @ T[:3, :3]
        uv = p[:, :2] / p[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
        ok.append(bool(np.all(p[:, 2] > 0) and np.all((uv >= 0) & (uv <= [W, H]))))
    return np.array(ok)


def _gl_camera_from_cv(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV camera-to-world pose -> MuJoCo GL camera (pos, forward, up); GL cameras look along -z, +y up."""
    R = T_world_cam[:3, :3]
    return T_world_cam[:3, 3].copy(), R[:, 2].copy(), -R[:, 1].copy()


class _Offscreen:
    """One EGL/OSMesa context + MuJoCo render context, reused for every render of a rig."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int) -> None:
        self.width, self.height = width, height
        vis = model.vis
        vis.global_.offwidth = max(int(vis.global_.offwidth), width)
        vis.global_.offheight = max(int(vis.global_.offheight), height)
        vis.quality.offsamples = 0
        self.gl = mujoco.GLContext(width, height)
        self.gl.make_current()
        self.con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.con)
        self.con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.rect = mujoco.MjrRect(0, 0, width, height)
        self.scene = mujoco.MjvScene(model, maxgeom=max(2000, 4 * model.ngeom + 500))
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._depth = np.empty((height, width), np.float32)

    def close(self) -> None:
        if self.con is not None:
            self.con.free()
            self.con = None
        if self.gl is not None:
            self.gl.free()
            self.gl = None

    def render(self, ids: bool, want_rgb: bool, want_depth: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Render the current scene (``ids``: segmentation colours); returns (rgb, raw depth) in image row order."""
        if self.con is None:
            raise CaptureError("the camera rig was closed; create a new SimCameraRig")
        self.gl.make_current()
        flags = self.scene.flags
        seg, idc = mujoco.mjtRndFlag.mjRND_SEGMENT, mujoco.mjtRndFlag.mjRND_IDCOLOR
        flags[seg] = flags[idc] = 1 if ids else 0
        mujoco.mjr_render(self.rect, self.scene, self.con)
        mujoco.mjr_readPixels(self._rgb if want_rgb else None, self._depth if want_depth else None, self.rect, self.con)
        flags[seg] = flags[idc] = 0
        rgb = np.flipud(self._rgb).copy() if want_rgb else None
        depth = np.flipud(self._depth).copy() if want_depth else None
        return rgb, depth

    def linear_depth(self, raw: np.ndarray) -> np.ndarray:
        """Reverse-Z depth buffer -> metric z-depth (m), float32; 0 where nothing was hit (far plane)."""
        cam = self.scene.camera[0]
        znear, zfar = np.float32(cam.frustum_near), np.float32(cam.frustum_far)
        c = -(zfar + znear) / (zfar - znear)
        d = -(np.float32(2) * zfar * znear) / (zfar - znear)
        c = np.float32(-0.5) * c - np.float32(0.5)
        d = np.float32(-0.5) * d
        out = (float(d) / (raw.astype(np.float64) + float(c))).astype(np.float32)
        out[raw <= 0.0] = 0.0
        return out

    def segment_ids(self, rgb: np.ndarray) -> np.ndarray:
        """Segmentation colours -> (H, W) int32 geom ids (-1 for background and non-geom elements)."""
        n = self.scene.ngeom
        geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
        if n + 1 < 256:  # every id fits the red channel: index with uint8 directly (fast path)
            lut = np.full(256, -1, dtype=np.int32)
            seg = rgb[..., 0]
        else:
            lut = np.full(n + 2, -1, dtype=np.int32)
            r, g, b = (rgb[..., c].astype(np.int32) for c in range(3))
            seg = r | (g << 8) | (b << 16)
            seg = np.minimum(seg, n + 1)
        for g in self.scene.geoms[:n]:
            if g.segid >= 0 and g.objtype == geom_type:
                lut[g.segid + 1] = g.objid
        return lut[seg]


def _renderer_label(renderer: Any) -> str:
    """Who rendered the RGB images, e.g. ``pbr mitsuba 3.9.1 llvm_ad_rgb spp 16 ...`` (capture metadata)."""
    describe = getattr(renderer, "describe", None)
    return describe() if callable(describe) else str(getattr(renderer, "name", type(renderer).__name__))


def _make_option(groups: Iterable[int]) -> mujoco.MjvOption:
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 0
    for g in groups:
        opt.geomgroup[g] = 1
    opt.sitegroup[:] = 0
    opt.tendongroup[:] = 0
    opt.skingroup[:] = 0
    opt.flexgroup[:] = 0
    opt.flags[mujoco.mjtVisFlag.mjVIS_TENDON] = 0
    opt.flags[mujoco.mjtVisFlag.mjVIS_SKIN] = 0
    return opt


def _attr(obj: Any, *names: str, default: Any = None) -> Any:
    for n in names:
        if obj is not None and hasattr(obj, n):
            v = getattr(obj, n)
            if v is not None:
                return v
    return default


class SimCameraRig:
    """Renders multi-view captures of a MuJoCo scene (an :class:`~torm.capture.provider.ImageProvider`).

    Args:
        model, data: the compiled scene and its state (``mj_forward`` is called before rendering).
        geom_to_instance: (ngeom,) int array, geom id -> instance id k (0 for non-objects).
        config: the rig layout and intrinsics.
        object_ids, object_names: the scene's objects (instance ids and names), copied into captures.
        scenario, seed, table_height, workspace_bounds: metadata copied into captures.
        rgb_renderer: a :class:`sim.render.Renderer` that renders the RGB images instead of MuJoCo (e.g. the
            physically based ``sim.render.MitsubaRenderer``); depth and instance masks still come from MuJoCo.

    Use :meth:`from_world` with a ``sim.world.World`` (or any object with ``model``, ``data`` and
    ``geom_to_instance``). Call :meth:`close` (or use ``with``) to free the GL context.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        geom_to_instance: np.ndarray | None = None,
        config: CameraRigConfig | None = None,
        *,
        object_ids: Sequence[int] | None = None,
        object_names: Sequence[str] | None = None,
        scenario: str = "",
        seed: int | None = None,
        table_height: float | None = None,
        workspace_bounds: np.ndarray | None = None,
        rgb_renderer: Any = None,
        depth_model: Any = None,
        depth_seed: int = 0,
    ) -> None:
        self.model, self.data = model, data
        self.rgb_renderer = rgb_renderer
        #: the ``sim.world.World`` when built with :meth:`from_world` (None otherwise)
        self.world: Any = None
        self.config = config or CameraRigConfig()
        g2i = np.zeros(model.ngeom, np.int32) if geom_to_instance is None else np.asarray(geom_to_instance)
        if g2i.shape != (model.ngeom,):
            raise CaptureError(f"geom_to_instance has shape {g2i.shape} but the model has {model.ngeom} geoms")
        self.geom_to_instance = g2i.astype(np.int32)
        # lookup with one extra slot so geom id -1 (background) maps to instance 0
        self._lut = np.concatenate([self.geom_to_instance, [0]]).astype(np.int32)
        ids = sorted({int(i) for i in self.geom_to_instance if i > 0}) if object_ids is None else list(object_ids)
        self.object_ids = tuple(int(i) for i in ids)
        self.object_names = tuple(object_names) if object_names is not None else tuple(f"object_{i}" for i in ids)
        self.scenario, self.seed = scenario, seed
        self.table_height = table_height
        from sim.depth import IdealDepth

        #: the sensor-depth model (:class:`sim.depth.DepthModel`) and the seed its noise is drawn from
        self.depth_model = depth_model if depth_model is not None else IdealDepth()
        self.depth_seed = int(depth_seed)
        self._n_captures = 0
        self._n_depth_renders = 0
        self.workspace_bounds = None if workspace_bounds is None else np.asarray(workspace_bounds, np.float64)
        self._off = _Offscreen(model, self.config.image_width, self.config.image_height)
        # free the GL context at garbage collection or interpreter exit (before EGL is torn down)
        self._finalizer = weakref.finalize(self, _Offscreen.close, self._off)
        self._opt_full = _make_option([GROUP_ENV, GROUP_GLASS, GROUP_OPAQUE])
        self._opt_sensor = _make_option([GROUP_ENV, GROUP_OPAQUE])
        self._opt_solo = _make_option([_GROUP_SOLO])
        self._free_cam = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(model, self._free_cam)
        scene = self._off.scene
        scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.config.shadows)
        scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.config.reflections)

    @classmethod
    def from_world(cls, world: Any, config: CameraRigConfig | None = None, rgb_renderer: Any = None,
                   depth_model: Any = None, depth_seed: int | None = None) -> SimCameraRig:
        """A rig for a ``sim.world.World`` (duck-typed: ``model``, ``data``, ``geom_to_instance``, ``objects``...).

        ``depth_model`` (a :class:`sim.depth.DepthModel`, default ``ideal``) makes the sensor depth; its noise is
        seeded from ``depth_seed`` (default: the world's seed).
        """
        objects = list(_attr(world, "objects", default=[]) or [])
        ids = [int(_attr(o, "instance_id", "k", "id", default=i + 1)) for i, o in enumerate(objects)] or None
        names = [str(_attr(o, "name", "kind", default=f"object_{i + 1}")) for i, o in enumerate(objects)] or None
        scenario = _attr(world, "scenario", "scenario_name", default="")
        scenario = str(_attr(scenario, "name", default=scenario))
        rig = cls(
            world.model, world.data, _attr(world, "geom_to_instance"), config,
            object_ids=ids, object_names=names, scenario=scenario, seed=_attr(world, "seed"),
            table_height=_attr(world, "table_height"), workspace_bounds=_attr(world, "workspace_bounds"),
            rgb_renderer=rgb_renderer,
            depth_model=depth_model,
            depth_seed=int(depth_seed if depth_seed is not None else (_attr(world, "seed", default=0) or 0)),
        )
        rig.world = world  # the stereo depth model renders the world itself
        return rig

    # ----------------------------------------------------------------------------------- basics
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics of every view."""
        return self.config.K()

    def poses(self, n_views: int | None = None) -> np.ndarray:
        """(V, 4, 4) OpenCV camera-to-world poses of the layout."""
        return self.config.poses(n_views)

    def close(self) -> None:
        """Free the GL context (the rig cannot render afterwards)."""
        self._finalizer()

    def __enter__(self) -> SimCameraRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------- rendering
    def _update(self, opt: mujoco.MjvOption, T_world_cam: np.ndarray, K: np.ndarray) -> None:
        scene = self._off.scene
        cat = mujoco.mjtCatBit.mjCAT_ALL.value
        mujoco.mjv_updateScene(self.model, self.data, opt, None, self._free_cam, cat, scene)
        pos, fwd, up = _gl_camera_from_cv(T_world_cam)
        W, H = self._off.width, self._off.height
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        for cam in scene.camera:
            near = cam.frustum_near
            cam.pos[:] = pos
            cam.forward[:] = fwd
            cam.up[:] = up
            cam.frustum_top = near * cy / fy
            cam.frustum_bottom = -near * (H - cy) / fy
            # glFrustum(centre -+ halfwidth, bottom, top): MuJoCo 3.17 uses a non-zero frustum_width as the
            # half-width (0 = from the viewport aspect, which assumes fx = fy); checked by tests/test_capture_rig.py
            cam.frustum_center = near * 0.5 * ((W - cx) - cx) / fx
            cam.frustum_width = 0.5 * near * W / fx
            cam.orthographic = 0

    def _check_K(self, K: np.ndarray) -> None:
        if K.shape != (3, 3) or K[0, 1] != 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CaptureError(f"the MuJoCo rig renders pinhole cameras without skew; got K={K.tolist()}")

    def render_arrays(
        self, T_world_cam: np.ndarray, K: np.ndarray | None = None, channels: Iterable[str] | None = None,
        noise_key: Sequence[int] | None = None,
    ) -> dict[str, np.ndarray]:
        """Render the requested channels (any non-empty subset of :data:`CHANNELS`) at one pose.

        Returns ``{"rgb": (H, W, 3) uint8, "depth": (H, W) float32 m, "sensor_depth": (H, W) float32 m,
        "mask": (H, W) int32}`` restricted to ``channels``. Passes: one lit pass for rgb, one id pass for
        depth and mask together, one id pass with glass hidden for sensor depth. The depth model's noise is
        drawn from ``numpy.random.default_rng([depth_seed, *noise_key])`` (default key: a running count of
        sensor-depth renders of this rig).
        """
        chans = set(self.config.channels if channels is None else channels)
        if not chans or not chans <= set(CHANNELS):
            raise CaptureError(f"channels {sorted(chans)} must be a non-empty subset of {CHANNELS}")
        K = self.K() if K is None else np.asarray(K, dtype=np.float64)
        self._check_K(K)
        T = np.asarray(T_world_cam, dtype=np.float64)
        mujoco.mj_forward(self.model, self.data)
        off = self._off
        out: dict[str, np.ndarray] = {}
        first_surface = "sensor_depth" in chans and self.depth_model.needs_first_surface
        geom_ids = depth_first = None
        if chans & {"rgb", "depth", "mask"} or first_surface:
            self._update(self._opt_full, T, K)
        if "rgb" in chans and self.rgb_renderer is not None:
            out["rgb"] = self._external_rgb(T, K)
        elif "rgb" in chans:
            out["rgb"], _ = off.render(ids=False, want_rgb=True, want_depth=False)
        if "depth" in chans or "mask" in chans or first_surface:
            want_ids, want_depth = "mask" in chans or first_surface, "depth" in chans or first_surface
            ids_rgb, raw = off.render(ids=True, want_rgb=want_ids, want_depth=want_depth)
            if raw is not None:
                depth_first = off.linear_depth(raw)
                if "depth" in chans:
                    out["depth"] = depth_first
            if ids_rgb is not None:
                geom_ids = off.segment_ids(ids_rgb)
                if "mask" in chans:
                    out["mask"] = self._lut[geom_ids]
        if "sensor_depth" in chans:
            self._update(self._opt_sensor, T, K)
            _, raw = off.render(ids=True, want_rgb=False, want_depth=True)
            depth_opaque = off.linear_depth(raw)
            out["sensor_depth"] = self._sensor_depth(T, K, depth_opaque, depth_first, geom_ids, noise_key)
        return out

    def _sensor_depth(self, T: np.ndarray, K: np.ndarray, depth_opaque: np.ndarray, depth_first: np.ndarray | None,
                      geom_ids: np.ndarray | None, noise_key: Sequence[int] | None) -> np.ndarray:
        """Run the depth model on what the simulator knows about this view (:class:`sim.depth.DepthScene`)."""
        from sim.depth import DepthScene

        key = (self._n_depth_renders,) if noise_key is None else tuple(int(k) for k in noise_key)
        self._n_depth_renders += 1
        rng = np.random.default_rng([self.depth_seed, *key])
        if depth_first is None or geom_ids is None:  # a model that only needs the opaque pass
            depth_first, geom_ids = depth_opaque, np.full(depth_opaque.shape, -1, np.int32)
        groups = np.concatenate([self.model.geom_group, [-1]])
        scene = DepthScene(K=K, T_world_cam=T, depth_first=depth_first, depth_opaque=depth_opaque,
                           glass=groups[geom_ids] == GROUP_GLASS, instance=self._lut[geom_ids], renderer=self)
        return self.depth_model.sensor_depth(scene, rng)

    def _external_rgb(self, T_world_cam: np.ndarray, K: np.ndarray, noise_seed: int = 0) -> np.ndarray:
        from sim.render.base import RenderCamera

        cam = RenderCamera(K, T_world_cam, self._off.width, self._off.height)
        kw = {"noise_seed": noise_seed} if noise_seed else {}
        return self.rgb_renderer.render([cam], rgb=True, instance=False, **kw)[0].rgb

    def reference_rgb(self, poses_vx4x4: np.ndarray, K: np.ndarray | None = None) -> list[np.ndarray]:
        """(H, W, 3) uint8 RGB of each pose over the empty workspace: the objects hidden, the same renderer, render
        noise independent of the scene's views (PBR ``noise_seed`` 1). Needs a rig built with :meth:`from_world`."""
        from sim.cameras.reference_pass import objects_hidden

        if self.world is None:
            raise CaptureError("a reference pass needs the world's objects: build the rig with SimCameraRig.from_world")
        K = self.K() if K is None else np.asarray(K, dtype=np.float64)
        out = []
        with objects_hidden(self.world):
            for T in np.asarray(poses_vx4x4, dtype=np.float64).reshape(-1, 4, 4):
                mujoco.mj_forward(self.model, self.data)
                if self.rgb_renderer is not None:
                    out.append(self._external_rgb(T, K, noise_seed=1))
                else:
                    self._update(self._opt_full, T, K)
                    out.append(self._off.render(ids=False, want_rgb=True, want_depth=False)[0])
        return out

    def render_view(
        self,
        T_world_cam: np.ndarray,
        K: np.ndarray | None = None,
        channels: Iterable[str] | None = None,
        name: str = "",
        noise_key: Sequence[int] | None = None,
    ) -> CameraView:
        """Render one view at ``T_world_cam`` (4, 4, OpenCV axes, m) with intrinsics ``K`` (default: the rig's).

        ``channels`` is a subset of :data:`CHANNELS` (default: the config's); it must contain ``rgb`` or ``mask``.
        """
        chans = set(self.config.channels if channels is None else channels)
        if not chans & {"rgb", "mask"}:
            raise CaptureError(f"channels {sorted(chans)} must contain 'rgb' or 'mask' to make a CameraView")
        K = self.K() if K is None else np.asarray(K, dtype=np.float64)
        arrays = self.render_arrays(T_world_cam, K, chans, noise_key)
        return CameraView(K=K, T_world_cam=np.asarray(T_world_cam, dtype=np.float64), name=name, **arrays)

    def render_geom_ids(self, T_world_cam: np.ndarray, K: np.ndarray | None = None, glass: bool = True) -> np.ndarray:
        """(H, W) int32 geom id of the first surface per pixel (-1 background); glass hidden unless ``glass``."""
        K = self.K() if K is None else np.asarray(K, dtype=np.float64)
        self._check_K(K)
        mujoco.mj_forward(self.model, self.data)
        self._update(self._opt_full if glass else self._opt_sensor, np.asarray(T_world_cam, np.float64), K)
        ids_rgb, _ = self._off.render(ids=True, want_rgb=True, want_depth=False)
        return self._off.segment_ids(ids_rgb)

    def render_solo_masks(
        self, T_world_cam: np.ndarray, K: np.ndarray | None = None, instance_ids: Sequence[int] | None = None
    ) -> dict[int, np.ndarray]:
        """Per object, its full unoccluded silhouette (H, W) bool: only that object's visual geoms are drawn.

        Temporarily moves the object's visual geoms (groups 2 and 4) to group 5 in ``model.geom_group``
        and restores them before returning.
        """
        K = self.K() if K is None else np.asarray(K, dtype=np.float64)
        self._check_K(K)
        T = np.asarray(T_world_cam, np.float64)
        mujoco.mj_forward(self.model, self.data)
        groups = self.model.geom_group
        visual = np.isin(groups, [GROUP_GLASS, GROUP_OPAQUE])
        out: dict[int, np.ndarray] = {}
        for k in self.object_ids if instance_ids is None else instance_ids:
            sel = np.nonzero(visual & (self.geom_to_instance == k))[0]
            saved = groups[sel].copy()
            try:
                groups[sel] = _GROUP_SOLO
                self._update(self._opt_solo, T, K)
                ids_rgb, _ = self._off.render(ids=True, want_rgb=True, want_depth=False)
            finally:
                groups[sel] = saved
            out[int(k)] = self._lut[self._off.segment_ids(ids_rgb)] == k
        return out

    def capture(
        self,
        n_views: int | None = None,
        *,
        poses: np.ndarray | None = None,
        channels: Iterable[str] | None = None,
        progress: bool = False,
        metadata: dict[str, Any] | None = None,
        indices: Sequence[int] | None = None,
        reference: bool = False,
    ) -> Capture:
        """Render every view of the layout (or of ``poses`` (V, 4, 4), OpenCV camera-to-world) into a Capture.

        ``n_views`` overrides the config's view count; ``indices`` renders only those views of the layout
        (names and sensor-depth noise keep the layout index); ``progress`` shows a tqdm bar on stderr.
        ``reference``: also render each view's reference (``CameraView.reference_rgb``): the same camera over the
        empty workspace (objects hidden: :func:`sim.cameras.reference_pass.objects_hidden`), by the same renderer with
        independent render noise, as a robot's pass before the objects are placed.
        """
        Ts = self.poses(n_views) if poses is None else np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        K = self.K()
        sel = list(range(len(Ts))) if indices is None else [int(i) for i in indices]
        if any(not 0 <= i < len(Ts) for i in sel):
            raise CaptureError(f"capture indices {sel} must lie in 0..{len(Ts) - 1} (the layout's views)")
        it: Iterable[int] = sel
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc="capture", unit="view")
        n_cap = self._n_captures
        self._n_captures += 1
        views = [self.render_view(Ts[i], K, channels, name=f"view_{i:03d}", noise_key=(n_cap, i)) for i in it]
        if reference:
            refs = self.reference_rgb(Ts[sel], K)
            views = [v.with_(reference_rgb=r) for v, r in zip(views, refs, strict=True)]
        meta = {
            "renderer": f"mujoco {mujoco.__version__} offscreen" if self.rgb_renderer is None
            else _renderer_label(self.rgb_renderer),
            "depth_model": self.depth_model.record(),
            "layout_indices": sel,
            **({"reference": "simulated reference pass (objects hidden, same renderer, independent noise)"}
               if reference else {}),
            **({"mask_source": "simulator (ground truth)"} if "mask" in (channels or self.config.channels) else {}),
            "camera_rig": {
                "radius": self.config.radius, "centre": list(self.config.centre),
                "target_height": self.config.target_height, "hfov_deg": self.config.hfov_deg,
                "elevation_deg": [self.config.elevation_min_deg, self.config.elevation_max_deg],
                "shadows": self.config.shadows, "reflections": self.config.reflections,
            },
        }
        meta.update(metadata or {})
        return Capture(
            views=tuple(views), scenario=self.scenario, seed=self.seed, object_ids=self.object_ids,
            object_names=self.object_names, table_height=self.table_height,
            workspace_bounds=self.workspace_bounds, metadata=meta,
        )
