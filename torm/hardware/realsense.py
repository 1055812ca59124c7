"""Intel RealSense D455 wrist camera (implements :class:`torm.backend.protocol.Camera`).

Streams colour ``bgr8`` at ``width x height`` (default 1280 x 720, 30 fps) and, optionally, ``z16``
depth aligned to colour with ``rs.align(rs.stream.color)``. Intrinsics and distortion come from the
colour stream profile; every frame is undistorted with OpenCV (the same remap for the aligned depth,
nearest-neighbour) so the returned ``K`` is a plain pinhole ``K``. The D455 colour stream reports the
(inverse) Brown-Conrady model with coefficients ``[k1, k2, p1, p2, k3]``, which is OpenCV's order.

The camera pose is ``T_world_cam = T_world_flange(q) @ T_flange_cam`` with ``q`` the arm's measured
joints at the time of the frame and ``T_flange_cam`` the hand-eye calibration
(:mod:`torm.hardware.handeye`). Depth is returned as ``sensor_depth`` (metres, float32; 0 = no reading):
it is what a real depth camera sees (through glass).

``pyrealsense2`` is imported lazily: without it (or without a camera) a HardwareError says what to do.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from torm.errors import HardwareError
from torm.types import CameraView

log = logging.getLogger(__name__)


def import_pyrealsense2() -> Any:
    """The ``pyrealsense2`` module, or HardwareError with the install hint."""
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise HardwareError("pyrealsense2 is not installed: pip install 'torm[hardware]' (or pip install "
                            "pyrealsense2; on ARM build librealsense with its Python bindings)") from exc
    return rs


def intrinsics_to_K(intr: Any) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), dist (5,)) from an ``rs.intrinsics`` (fx, fy, ppx, ppy, coeffs)."""
    K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
    return K, np.asarray(list(intr.coeffs)[:5], dtype=np.float64)


class Undistorter:
    """Precomputed OpenCV undistortion maps for one (K, dist, size); the output keeps ``K`` (pinhole)."""

    def __init__(self, K: np.ndarray, dist: np.ndarray, size_wh: tuple[int, int]) -> None:
        self.K = np.asarray(K, np.float64)
        self.dist = np.asarray(dist, np.float64)
        self.identity = not np.any(self.dist)
        self.map1, self.map2 = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, size_wh, cv2.CV_32FC1)

    def image(self, img: np.ndarray) -> np.ndarray:
        return img if self.identity else cv2.remap(img, self.map1, self.map2, cv2.INTER_LINEAR)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        return depth if self.identity else cv2.remap(depth, self.map1, self.map2, cv2.INTER_NEAREST)


class RealSenseCamera:
    """A D455 on the wrist.

    Args:
        T_flange_cam: (4, 4) hand-eye transform (OpenCV camera axes).
        flange_pose: callable returning the current T_world_flange (4, 4) (the arm's FK at measured joints).
        serial: device serial number (None: the first camera found).
        width, height, fps: colour stream; depth: also stream aligned depth.
        warmup_frames: frames dropped after start (auto exposure settles).
        timeout_ms: frame wait timeout.
    """

    def __init__(self, T_flange_cam: np.ndarray, flange_pose: Callable[[], np.ndarray], serial: str | None = None,
                 width: int = 1280, height: int = 720, fps: int = 30, depth: bool = True,
                 warmup_frames: int = 15, timeout_ms: int = 5000) -> None:
        rs = import_pyrealsense2()
        self._rs = rs
        self.T_flange_cam = np.asarray(T_flange_cam, np.float64)
        self._flange_pose = flange_pose
        self.depth_enabled = depth
        self.timeout_ms = timeout_ms
        ctx = rs.context()
        devices = [d.get_info(rs.camera_info.serial_number) for d in ctx.query_devices()]
        if not devices:
            raise HardwareError("no RealSense camera found; check the USB 3 cable (rs-enumerate-devices) and that "
                                "no other program holds the camera")
        if serial is not None and serial not in devices:
            raise HardwareError(f"RealSense {serial} not connected; found {devices}")
        self.pipeline = rs.pipeline()
        cfg = rs.config()
        if serial is not None:
            cfg.enable_device(serial)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.bgr8, fps)
        if depth:
            cfg.enable_stream(rs.stream.depth, 0, 0, rs.format.z16, fps)  # let the device choose the depth size
        try:
            profile = self.pipeline.start(cfg)
        except RuntimeError as exc:
            raise HardwareError(f"cannot start the RealSense streams ({width}x{height} bgr8 @ {fps} fps): "
                                f"{exc}") from exc
        color = profile.get_stream(rs.stream.color).as_video_stream_profile()
        self.K, self.dist = intrinsics_to_K(color.get_intrinsics())
        self.undistort = Undistorter(self.K, self.dist, (width, height))
        self.depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale()) if depth else 0.0
        self._align = rs.align(rs.stream.color) if depth else None
        for _ in range(max(0, warmup_frames)):
            self.pipeline.wait_for_frames(timeout_ms)
        self._count = 0
        log.info("RealSense started: K fx %.1f fy %.1f cx %.1f cy %.1f, dist %s", self.K[0, 0], self.K[1, 1],
                 self.K[0, 2], self.K[1, 2], np.round(self.dist, 4).tolist())

    def read(self) -> CameraView:
        """One undistorted frame (RGB uint8, pinhole K, sensor depth in m) posed at the current flange pose."""
        try:
            frames = self.pipeline.wait_for_frames(self.timeout_ms)
        except RuntimeError as exc:
            raise HardwareError(f"no RealSense frame within {self.timeout_ms} ms: {exc}; check the USB cable") from exc
        if self._align is not None:
            frames = self._align.process(frames)
        color = frames.get_color_frame()
        if not color:
            raise HardwareError("the RealSense frame set has no colour frame")
        bgr = np.asanyarray(color.get_data()).copy()
        rgb = cv2.cvtColor(self.undistort.image(bgr), cv2.COLOR_BGR2RGB)
        sensor_depth = None
        if self._align is not None:
            d = frames.get_depth_frame()
            if d:
                z = np.asanyarray(d.get_data()).astype(np.float32) * self.depth_scale
                sensor_depth = self.undistort.depth(z)
        T_world_cam = self._flange_pose() @ self.T_flange_cam
        self._count += 1
        return CameraView(K=self.K.copy(), T_world_cam=T_world_cam, rgb=rgb, sensor_depth=sensor_depth,
                          name=f"real_{self._count:05d}")

    def close(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.pipeline.stop()
