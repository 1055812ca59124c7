"""Small RGB / depth cameras for the gymnasium envs: a fixed overview camera and a wrist-like camera.

Unlike the capture rig (:mod:`sim.cameras.rig`, which hides the robot), these cameras show the robot
(geom groups 0 environment, 1 robot, 2 glass, 4 opaque; collision group 3 hidden) because a policy
needs to see its gripper. Frames: world = robot base frame, z up, metres; camera poses ``T_world_cam``
(4, 4) in OpenCV axes (x right, y down, z forward). Images are (H, W, 3) uint8 RGB; depth is (H, W)
float32 metric z-depth along the optical axis (m), clipped to ``[0, MAX_DEPTH]``.

Shadows, reflections and multisampling are off (several times faster on a CPU renderer).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass

from torm.runtime import ensure_headless_gl

ensure_headless_gl()

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from torm.errors import ConfigError, UnknownNameError  # noqa: E402
from torm.geometry import look_at_cv  # noqa: E402

#: Camera names the envs know.
CAMERA_NAMES = ("overview", "wrist", "scene")
#: Largest depth reported (m); the depth space's upper bound.
MAX_DEPTH = 10.0
#: Geom groups drawn: environment, robot, glass objects, opaque objects (collision geoms hidden).
VISIBLE_GROUPS = (0, 1, 2, 4)

#: Overview camera: in front of and beside the workspace, looking at the table in front of the robot (m).
OVERVIEW_EYE = (0.95, 0.42, 0.50)
OVERVIEW_TARGET = (0.50, 0.0, 0.10)
#: Scene camera (``render()``): in front of the robot and to its right, far enough back to show the whole
#: arm (base at the origin, about 1.3 m tall at its zero pose) and the object workspace on the table (m).
SCENE_EYE = (1.35, -1.15, 0.95)
SCENE_TARGET = (0.40, 0.0, 0.35)
#: Vertical field of view of the scene camera (deg).
SCENE_FOVY_DEG = 50.0


@dataclass(frozen=True)
class WristMount:
    """Where the wrist-like camera sits relative to the TCP (m), along the TCP's approach axis and its third axis.

    The camera sits ``back`` behind the TCP along the approach axis and ``side`` along the axis orthogonal to
    approach and closing, looking at the point ``ahead`` in front of the TCP (between the fingertips and beyond).
    """

    back: float = 0.06
    side: float = 0.09
    ahead: float = 0.12
    fovy_deg: float = 75.0


def overview_pose() -> np.ndarray:
    """(4, 4) OpenCV ``T_world_cam`` of the fixed overview camera."""
    return look_at_cv(np.array(OVERVIEW_EYE), np.array(OVERVIEW_TARGET))


def scene_pose() -> np.ndarray:
    """(4, 4) OpenCV ``T_world_cam`` of the fixed scene camera used by ``render()`` (whole arm + workspace)."""
    return look_at_cv(np.array(SCENE_EYE), np.array(SCENE_TARGET))


def wrist_pose(T_world_tcp: np.ndarray, approach_axis: str, closing_axis: str, mount: WristMount) -> np.ndarray:
    """(4, 4) OpenCV ``T_world_cam`` of the wrist camera for TCP pose ``T_world_tcp`` (4, 4)."""
    axes = "xyz"
    R = np.asarray(T_world_tcp, float)[:3, :3]
    p = np.asarray(T_world_tcp, float)[:3, 3]
    a = R[:, axes.index(approach_axis)]
    o = R[:, next(i for i in range(3) if axes[i] not in (approach_axis, closing_axis))]
    eye = p - mount.back * a + mount.side * o
    return look_at_cv(eye, p + mount.ahead * a, up=o)


class EnvCameras:
    """Renders named cameras of a MuJoCo scene at one image size (one offscreen GL context).

    Args:
        model, data: the scene (``data`` is read, never stepped).
        height, width: image size in pixels.
        fovy_deg: vertical field of view of the overview camera (deg); the wrist camera uses ``mount.fovy_deg``,
            the scene camera :data:`SCENE_FOVY_DEG`.
        tcp_site: name of the TCP site (for the wrist camera).
        approach_axis, closing_axis: TCP axes of the gripper ("x"/"y"/"z").
        mount: wrist camera placement.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, height: int, width: int, *,
                 fovy_deg: float = 60.0, tcp_site: str | None = None, approach_axis: str = "z",
                 closing_axis: str = "y", mount: WristMount | None = None) -> None:
        if height < 8 or width < 8:
            raise ConfigError(f"camera images must be at least 8x8 pixels, got {height}x{width}")
        if not 1.0 < fovy_deg < 170.0:
            raise ConfigError(f"camera fovy_deg must be in (1, 170), got {fovy_deg}")
        self.model, self.data = model, data
        self.height, self.width = int(height), int(width)
        self.fovy_deg = float(fovy_deg)
        self.mount = mount or WristMount()
        self.approach_axis, self.closing_axis = approach_axis, closing_axis
        self._tcp = None if tcp_site is None else model.site(tcp_site).id
        vis = model.vis
        vis.global_.offwidth = max(int(vis.global_.offwidth), self.width)
        vis.global_.offheight = max(int(vis.global_.offheight), self.height)
        vis.quality.offsamples = 0
        self._renderer = mujoco.Renderer(model, self.height, self.width)
        self._finalizer = weakref.finalize(self, self._renderer.close)
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[:] = 0
        for g in VISIBLE_GROUPS:
            self._opt.geomgroup[g] = 1
        self._opt.sitegroup[:] = 0
        self._free_cam = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(model, self._free_cam)
        self._overview = overview_pose()
        self._scene = scene_pose()
        # The first depth frame of a fresh GL context differs from later ones by ~1e-5 m; render one frame of
        # each kind now so equal states always give bit-identical observations.
        self.render(["overview"], depth=True)

    def close(self) -> None:
        """Free the GL context (idempotent)."""
        self._finalizer()

    def pose(self, name: str) -> np.ndarray:
        """(4, 4) OpenCV ``T_world_cam`` of camera ``name`` now."""
        if name == "overview":
            return self._overview
        if name == "scene":
            return self._scene
        if name == "wrist":
            if self._tcp is None:
                raise ConfigError("the wrist camera needs tcp_site")
            T = np.eye(4)
            T[:3, :3] = self.data.site_xmat[self._tcp].reshape(3, 3)
            T[:3, 3] = self.data.site_xpos[self._tcp]
            return wrist_pose(T, self.approach_axis, self.closing_axis, self.mount)
        raise UnknownNameError("camera", name, CAMERA_NAMES)

    def K(self, name: str) -> np.ndarray:
        """(3, 3) pinhole intrinsics (px) of camera ``name`` at the observation size (square pixels, centred)."""
        f = 0.5 * self.height / math.tan(math.radians(self._fovy(name)) / 2.0)
        return np.array([[f, 0.0, self.width / 2.0], [0.0, f, self.height / 2.0], [0.0, 0.0, 1.0]])

    def pointcloud(self, names: Sequence[str], n_points: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(``xyz`` (n, 3) float32 world frame m, ``rgb`` (n, 3) uint8): the cameras' depth pixels with a return
        (z < MAX_DEPTH) back-projected through pixel centres and their colours, ``n_points`` drawn with ``rng``
        (with replacement when fewer; zeros when no pixel has a return)."""
        imgs = self.render(names, depth=True)
        pts, cols = [], []
        vv, uu = np.mgrid[0:self.height, 0:self.width]
        for name in names:
            z = imgs[f"{name}_depth"].astype(np.float64)
            ok = (z > 0) & (z < 0.999 * MAX_DEPTH)
            K, T = self.K(name), self.pose(name)
            x = (uu[ok] + 0.5 - K[0, 2]) / K[0, 0] * z[ok]
            y = (vv[ok] + 0.5 - K[1, 2]) / K[1, 1] * z[ok]
            pts.append(np.stack([x, y, z[ok]], axis=1) @ T[:3, :3].T + T[:3, 3])
            cols.append(imgs[f"{name}_rgb"][ok])
        xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
        rgb = np.concatenate(cols) if cols else np.zeros((0, 3), np.uint8)
        if not len(xyz):
            return np.zeros((n_points, 3), np.float32), np.zeros((n_points, 3), np.uint8)
        idx = rng.choice(len(xyz), size=n_points, replace=len(xyz) < n_points)
        return xyz[idx].astype(np.float32), rgb[idx].astype(np.uint8)

    def _fovy(self, name: str) -> float:
        if name == "scene":
            return SCENE_FOVY_DEG
        return self.mount.fovy_deg if name == "wrist" else self.fovy_deg

    def _update(self, name: str) -> None:
        r = self._renderer
        r.update_scene(self.data, self._free_cam, self._opt)
        T = self.pose(name)
        f = 0.5 * self.height / math.tan(math.radians(self._fovy(name)) / 2.0)
        for cam in r.scene.camera:
            near = cam.frustum_near
            cam.pos[:] = T[:3, 3]
            cam.forward[:] = T[:3, 2]
            cam.up[:] = -T[:3, 1]
            cam.frustum_top = near * 0.5 * self.height / f
            cam.frustum_bottom = -near * 0.5 * self.height / f
            cam.frustum_center = 0.0
            cam.frustum_width = 0.5 * near * self.width / f
            cam.orthographic = 0

    def render(self, names: Sequence[str], depth: bool = True) -> dict[str, np.ndarray]:
        """``{"<name>_rgb": (H, W, 3) uint8, "<name>_depth": (H, W) float32 m}`` for every camera in ``names``."""
        out: dict[str, np.ndarray] = {}
        mujoco.mj_kinematics(self.model, self.data)
        r = self._renderer
        for name in names:
            self._update(name)
            out[f"{name}_rgb"] = r.render().copy()
            if depth:
                r.enable_depth_rendering()
                try:
                    d = r.render()
                finally:
                    r.disable_depth_rendering()
                out[f"{name}_depth"] = np.clip(d, 0.0, MAX_DEPTH).astype(np.float32)
        return out
