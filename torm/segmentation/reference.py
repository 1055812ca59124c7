"""Reference views: the same camera over the empty workspace, as evidence for segmentation (issue 43).

A robot flies its capture path once before the objects are placed; each scene view then has a reference view.
Glass changes the pixels behind it (refraction, reflections, rims), so the scene-minus-reference difference is a
high-recall cue; alone it is not a segmenter (shadows, render or sensor noise and a fraction of a pixel of
misregistration all differ too: mean IoU 0.63 measured on PBR pairs, ``../shared/facts/PERCEPTION.md``).

- :func:`attach_reference`: pair a recorded reference capture with a scene capture, view by view, by camera pose;
  refuse a reference whose poses differ by more than the arm's repeatability, of another image size or of another
  renderer (named errors with the fix).
- :func:`difference_instances`: the plain thresholded difference (per-channel exposure normalisation with the
  reference's gain read off the static background, optional Gaussian smoothing of both images, |scene - reference|
  > ``threshold`` grey levels in any channel, close 7x7, open 3x3, holes filled, connected components >=
  ``min_area_px``) as instance masks: the baseline, and the high-recall seed. :func:`pair_noise` measures a pair's
  noise; ``blur_sigma_px: auto`` (the default) smooths only pairs that have some.
- :class:`DifferenceSegmenter` (``difference``): that baseline as a :class:`~torm.segmentation.base.Segmenter`.
- :func:`check_background`: the median absolute difference between scene and reference outside the (dilated)
  objects after segmentation, or over the whole views before it; above ``max_grey`` the static background no longer
  matches (the table moved, the light changed) and the reference is refused.

The reference-mode learned model (``in_channels`` 6) reads scene and reference side by side:
:class:`torm.segmentation.learned.LearnedSegmenter` with a model trained by ``torm train-segmenter`` with
``train.reference: true``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

from torm.errors import CaptureError, ConfigError
from torm.segmentation.base import Detection, SegmentationResult, Segmenter, score_against_capture
from torm.types import Capture

log = logging.getLogger(__name__)

#: default pose tolerance between a view and its reference: a UR-class arm's stated pose repeatability is
#: +-0.03-0.1 mm, hand-eye and re-planned paths add more; 2 mm / 0.5 deg admits a re-flown path, not a moved camera
MAX_SHIFT_MM = 2.0
MAX_ROT_DEG = 0.5


def _rot_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def attach_reference(capture: Capture, reference: Capture, max_shift_mm: float = MAX_SHIFT_MM,
                     max_rot_deg: float = MAX_ROT_DEG) -> Capture:
    """``capture`` with every view's ``reference_rgb`` set from the reference capture's view at the nearest camera
    pose. Raises :class:`CaptureError` when a view has no reference within ``max_shift_mm`` / ``max_rot_deg``,
    when the image sizes differ, or when the two captures name different renderers."""
    if any(v.rgb is None for v in reference.views):
        raise CaptureError("the reference capture has views without RGB images; record it with RGB")
    r_scene = str(capture.metadata.get("renderer") or "recorded")
    r_ref = str(reference.metadata.get("renderer") or "recorded")
    if r_scene.split()[0] != r_ref.split()[0] or ("scalar_rgb" in r_scene) != ("scalar_rgb" in r_ref):
        raise CaptureError(f"the reference was rendered by {r_ref!r} but the scene by {r_scene!r}: a reference "
                           "must come from the same camera or renderer; record it again")
    if reference.image_size != capture.image_size:
        raise CaptureError(f"reference images are {reference.image_size[1]}x{reference.image_size[0]} but the scene's "
                           f"are {capture.image_size[1]}x{capture.image_size[0]}; record the reference with the same "
                           "camera settings")
    t_ref = np.stack([v.T_world_cam[:3, 3] for v in reference.views])
    views = []
    for i, v in enumerate(capture.views):
        d = np.linalg.norm(t_ref - v.T_world_cam[:3, 3], axis=1) * 1000.0
        j = int(np.argmin(d))
        rot = _rot_deg(v.T_world_cam[:3, :3], reference.views[j].T_world_cam[:3, :3])
        if d[j] > max_shift_mm or rot > max_rot_deg:
            raise CaptureError(f"view {i} ({v.name!r}): the nearest reference view ({j}) is {d[j]:.1f} mm and "
                               f"{rot:.2f} deg away (allowed {max_shift_mm} mm, {max_rot_deg} deg): the reference "
                               "pass must fly the same camera poses; record it again with the same path")
        views.append(v.with_(reference_rgb=reference.views[j].rgb))
    from dataclasses import replace

    meta = dict(capture.metadata)
    meta["reference"] = {"source": str(reference.metadata.get("source") or reference.scenario or "recorded"),
                         "recorded": reference.metadata.get("date") or reference.metadata.get("created"),
                         "renderer": r_ref}
    return replace(capture, views=tuple(views), metadata=meta)


def _normalised_pair(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exposure normalisation of a scene / reference pair (float32, grey levels): the scene's channels scaled to a
    mean of 128, the reference's by the same factor times its per-channel gain to the scene, the median of the
    pixel ratios scene / reference over pixels above 8 grey levels in both. The median is read off the static
    background, which most pixels show; a mean ratio would also count the objects, which only the scene holds, and
    leave a difference of a few grey levels on a background that did not change."""
    a, b = rgb_hxwx3.astype(np.float32), reference_hxwx3.astype(np.float32)
    k = 128.0 / np.maximum(a.reshape(-1, 3).mean(axis=0), 1.0)
    gain = np.ones(3, np.float32)
    for c in range(3):
        ok = (a[..., c] > 8) & (b[..., c] > 8)
        if np.count_nonzero(ok) >= 100:
            gain[c] = float(np.median(a[..., c][ok] / b[..., c][ok]))
    return a * k, b * (k * gain)


