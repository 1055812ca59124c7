"""Lens models of recorded captures (nerfstudio / COLMAP names) and undistortion to the pinhole every stage uses.

torm's reconstruction, rasteriser, scoring and grasp planning all project with a pinhole ``K``. A capture whose
``transforms.json`` declares a lens model with distortion is therefore undistorted once, when it is loaded: each
image (bilinear), mask and depth map (nearest) is resampled onto the pinhole camera with the **same** ``K``
(``cv2.initUndistortRectifyMap`` / ``cv2.fisheye.initUndistortRectifyMap`` with ``newCameraMatrix = K``), so every
later stage is exact; pixels that fall outside the source image become 0 (background, no depth). The capture's
metadata records what was undone (``undistorted``).

Models (``camera_model`` at the top level or per frame; coefficients likewise, per frame overriding):

================  ==========================  =====================================================
model             coefficients                OpenCV distortion vector
================  ==========================  =====================================================
PINHOLE           none                        -
SIMPLE_PINHOLE    none                        -
SIMPLE_RADIAL     k1                          (k1, 0, 0, 0)
RADIAL            k1 k2                       (k1, k2, 0, 0)
OPENCV            k1 k2 p1 p2 (k3)            (k1, k2, p1, p2, k3)
OPENCV_FISHEYE    k1 k2 k3 k4                 fisheye (k1, k2, k3, k4), equidistant
================  ==========================  =====================================================

nerfstudio writes ``camera_model`` OPENCV by default; a file with coefficients and no ``camera_model`` is read as
OPENCV. An unknown model, or non-zero coefficients under a pinhole model, is a named error (never silently ignored).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from torm.errors import CaptureError

#: coefficient names each model uses
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "PINHOLE": (),
    "SIMPLE_PINHOLE": (),
    "SIMPLE_RADIAL": ("k1",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2", "k3"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
}
COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass(frozen=True)
class Lens:
    """A lens model and its coefficients (dimensionless; OpenCV's conventions on normalised coordinates)."""

    model: str = "PINHOLE"
    coeffs: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise CaptureError(f"camera_model {self.model!r} is not supported; valid choices: "
                               f"{', '.join(CAMERA_MODELS)} (undistort the images first for another model)")
        unused = [k for k, v in self.coeffs if v and k not in CAMERA_MODELS[self.model]]
        if unused:
            hint = ("OPENCV (k1 k2 p1 p2 k3) or OPENCV_FISHEYE (k1..k4)" if not CAMERA_MODELS[self.model]
                    else f"a model that has them (valid for {self.model}: {', '.join(CAMERA_MODELS[self.model])})")
            raise CaptureError(f"camera_model {self.model} has no coefficient(s) {', '.join(unused)}, but the file "
                               f"gives them non-zero: set camera_model to {hint}, or remove them")

    @classmethod
    def from_json(cls, doc: dict[str, Any], frame: dict[str, Any] | None = None) -> Lens:
        """The lens of ``frame`` (its own ``camera_model`` and coefficients over the top level's)."""
        frame = frame or {}
        vals = {k: float(frame[k]) if k in frame else float(doc.get(k, 0.0) or 0.0) for k in COEFFICIENTS}
        model = frame.get("camera_model", doc.get("camera_model"))
        if model is None:
            model = "OPENCV" if any(vals.values()) else "PINHOLE"
        return cls(str(model).upper(), tuple((k, v) for k, v in vals.items() if v))

    @property
    def is_pinhole(self) -> bool:
        return not any(v for _, v in self.coeffs)

    def get(self, name: str) -> float:
        return dict(self.coeffs).get(name, 0.0)

    def opencv_vector(self) -> np.ndarray:
        """OpenCV's distortion vector: (k1, k2, p1, p2, k3) or, for the fisheye model, (k1, k2, k3, k4)."""
        g = self.get
        if self.model == "OPENCV_FISHEYE":
            return np.array([g("k1"), g("k2"), g("k3"), g("k4")], np.float64)
        return np.array([g("k1"), g("k2"), g("p1"), g("p2"), g("k3")], np.float64)

    def to_json(self) -> dict[str, Any]:
        return {"camera_model": self.model, **dict(self.coeffs)}

    def undistort_maps(self, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y) (H, W) float32: for each pixel of the pinhole image with intrinsics ``K``, where to sample
        the distorted image (px)."""
        K = np.asarray(K, np.float64)
        if self.model == "OPENCV_FISHEYE":
            return cv2.fisheye.initUndistortRectifyMap(K, self.opencv_vector(), np.eye(3), K, (width, height),
                                                       cv2.CV_32FC1)
        return cv2.initUndistortRectifyMap(K, self.opencv_vector(), None, K, (width, height), cv2.CV_32FC1)

    def distort_points(self, K: np.ndarray, uv_nx2: np.ndarray) -> np.ndarray:
        """(N, 2) pixel positions in the distorted image of pinhole pixels ``uv`` (both with intrinsics ``K``)."""
        K = np.asarray(K, np.float64)
        uv = np.asarray(uv_nx2, np.float64)
        xy = (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)[:, None, :]
        if self.model == "OPENCV_FISHEYE":
            out = cv2.fisheye.distortPoints(xy[:, None, :], K, self.opencv_vector())
            return out.reshape(-1, 2)
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, self.opencv_vector())
        return out.reshape(-1, 2)


def undistort(img: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool = False) -> np.ndarray:
    """Resample ``img`` (H, W[, C]) with :meth:`Lens.undistort_maps` (bilinear, or nearest for ids and depth);
    outside the source: 0."""
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    src = img
    if img.dtype in (np.int32, np.int64):  # OpenCV remaps 16-bit and float, not int32 ids
        src = img.astype(np.float32)
    out = cv2.remap(src, maps[0], maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(img.dtype) if out.dtype != img.dtype else out
