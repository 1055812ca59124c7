"""The paper's occlusion ratio (OCC): the share of views in which at least one object is partly occluded by another.

Per view and object k, the object's full silhouette is rendered with only its own visual geoms drawn
(:meth:`sim.cameras.rig.SimCameraRig.render_solo_masks`) and compared with the full-scene instance
mask. The pixels of that solo silhouette that the full scene shows as *another object* (mask value
j > 0, j != k) are the pixels lost to occlusion. Object k counts as partly occluded in the view when
``lost > tol * solo`` and ``lost >= min_pixels`` (tol = 2% and a few pixels by default, so
anti-aliasing-free rasterisation jitter on a touching boundary does not count). Pixels lost to the
table or the robot do not count: the robot is hidden in captures, and the paper's OCC is about
object-object occlusion. Objects outside a view (empty solo silhouette) are never occluded there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim.cameras.rig import SimCameraRig
from torm.errors import CaptureError
from torm.types import Capture


@dataclass(frozen=True, eq=False)
class OcclusionResult:
    """Occlusion statistics of a set of views.

    Attributes:
        ratio: share of views (0..1) with at least one partly occluded object (the paper's OCC).
        view_flags: (V,) bool, True where at least one object is partly occluded.
        occluded: (V, N) bool, object n partly occluded in view v.
        lost_fraction: (V, N) float64, share of the object's solo silhouette hidden by other objects
            (NaN where the object is outside the view).
        solo_pixels: (V, N) int64, pixel count of each object's unoccluded silhouette.
        object_ids: (N,) instance ids, the column order of the (V, N) arrays.
    """

    ratio: float
    view_flags: np.ndarray
    occluded: np.ndarray
    lost_fraction: np.ndarray
    solo_pixels: np.ndarray
    object_ids: tuple[int, ...]

    def summary(self) -> dict[str, object]:
        """JSON-friendly summary: ratio, occluded view count, per object (id as a string) the share of views
        in which it is partly occluded."""
        n = max(len(self.view_flags), 1)
        return {
            "occlusion_ratio": float(self.ratio),
            "views": int(len(self.view_flags)),
            "occluded_views": int(self.view_flags.sum()),
            # string keys: JSON object keys are strings, so the summary survives a save/load round trip
            "per_object_occluded_share": {
                str(k): float(self.occluded[:, i].sum() / n) for i, k in enumerate(self.object_ids)
            },
        }


def occlusion_from_masks(
    full_masks_vxhxw: np.ndarray,
    solo_masks: Sequence[dict[int, np.ndarray]],
    object_ids: Sequence[int],
    tol: float = 0.02,
    min_pixels: int = 4,
) -> OcclusionResult:
    """OCC from full-scene instance masks (V, H, W) and per-view solo silhouettes ``{k: (H, W) bool}``."""
    if len(full_masks_vxhxw) != len(solo_masks):
        raise CaptureError(f"got {len(full_masks_vxhxw)} full masks but {len(solo_masks)} sets of solo masks")
    if not 0 <= tol < 1:
        raise CaptureError(f"occlusion tol must be in [0, 1), got {tol}")
    ids = tuple(int(k) for k in object_ids)
    V, N = len(full_masks_vxhxw), len(ids)
    occluded = np.zeros((V, N), bool)
    lost_fraction = np.full((V, N), np.nan)
    solo_px = np.zeros((V, N), np.int64)
    for v, (full, solos) in enumerate(zip(full_masks_vxhxw, solo_masks, strict=True)):
        other_object = full > 0
        for i, k in enumerate(ids):
            solo = solos[k]
            if solo.shape != full.shape:
                raise CaptureError(f"view {v}: solo mask of object {k} is {solo.shape}, the full mask {full.shape}")
            n_solo = int(solo.sum())
            solo_px[v, i] = n_solo
            if n_solo == 0:
                continue
            lost = int(np.count_nonzero(solo & other_object & (full != k)))
            lost_fraction[v, i] = lost / n_solo
            occluded[v, i] = lost > tol * n_solo and lost >= min_pixels
    flags = occluded.any(axis=1)
    return OcclusionResult(
        ratio=float(flags.mean()) if V else 0.0, view_flags=flags, occluded=occluded,
        lost_fraction=lost_fraction, solo_pixels=solo_px, object_ids=ids,
    )


def occlusion_ratio(
    rig: SimCameraRig,
    capture: Capture | None = None,
    poses: np.ndarray | None = None,
    tol: float = 0.02,
    min_pixels: int = 4,
) -> OcclusionResult:
    """The paper's OCC for the rig's scene in its current state.

    Uses the views (poses, intrinsics and instance masks) of ``capture`` when given (it must come
    from this rig's scene in the same state); otherwise renders masks at ``poses`` (V, 4, 4)
    (default: the rig layout). Costs one solo segmentation render per object and view.
    """
    if capture is not None:
        if not capture.has_masks:
            raise CaptureError("occlusion_ratio needs a capture with instance masks; capture with the 'mask' channel")
        Ts, Ks, full = capture.poses(), capture.Ks(), capture.masks()
    else:
        Ts = rig.poses() if poses is None else np.asarray(poses, np.float64).reshape(-1, 4, 4)
        Ks = np.repeat(rig.K()[None], len(Ts), axis=0)
        full = np.stack([rig.render_view(T, K, channels=("mask",)).mask for T, K in zip(Ts, Ks, strict=True)])
    solos = [rig.render_solo_masks(T, K) for T, K in zip(Ts, Ks, strict=True)]
    return occlusion_from_masks(full, solos, rig.object_ids, tol=tol, min_pixels=min_pixels)