def _noise(a_hxwx3: np.ndarray, b_hxwx3: np.ndarray) -> float:
    d = (a_hxwx3 - b_hxwx3).reshape(-1, 3)
    return float((1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)).max())


def pair_noise(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray) -> float:
    """Robust noise of a scene / reference pair, grey levels: the largest over channels of 1.4826 x the median
    absolute deviation of the exposure-normalised difference (a Gaussian's sigma; the objects, a minority of the
    pixels, do not move it). 0 for a deterministic renderer's passes (MuJoCo); 1.5-3 for Mitsuba at 16 spp."""
    return _noise(*_normalised_pair(rgb_hxwx3, reference_hxwx3))


#: the smoothing ``blur_sigma_px: auto`` applies to a pair with noise (px), and the noise below which a pair counts
#: as noise-free (grey levels: below half a level only the 8-bit quantisation differs)
AUTO_BLUR_PX = 1.5
NOISE_FREE_GREY = 0.5


def _resolve(a_hxwx3: np.ndarray, b_hxwx3: np.ndarray, blur_sigma_px: float | str) -> float:
    if blur_sigma_px == "auto":
        return 0.0 if _noise(a_hxwx3, b_hxwx3) < NOISE_FREE_GREY else AUTO_BLUR_PX
    return float(blur_sigma_px)


def resolve_blur(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray, blur_sigma_px: float | str) -> float:
    """The smoothing (px) for a pair: ``blur_sigma_px`` itself, or for ``"auto"`` 0 when the pair is noise-free
    (:func:`pair_noise` < :data:`NOISE_FREE_GREY`) and :data:`AUTO_BLUR_PX` otherwise."""
    if blur_sigma_px != "auto":
        return float(blur_sigma_px)
    return _resolve(*_normalised_pair(rgb_hxwx3, reference_hxwx3), blur_sigma_px)


