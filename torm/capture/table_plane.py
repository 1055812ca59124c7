"""Table-top plane from a capture's metric depth, as a real robot would measure it (no simulator truth).

:func:`estimate_table_plane` back-projects every valid depth pixel of every view into the world frame
(z up), leaves out the pixels the instance masks claim for objects, and fits the dominant
near-horizontal plane with RANSAC (hypotheses tilted more than :data:`MAX_TILT_DEG` from world +z are
discarded) followed by a least-squares refinement on the inliers. Units are metres throughout.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from torm.errors import CaptureError, UnknownNameError
from torm.geometry import backproject_depth
from torm.types import Capture

log = logging.getLogger(__name__)

#: Depth channels of a :class:`~torm.types.CameraView`, plus ``auto`` (sensor depth first, then ideal depth).
CHANNELS: tuple[str, ...] = ("auto", "sensor_depth", "depth")
MAX_TILT_DEG = 10.0  #: largest angle (deg) between the plane normal and world +z
MIN_POINTS = 500  #: fewest valid depth points to fit from
MIN_INLIER_SHARE = 0.20  #: smallest share of the points the table plane must explain
N_HYPOTHESES = 512  #: RANSAC plane hypotheses (three-point samples)
N_SCORE_POINTS = 20_000  #: points each hypothesis is scored on (a random subset of the fit points)


@dataclass(frozen=True, eq=False)
class TablePlane:
    """The table-top plane in the world frame.

    Attributes:
        height_m: z (m) of the plane at ``centre_xy_m``.
        normal: (3,) unit normal, world frame, pointing up (``normal[2] > 0``).
        centre_xy_m: (2,) world xy (m) where ``height_m`` is taken: the workspace centre when the
            capture declares ``workspace_bounds``, else the inliers' centroid.
        inlier_share: share (0..1) of the ``n_points`` fit points within ``inlier_tol_m`` of the plane.
        residual_std_m: standard deviation (m) of the inliers' signed distances to the refined plane.
        n_points: number of points the plane was fit on (after subsampling).
        channel: depth channel used (``sensor_depth`` or ``depth``).
    """

    height_m: float
    normal: np.ndarray
    centre_xy_m: np.ndarray
    inlier_share: float
    residual_std_m: float
    n_points: int
    channel: str

    @property
    def tilt_deg(self) -> float:
        """Angle (deg) between :attr:`normal` and world +z."""
        return math.degrees(math.acos(min(1.0, abs(float(self.normal[2])))))

    def height_at(self, xy_m: np.ndarray) -> np.ndarray:
        """z (m) of the plane at world xy (..., 2) m."""
        xy = np.asarray(xy_m, dtype=np.float64)
        n = self.normal
        return self.height_m - ((xy - self.centre_xy_m) @ n[:2]) / n[2]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (floats and lists only)."""
        return {
            "height_m": float(self.height_m),
            "normal": [float(v) for v in self.normal],
            "centre_xy_m": [float(v) for v in self.centre_xy_m],
            "tilt_deg": float(self.tilt_deg),
            "inlier_share": float(self.inlier_share),
            "residual_std_m": float(self.residual_std_m),
            "n_points": int(self.n_points),
            "channel": self.channel,
        }


def _pick_channel(capture: Capture, channel: str) -> str:
    if channel not in CHANNELS:
        raise UnknownNameError("table-plane depth channel", channel, CHANNELS)
    have = [c for c in ("sensor_depth", "depth") if any(getattr(v, c) is not None for v in capture.views)]
    if not have:
        raise CaptureError(
            f"capture {capture.scenario!r} has no depth in any of its {len(capture)} views, so the table plane "
            "cannot be measured; capture with depth, or declare the table height"
        )
    if channel == "auto":
        return have[0]
    if channel not in have:
        raise CaptureError(
            f"capture {capture.scenario!r} has no {channel!r} in any view (it has {', '.join(have)}); "
            "pick channel='auto' or capture with that depth channel"
        )
    return channel


