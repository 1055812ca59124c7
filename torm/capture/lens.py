"""Lens models of recorded captures (nerfstudio / COLMAP names) and undistortion to the pinhole every stage uses.

torm's reconstruction, rasteriser, scoring and grasp planning all project with a pinhole ``K``. A capture whose
``transforms.json`` declares a lens model with distortion is therefore undistorted once, when it is loaded: each
image (bilinear), mask and depth map (nearest) is resampled onto the pinhole camera with the **same** ``K``
(``cv2.initUndistortRectifyMap`` / ``cv2.fisheye.initUndistortRectifyMap`` with ``newCameraMatrix = K``), so every
later stage is exact. A pinhole pixel whose source lies outside the recorded image (the corners and edges of a
pincushion lens, k1 > 0) has no evidence: its image, mask and depth values are 0, and :func:`no_evidence_masks`
marks it, so the reconstruction treats it as it treats a point outside the image (the view says nothing there)
instead of as background that carves. The capture's metadata records what was undone (``undistorted``: the lens,
and the ``frames`` and view ``names`` it was undone on), from which :func:`no_evidence_masks` recomputes the
source-less pixels of every view, also after the capture was saved, reloaded, subset or segmented.

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
OPENCV. An unknown model, non-zero coefficients under a pinhole model, or a non-zero lens coefficient torm does not
model (e.g. ``k5``, ``k6`` of COLMAP's FULL_OPENCV, ``s1``... of THIN_PRISM_FISHEYE) is a named error listing the
valid keys (never silently ignored).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from torm.errors import CaptureError
from torm.types import Capture

log = logging.getLogger(__name__)

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
#: keys that look like lens coefficients (radial k, tangential p, thin-prism s); those not in COEFFICIENTS are refused
_LENS_KEY = re.compile(r"^[kps]\d+$")


def _unknown_lens_keys(entry: dict[str, Any]) -> list[str]:
    """Coefficient-like keys of ``entry`` (top level or frame) that torm does not model, with a non-zero value."""
    out = []
    for k, v in entry.items():
        if isinstance(k, str) and _LENS_KEY.match(k) and k not in COEFFICIENTS:
            try:
                nonzero = float(v or 0.0) != 0.0
            except (TypeError, ValueError):
                nonzero = True
            if nonzero:
                out.append(k)
    return sorted(out)


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
        unknown = sorted(set(_unknown_lens_keys(doc)) | set(_unknown_lens_keys(frame)))
        if unknown:
            model = str(frame.get("camera_model", doc.get("camera_model", "OPENCV"))).upper()
            valid = CAMERA_MODELS.get(model, COEFFICIENTS)
            raise CaptureError(f"lens coefficient(s) {', '.join(unknown)} are not modelled by torm (camera_model "
                               f"{model}); valid keys: {', '.join(valid) or 'none (a pinhole model)'} (all models: "
                               f"{', '.join(COEFFICIENTS)}): undistort the images first (colmap image_undistorter) "
                               "or remove the keys if their value is meant to be 0")
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

    def source_mask(self, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """(H, W) bool: True where a pixel of the undistorted pinhole image (intrinsics ``K``) has a source pixel in
        the recorded ``width`` x ``height`` image, False where it has none (no evidence)."""
        mx, my = self.undistort_maps(K, width, height)
        return source_mask_from_maps((mx, my), width, height)

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


def source_mask_from_maps(maps: tuple[np.ndarray, np.ndarray], width: int, height: int) -> np.ndarray:
    """(H, W) bool: True where the undistortion map samples inside the recorded image (pixel centres at integers,
    so the image covers [-0.5, width - 0.5] x [-0.5, height - 0.5] px)."""
    mx, my = maps
    ok = (mx >= -0.5) & (mx <= width - 0.5) & (my >= -0.5) & (my <= height - 0.5)
    return np.asarray(ok & np.isfinite(mx) & np.isfinite(my))


def undistort(img: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool = False) -> np.ndarray:
    """Resample ``img`` (H, W[, C]) with :meth:`Lens.undistort_maps` (bilinear, or nearest for ids and depth);
    outside the source: 0 (:func:`no_evidence_masks` marks those pixels as no evidence)."""
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    src = img
    if img.dtype in (np.int32, np.int64):  # OpenCV remaps 16-bit and float, not int32 ids
        src = img.astype(np.float32)
    out = cv2.remap(src, maps[0], maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(img.dtype) if out.dtype != img.dtype else out


def _entry_lens(entry: dict[str, Any]) -> Lens:
    """The lens of one ``metadata["undistorted"]`` entry."""
    coeffs = tuple((k, float(entry[k])) for k in COEFFICIENTS if entry.get(k))
    return Lens(str(entry.get("camera_model", "OPENCV")), coeffs)


def no_evidence_masks(capture: Capture) -> np.ndarray | None:
    """(V, H, W) bool: True where a view's pixel had no source pixel when its lens distortion was undone at load
    (no evidence: neither object nor background), or None when no view was undistorted.

    Recomputed from ``capture.metadata["undistorted"]`` (lens per view name) with each view's own ``K`` and the
    image size, so it follows the views through :meth:`~torm.types.Capture.subset`, segmentation and a save and
    reload. A view whose name is in no entry has evidence everywhere.

    Raises:
        CaptureError: one view name is listed under two different lenses (name the frames uniquely).
    """
    entries = capture.metadata.get("undistorted") or []
    if not entries:
        return None
    by_name: dict[str, Lens] = {}
    for e in entries:
        lens = _entry_lens(e)
        for name in e.get("names") or ():
            if by_name.get(name, lens) != lens:
                raise CaptureError(f"view name {name!r} is listed under two lenses in metadata['undistorted']; give "
                                   "the frames unique names (the 'name' key of each frame)")
            by_name[name] = lens
    if not by_name:
        log.warning("metadata['undistorted'] lists no view names (a capture saved by torm < issue 60): the pixels "
                    "without a source are not marked as no evidence; reload the recorded folder")
        return None
    H, W = capture.image_size
    out = np.zeros((len(capture.views), H, W), bool)
    cache: dict[tuple[Lens, bytes], np.ndarray] = {}
    for i, v in enumerate(capture.views):
        lens = by_name.get(v.name)
        if lens is None or lens.is_pinhole:
            continue
        key = (lens, v.K.tobytes())
        if key not in cache:
            cache[key] = ~lens.source_mask(v.K, W, H)
        out[i] = cache[key]
    return out if out.any() else None
