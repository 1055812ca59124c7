"""Degrade an exact capture the way real recorded captures are degraded (issue 38): camera pose error of a
structure-from-motion solve, lens distortion, hand-drawn masks.

Each function is pure (explicit generator) and returns what it did, so a benchmark row can say how degraded its
input was (``benchmarks/recon_degraded.py``):

- :func:`perturb_poses`: each camera-to-world pose rotated and shifted so that surface points of the scene move by
  a chosen RMS reprojection error (px) in that view; COLMAP solves of object captures typically report 0.3-1 px
  mean reprojection error (the range issue 38 gives for real captures).
- :func:`distort_image`: what a camera with lens ``lens`` records of a pinhole image (the inverse of the loader's
  undistortion, :mod:`torm.capture.lens`).
- :func:`hand_drawn_mask`: a polygon annotation of a mask as a person draws it in a labelling tool: every outline
  simplified to a polygon (Douglas-Peucker tolerance ``simplify_px``), each vertex placed with an error
  (``vertex_sigma_px``), filled anti-aliased (soft edges, 0..1), holes kept.

Frames and units: poses camera-to-world, OpenCV axes (x right, y down, z forward), metres; K pinhole, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from torm.errors import CaptureError


@dataclass(frozen=True)
class PoseError:
    """What :func:`perturb_poses` did to one view: rotation (rad), translation (m), and the RMS reprojection error
    (px) it causes on the given points."""

    rotation_rad: float
    translation_m: float
    reprojection_rms_px: float


def _rodrigues(axis_angle_3: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle_3, np.float64).reshape(3, 1))[0]


def _project(points_world_nx3: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    T_cw = np.linalg.inv(T_world_cam)
    pc = points_world_nx3 @ T_cw[:3, :3].T + T_cw[:3, 3]
    return pc[:, :2] / pc[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


def reprojection_rms_px(points_world_nx3: np.ndarray, K: np.ndarray, T_true: np.ndarray,
                        T_est: np.ndarray) -> float:
    """RMS distance (px) between the projections of the points (N, 3) m through the true and the estimated pose."""
    d = _project(points_world_nx3, K, T_true) - _project(points_world_nx3, K, T_est)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def perturb_poses(poses_vx4x4: np.ndarray, Ks_vx3x3: np.ndarray, points_world_nx3: np.ndarray,
                  target_px: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, list[PoseError]]:
    """Poses (V, 4, 4) with errors that move ``points_world_nx3`` (N, 3) m by ``target_px`` (V,) px RMS per view.

    Each view gets a rotation about a random axis and a translation in a random direction, each contributing
    about half of the error (in squares); both are scaled together until the measured RMS reprojection error of
    the points is ``target_px`` (within 1 %). Returns the perturbed poses and one :class:`PoseError` per view.
    """
    P = np.asarray(poses_vx4x4, np.float64).reshape(-1, 4, 4)
    Ks = np.asarray(Ks_vx3x3, np.float64).reshape(-1, 3, 3)
    pts = np.asarray(points_world_nx3, np.float64)
    target = np.broadcast_to(np.asarray(target_px, np.float64), (len(P),))
    if len(Ks) != len(P) or pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise CaptureError(f"perturb_poses: need one K per pose and (N >= 3, 3) points; got {len(P)} poses, "
                           f"{len(Ks)} K, points {pts.shape}")
    if np.any(target < 0):
        raise CaptureError("perturb_poses: target reprojection errors must be >= 0 px")
    out, errs = P.copy(), []
    for i, (T, K, r) in enumerate(zip(P, Ks, target, strict=True)):
        if r == 0:
            errs.append(PoseError(0.0, 0.0, 0.0))
            continue
        f = float(K[0, 0])
        depth = float(np.median(np.linalg.norm(pts - T[:3, 3], axis=1)))
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        angle, shift = r / (np.sqrt(2) * f), r * depth / (np.sqrt(2) * f)
        for _ in range(20):  # the error is nearly linear in the scale: a few fixed-point steps
            Ti = T.copy()
            Ti[:3, :3] = _rodrigues(axis * angle) @ T[:3, :3]
            Ti[:3, 3] = T[:3, 3] + direction * shift
            got = reprojection_rms_px(pts, K, T, Ti)
            if got <= 0 or abs(got - r) <= 0.01 * r:
                break
            angle, shift = angle * r / got, shift * r / got
        out[i] = Ti
        errs.append(PoseError(float(angle), float(shift), got))
    return out, errs


def distort_image(img: np.ndarray, K: np.ndarray, lens: object, nearest: bool = False) -> np.ndarray:
    """What a camera with ``lens`` (:class:`torm.capture.lens.Lens`) records of the pinhole image ``img`` (H, W[, C])
    with intrinsics ``K``: each recorded pixel shows the pinhole pixel its ray belongs to."""
    h, w = img.shape[:2]
    K = np.asarray(K, np.float64)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1)[:, None, :]
    vec = lens.opencv_vector()  # type: ignore[attr-defined]
    if lens.model == "OPENCV_FISHEYE":  # type: ignore[attr-defined]
        und = cv2.fisheye.undistortPoints(pts, K, vec, P=K)
    else:
        und = cv2.undistortPoints(pts, K, vec, P=K)
    mx = und[:, 0, 0].reshape(h, w).astype(np.float32)
    my = und[:, 0, 1].reshape(h, w).astype(np.float32)
    src = img.astype(np.float32) if img.dtype in (np.int32, np.int64, bool) else img
    out = cv2.remap(src, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderValue=0)
    return out.astype(img.dtype)


def hand_drawn_mask(mask: np.ndarray, rng: np.random.Generator, simplify_px: float = 2.0,
                    vertex_sigma_px: float = 1.0) -> np.ndarray:
    """(H, W) float32 coverage in [0, 1]: ``mask`` (H, W, > 0 = object) redrawn as polygons (see the module
    docstring). Outlines shorter than 3 vertices after simplification are dropped, as an annotator skips specks."""
    if simplify_px < 0 or vertex_sigma_px < 0:
        raise CaptureError("hand_drawn_mask: simplify_px and vertex_sigma_px must be >= 0 px")
    binary = (np.asarray(mask) > 0).astype(np.uint8)
    H, W = binary.shape
    # traced on the 2x mask, the outline runs a quarter pixel inside the edge (on the 1x mask: half a pixel)
    up = cv2.resize(binary, (2 * W, 2 * H), interpolation=cv2.INTER_NEAREST)
    contours, hierarchy = cv2.findContours(up, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    canvas = np.zeros((H, W), np.uint8)
    if not contours:
        return canvas.astype(np.float32)
    shift = 4  # sub-pixel vertices: cv2 draws with 4 fractional bits
    outer, holes = [], []
    for c, h in zip(contours, hierarchy[0], strict=True):
        c1 = ((c.reshape(-1, 2).astype(np.float32) + 0.5) / 2 - 0.5)[:, None, :]  # 1x px, cv2 centres at integers
        poly = cv2.approxPolyDP(c1, simplify_px, True).reshape(-1, 2).astype(np.float64) if simplify_px > 0 \
            else c1.reshape(-1, 2).astype(np.float64)
        if len(poly) < 3:
            continue
        poly = poly + rng.normal(0.0, vertex_sigma_px, poly.shape)  # the hand's error
        (holes if h[3] >= 0 else outer).append(np.round(poly * (1 << shift)).astype(np.int32))
    if outer:
        cv2.fillPoly(canvas, outer, 255, lineType=cv2.LINE_AA, shift=shift)
    if holes:
        cv2.fillPoly(canvas, holes, 0, lineType=cv2.LINE_AA, shift=shift)
    return canvas.astype(np.float32) / 255.0


__all__ = ["PoseError", "distort_image", "hand_drawn_mask", "perturb_poses", "reprojection_rms_px"]
