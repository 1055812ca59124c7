"""``plane_fill``: an example torm perception plug-in (a depth-completion baseline of the kind the field uses).

A depth camera loses most of a glass object's depth (``sensor_depth`` 0 or NaN) and reads the table through the
rest. ClearGrasp-style methods complete the missing depth from what surrounds it; this baseline does the simplest
version of that, per object of the most top-down view:

1. the object's pixels are its mask's (the capture's masks: it does not segment);
2. object pixels whose depth is valid and in front of the table plane are kept; if at least ``min_valid`` remain,
   a plane ``z = a u + b v + c`` (camera depth over pixel coordinates) is fitted to them by least squares and
   fills the others; otherwise the object is taken as a fronto-parallel plane through its base: the depth where
   the ray of the mask's lowest pixels meets the table plane;
3. the filled pixels are back-projected to the world frame, and the unseen back is added by mirroring
   (:func:`torm.perception.complete_by_symmetry`, the usual symmetry prior).

Frames and units: the world frame (robot base, z up), metres; camera poses OpenCV, pixel centres at +0.5.
"""

from __future__ import annotations

import numpy as np

from torm.methods import MethodContext, Needs, ObjectEstimate
from torm.types import Capture

__version__ = "0.1.0"


class PlaneFill:
    """Single-view depth, glass holes filled by a fitted plane (or the table plane), symmetric completion."""

    name = "plane_fill"
    version = __version__
    needs = Needs(rgb=False, sensor_depth=True, masks=True, views="top_down")

    def __init__(self, min_pixels: int = 30, min_valid: int = 12, table_margin_m: float = 0.004) -> None:
        if min_pixels < 1 or min_valid < 3 or table_margin_m < 0:
            raise ValueError("plane_fill: need min_pixels >= 1, min_valid >= 3, table_margin_m >= 0")
        self.min_pixels, self.min_valid, self.table_margin_m = min_pixels, min_valid, table_margin_m

    def perceive(self, capture: Capture, context: MethodContext) -> list[ObjectEstimate]:
        from torm.perception import _estimate_normals, complete_by_symmetry

        view = capture.views[0]
        if view.sensor_depth is None or view.mask is None:
            raise ValueError("plane_fill needs sensor depth and masks (its Needs say so)")
        H, W = view.mask.shape
        K, T = view.K, view.T_world_cam
        vv, uu = np.mgrid[0:H, 0:W]
        rays_cam = np.stack([(uu + 0.5 - K[0, 2]) / K[0, 0], (vv + 0.5 - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
        rays_w = rays_cam @ T[:3, :3].T
        eye = T[:3, 3]
        z = np.nan_to_num(view.sensor_depth.astype(np.float64), nan=0.0)
        height_w = eye[2] + rays_w[..., 2] * z  # world height of each pixel's depth reading
        out = []
        for inst in sorted(int(i) for i in np.unique(view.mask) if i > 0):
            sel = view.mask == inst
            if sel.sum() < self.min_pixels:
                continue
            valid = sel & (z > 0) & (height_w > context.table_height + self.table_margin_m)
            zf = np.zeros((H, W))
            if valid.sum() >= self.min_valid:
                A = np.stack([uu[valid], vv[valid], np.ones(int(valid.sum()))], axis=1).astype(np.float64)
                coef, *_ = np.linalg.lstsq(A, z[valid], rcond=None)
                zf[sel] = coef[0] * uu[sel] + coef[1] * vv[sel] + coef[2]
                zf[valid] = z[valid]
                lo, hi = np.percentile(z[valid], [2, 98])
                zf[sel] = np.clip(zf[sel], lo, hi)
            else:  # no usable depth: a fronto-parallel plane through the object's base on the table
                rows = vv[sel]
                base = sel & (vv >= np.percentile(rows, 95))
                d = rays_w[base]
                t = (context.table_height - eye[2]) / np.where(np.abs(d[:, 2]) > 1e-9, d[:, 2], -1e-9)
                t = t[t > 0]
                if not len(t):
                    continue
                zf[sel] = float(np.median(t))  # depth along the optical axis (rays have z_cam = 1)
            p_cam = rays_cam[sel] * zf[sel][:, None]
            p = p_cam @ T[:3, :3].T + eye
            p = p[p[:, 2] > context.table_height - 0.01]
            if len(p) < 10:
                continue
            n = _estimate_normals(p, eye)
            p, n = complete_by_symmetry(p, n, eye)
            out.append(ObjectEstimate(p, n, confidence=float(valid.sum() / sel.sum())))
        return out