def world_points(capture: Capture, channel: str, use_masks: bool = True) -> np.ndarray:
    """(N, 3) world points (m) of every valid ``channel`` depth pixel of ``capture``, object pixels left out.

    A pixel is valid when its depth is finite and > 0 and, with ``use_masks`` and where the view has an instance
    mask, the mask is 0.
    """
    out = []
    for v in capture.views:
        d = getattr(v, channel)
        if d is None:
            continue
        ok = np.isfinite(d) & (d > 0)
        if use_masks and v.mask is not None:
            ok &= v.mask == 0
        if not ok.any():
            continue
        p_cam_nx3 = backproject_depth(np.where(ok, d, 0.0), v.K)[ok]
        out.append(p_cam_nx3 @ v.T_world_cam[:3, :3].T + v.T_world_cam[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


def _fit_plane(points_nx3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (orthogonal) plane through ``points_nx3``: (unit normal with n_z >= 0, centroid), m."""
    c = points_nx3.mean(axis=0)
    n = np.linalg.svd(points_nx3 - c, full_matrices=False)[2][-1]
    return (n if n[2] >= 0 else -n), c


def estimate_table_plane(
    capture: Capture,
    *,
    channel: str = "auto",
    max_points: int = 200_000,
    inlier_tol_m: float = 0.003,
    rng: np.random.Generator | None = None,
    use_masks: bool = True,
) -> TablePlane:
    """Fit the dominant near-horizontal plane (the table top) to a capture's metric depth.

    Every valid depth pixel (finite, > 0) of each view is back-projected with the view's ``K`` and
    ``T_world_cam`` (OpenCV axes) into the world frame; pixels inside instance masks (objects) are
    skipped when the views have masks. At most ``max_points`` points, drawn with ``rng``, are fit:
    RANSAC over three-point plane hypotheses whose normal is within :data:`MAX_TILT_DEG` of world +z,
    then two least-squares refits on the inliers. Deterministic for a given ``rng``.

    Args:
        capture: views with ``sensor_depth`` and/or ``depth`` (float32 (H, W) z-depth, m; 0/NaN = none).
        channel: ``auto`` (``sensor_depth`` when any view has it, what a real camera gives, else ``depth``),
            ``sensor_depth`` or ``depth``.
        max_points: largest number of points fit (a random subset when there are more).
        inlier_tol_m: distance (m) to the plane within which a point is an inlier.
        rng: random generator for subsampling and RANSAC; default ``np.random.default_rng(0)``.
        use_masks: leave out the pixels the capture's instance masks claim for objects. The decision loop passes
            False: in simulation those masks are the simulator's truth, which a robot does not have; the objects'
            points are then RANSAC outliers of the table plane (a tabletop scene is mostly table).

    Returns:
        The :class:`TablePlane`; ``height_m`` is taken at the workspace centre when the capture has
        ``workspace_bounds``, else at the inliers' centroid.

    Raises:
        UnknownNameError: ``channel`` is not one of :data:`CHANNELS`.
        CaptureError: the capture has no depth (capture with depth, or declare the table height), has
            fewer than :data:`MIN_POINTS` valid points, or no near-horizontal plane holds at least
            :data:`MIN_INLIER_SHARE` of them.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    chan = _pick_channel(capture, channel)
    points_nx3 = world_points(capture, chan, use_masks)
    n_valid = len(points_nx3)
    if n_valid < MIN_POINTS:
        raise CaptureError(
            f"only {n_valid} valid {chan} points outside the object masks (need >= {MIN_POINTS}) to fit the "
            "table plane; capture views that see more of the table, or declare the table height"
        )
    if n_valid > max_points:
        points_nx3 = points_nx3[rng.choice(n_valid, size=max_points, replace=False)]
    n = len(points_nx3)

    # RANSAC: plane hypotheses from 3 random points, near-horizontal ones scored on a random subset.
    idx_hx3 = rng.integers(0, n, size=(N_HYPOTHESES, 3))
    a, b, c = (points_nx3[idx_hx3[:, k]] for k in range(3))
    normals_hx3 = np.cross(b - a, c - a)
    length_h = np.linalg.norm(normals_hx3, axis=1)
    cos_min = math.cos(math.radians(MAX_TILT_DEG))
    with np.errstate(invalid="ignore", divide="ignore"):
        normals_hx3 = normals_hx3 / length_h[:, None]
    keep = (length_h > 1e-12) & (np.abs(normals_hx3[:, 2]) >= cos_min)
    best_share = 0.0
    plane_n, plane_c = np.array([0.0, 0.0, 1.0]), points_nx3.mean(axis=0)
    if keep.any():
        hyp_n, hyp_c = normals_hx3[keep], a[keep]
        score_pts = points_nx3[rng.choice(n, size=min(n, N_SCORE_POINTS), replace=False)]
        counts_h = np.zeros(len(hyp_n), dtype=np.int64)
        for s in range(0, len(hyp_n), 64):  # chunks of hypotheses keep the (h, m) distance matrix small
            dist = np.abs((score_pts[None] - hyp_c[s:s + 64, None]) @ hyp_n[s:s + 64, :, None])[..., 0]
            counts_h[s:s + 64] = (dist <= inlier_tol_m).sum(axis=1)
        best = int(np.argmax(counts_h))
        best_share = counts_h[best] / len(score_pts)
        plane_n, plane_c = hyp_n[best], hyp_c[best]

    # Refine: least squares on the inliers of the current plane, twice.
    inl = np.zeros(n, dtype=bool)
    if best_share > 0:
        for _ in range(2):
            inl = np.abs((points_nx3 - plane_c) @ plane_n) <= inlier_tol_m
            if inl.sum() < 3:
                break
            plane_n, plane_c = _fit_plane(points_nx3[inl])
        inl = np.abs((points_nx3 - plane_c) @ plane_n) <= inlier_tol_m
    share = float(inl.mean())
    tilt = math.degrees(math.acos(min(1.0, abs(float(plane_n[2])))))
    if share < MIN_INLIER_SHARE or tilt > MAX_TILT_DEG:
        raise CaptureError(
            f"no near-horizontal plane (tilt <= {MAX_TILT_DEG:g} deg) holds >= {MIN_INLIER_SHARE:.0%} of the "
            f"{n} {chan} points within {inlier_tol_m * 1e3:g} mm (best: {share:.1%} of the points, tilt "
            f"{tilt:.1f} deg); is the table in view and the world frame z up? Otherwise declare the table height"
        )

    centre_xy = (capture.workspace_bounds.mean(axis=0)[:2] if capture.workspace_bounds is not None
                 else points_nx3[inl, :2].mean(axis=0))
    height = float(plane_c[2] - ((centre_xy - plane_c[:2]) @ plane_n[:2]) / plane_n[2])
    resid = (points_nx3[inl] - plane_c) @ plane_n
    plane = TablePlane(height_m=height, normal=plane_n.copy(), centre_xy_m=np.asarray(centre_xy, dtype=np.float64),
                       inlier_share=share, residual_std_m=float(resid.std()), n_points=n, channel=chan)
    log.info("table plane from %d %s points: z = %.4f m, tilt %.2f deg, %.0f%% inliers, residual std %.2f mm",
             n, chan, height, plane.tilt_deg, 100 * share, 1e3 * plane.residual_std_m)
    return plane