def difference_map(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray, blur_sigma_px: float | str = 0.0
                   ) -> np.ndarray:
    """(H, W) float32: max over channels of |scene - reference| after exposure normalisation
    (:func:`_normalised_pair`; grey levels); with ``blur_sigma_px`` > 0 both images are first smoothed by a Gaussian
    of that sigma (px), which averages out independent render or sensor noise between the two passes; ``"auto"``:
    :func:`resolve_blur`."""
    return _difference(rgb_hxwx3, reference_hxwx3, blur_sigma_px)[0]


def _difference(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray, blur_sigma_px: float | str
                ) -> tuple[np.ndarray, float]:
    """(:func:`difference_map`, the smoothing it applied in px)."""
    a, b = _normalised_pair(rgb_hxwx3, reference_hxwx3)
    sigma = _resolve(a, b, blur_sigma_px)
    if sigma > 0:
        a, b = (cv2.GaussianBlur(x, (0, 0), sigma) for x in (a, b))
    return np.abs(a - b).max(axis=2), sigma


def difference_instances(rgb_hxwx3: np.ndarray, reference_hxwx3: np.ndarray, threshold: float = 10.0,
                         min_area_px: int = 60, blur_sigma_px: float | str = 0.0) -> np.ndarray:
    """(H, W) int32 instances of the thresholded difference (see the module docstring), ids 1..N by area."""
    return _instances((difference_map(rgb_hxwx3, reference_hxwx3, blur_sigma_px) > threshold).astype(np.uint8),
                      min_area_px)


def _instances(fg: np.ndarray, min_area_px: int) -> np.ndarray:
    """Close 7x7, open 3x3, fill holes and keep connected components >= ``min_area_px`` of a (H, W) uint8 mask."""
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8))
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    # fill holes: background not connected to the border becomes foreground
    h, w = fg.shape
    flood = fg.copy()
    cv2.floodFill(flood, np.zeros((h + 2, w + 2), np.uint8), (0, 0), 1)
    fg = fg | (1 - flood)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    keep = [k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= min_area_px]
    keep.sort(key=lambda k: -stats[k, cv2.CC_STAT_AREA])
    out = np.zeros((h, w), np.int32)
    for new, k in enumerate(keep, start=1):
        out[lab == k] = new
    return out


#: the background check's limit, grey levels (median exposure-normalised |scene - reference|, both smoothed as the
#: difference's default, outside the objects). Chosen on a development set (layout seeds 100-123, PBR,
#: benchmarks/results/reference_background_dev.md): every valid pair <= 1.36, every stale one (another table and
#: lights) >= 5.23, whichever masks; 4 is 3x the largest valid value, headroom for a real camera's noise and flicker
BACKGROUND_MAX_GREY = 4.0


def check_background(capture: Capture, masks_vxhxw: np.ndarray | None = None, max_grey: float = BACKGROUND_MAX_GREY,
                     dilate_px: int = 15, blur_sigma_px: float | str = "auto") -> float:
    """Median over views of the median |scene - reference| (grey levels, exposure-normalised, both smoothed by
    ``blur_sigma_px`` as in :func:`difference_map`) outside the objects (``masks`` > 0, dilated by ``dilate_px``);
    raises :class:`CaptureError` above ``max_grey`` (the static background changed since the reference pass).
    Where the dilated masks cover more than half of a view, the median is taken over the whole view: a stale
    reference makes a segmenter that reads it (``difference``) mark most of the table, which would leave nothing to
    check; the objects, a minority of the pixels, do not move a median. ``masks_vxhxw`` None: the whole views (a
    check before segmentation). Returns the value."""
    if masks_vxhxw is not None and len(masks_vxhxw) != len(capture.views):
        raise CaptureError(f"{len(masks_vxhxw)} masks for {len(capture.views)} views: give one mask per view")
    vals = []
    k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    for i, v in enumerate(capture.views):
        if v.reference_rgb is None or v.rgb is None:
            continue
        d = difference_map(v.rgb, v.reference_rgb, blur_sigma_px)
        bg = None if masks_vxhxw is None else cv2.dilate((np.asarray(masks_vxhxw[i]) > 0).astype(np.uint8), k) == 0
        vals.append(float(np.median(d if bg is None or bg.mean() < 0.5 else d[bg])))
    if not vals:
        return 0.0
    med = float(np.median(vals))
    if med > max_grey:
        raise CaptureError(f"the static background differs from the reference pass by {med:.1f} grey levels "
                           f"(median outside the objects; allowed {max_grey}): the table, the camera or the lighting "
                           "changed since it was recorded; record a new reference pass over the empty workspace")
    return med


@dataclass(frozen=True)
class DifferenceConfig:
    """``threshold`` grey levels (exposure-normalised |scene - reference|), ``min_area_px`` px, ``blur_sigma_px``
    px (Gaussian smoothing of both images first; 0 = none; ``"auto"``: none on a noise-free pair, else
    :data:`AUTO_BLUR_PX`, see :func:`resolve_blur`)."""

    threshold: float = 10.0
    min_area_px: int = 60
    # 1.5 px was chosen on a development set of PBR pairs (layout seeds 100-123, benchmarks/results/
    # segmentation_reference_dev_blur.md: glass IoU 0.28 unsmoothed, 0.53 / 0.58 / 0.57 / 0.55 at 1 / 1.5 / 2 / 3 px);
    # it trades recall for precision (reported set: recall 0.91 -> 0.77, precision 0.29 -> 0.72). On noise-free
    # pairs (MuJoCo, segmentation_reference_dev_blur_mujoco.md: 0.91 unsmoothed, 0.82 smoothed) it only costs, so
    # "auto" leaves those unsmoothed. For the high-recall seed set 0
    blur_sigma_px: float | Literal["auto"] = "auto"

    def __post_init__(self) -> None:
        blur_ok = self.blur_sigma_px == "auto" or (
            isinstance(self.blur_sigma_px, (int, float)) and 0.0 <= self.blur_sigma_px <= 10.0)
        if not self.threshold > 0 or self.min_area_px < 0 or not blur_ok:
            raise ConfigError("difference: need threshold > 0, min_area_px >= 0 and blur_sigma_px 'auto' or a number "
                              f"of px in [0, 10] (got {self.blur_sigma_px!r})")


class DifferenceSegmenter(Segmenter):
    """The plain scene-minus-reference segmenter (``difference``); every view needs ``reference_rgb``."""

    name = "difference"

    def __init__(self, config: DifferenceConfig | None = None) -> None:
        self.config = config or DifferenceConfig()

    def segment(self, capture: Capture) -> SegmentationResult:
        import time

        t0 = time.perf_counter()
        masks, dets, blurs = [], [], []
        for i, v in enumerate(capture.views):
            if v.rgb is None or v.reference_rgb is None:
                raise CaptureError(f"view {i} ({v.name!r}) has no reference view; the difference segmenter needs a "
                                   "reference pass (--set capture.reference=true, or torm segment --reference DIR)")
            diff, sigma = _difference(v.rgb, v.reference_rgb, self.config.blur_sigma_px)
            m = _instances((diff > self.config.threshold).astype(np.uint8), self.config.min_area_px)
            d = []
            for k in range(1, int(m.max()) + 1):
                ys, xs = np.nonzero(m == k)
                d.append(Detection((float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)), 1.0,
                                   "object", k))
            masks.append(m)
            dets.append(tuple(d))
            blurs.append(sigma)
        info: dict[str, Any] = {"segmenter": self.name, "threshold": self.config.threshold,
                                "blur_sigma_px": self.config.blur_sigma_px,
                                "blur_sigma_px_used": sorted(set(blurs))}
        out = np.stack(masks)
        info.update(score_against_capture(out, capture))
        return SegmentationResult(out, tuple(dets), {"total": time.perf_counter() - t0}, info)
