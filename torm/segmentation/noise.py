"""A seeded error model that corrupts ground-truth masks the way segmenters fail on glass.

Operations, in the order they are applied to each view of a (V, H, W) instance-mask stack:

1. **Boundary offset** (erode/dilate): every object's boundary moves outwards (dilation, probability
   ``p_dilate``) or inwards (erosion) by a radius drawn uniformly from ``boundary_radius_px``; one
   draw per view (``boundary_mode="view"``) or per view and object (``"object"``).
2. **Jagged boundaries** (in a fraction ``p_jagged_view`` of the views): a Gaussian-blurred white-noise
   field (correlation length ``jagged_scale_px``, std ``jagged_amplitude_px`` in pixels) is added to
   each object's signed distance before thresholding, so edges wander irregularly.
3. **Merged neighbours** (fraction ``p_merge_view``): the two closest objects whose gap is at most
   ``merge_max_gap_px`` are closed together (dilate-and-erode of their union) into one label.
4. **Missed object** (fraction ``p_missing_view``): one visible object is removed from the view.
5. **Spurious blob** (fraction ``p_spurious_view``): a random filled ellipse with semi-axes of
   ``spurious_size_range`` times the capture's median object radius appears as a new instance.

Steps 1-2 threshold ``f + noise < offset`` where ``f`` is the object's signed distance in pixels
(negative inside, the boundary at 0). Pixel quantities are multiplied by ``W / radius_ref_width``
when ``radius_ref_width`` is set, so a preset defined on 256 px images degrades a 640 px capture by the
same relative amount. The IoU a preset produces depends on how many pixels the objects cover: the
same 2 px erosion costs a 13 px-radius disc far more than a 60 px one (measured table: README.md).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from scipy import ndimage

from torm.errors import ConfigError, SegmentationError, UnknownNameError
from torm.segmentation.base import SegmentationResult, Segmenter
from torm.segmentation.gt import gt_masks
from torm.segmentation.quality import mask_quality
from torm.types import Capture


def _check_fraction(name: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ConfigError(f"noise.{name} = {value} must be a fraction in [0, 1]")


def _check_range(name: str, lo_hi: tuple[float, float]) -> None:
    lo, hi = lo_hi
    if lo < 0 or hi < lo:
        raise ConfigError(f"noise.{name} = {lo_hi} must be (low, high) with 0 <= low <= high")


@dataclass(frozen=True)
class NoiseConfig:
    """Parameters of the mask error model (pixels unless stated; fractions are of the views)."""

    boundary_radius_px: tuple[float, float] = (0.0, 0.0)
    p_dilate: float = 0.5
    boundary_mode: Literal["view", "object"] = "view"
    jagged_amplitude_px: float = 0.0
    jagged_scale_px: float = 3.0
    p_jagged_view: float = 0.0
    p_merge_view: float = 0.0
    merge_max_gap_px: float = 12.0
    p_missing_view: float = 0.0
    p_spurious_view: float = 0.0
    spurious_size_range: tuple[float, float] = (0.5, 1.2)
    radius_ref_width: int | None = None

    def __post_init__(self) -> None:
        _check_range("boundary_radius_px", self.boundary_radius_px)
        _check_range("spurious_size_range", self.spurious_size_range)
        for name in ("p_dilate", "p_jagged_view", "p_merge_view", "p_missing_view", "p_spurious_view"):
            _check_fraction(name, getattr(self, name))
        if self.boundary_mode not in ("view", "object"):
            raise ConfigError(f"noise.boundary_mode = {self.boundary_mode!r} must be 'view' or 'object'")
        if self.jagged_amplitude_px < 0 or self.jagged_scale_px <= 0 or self.merge_max_gap_px < 0:
            raise ConfigError("noise: jagged_amplitude_px and merge_max_gap_px must be >= 0, jagged_scale_px > 0")
        if self.radius_ref_width is not None and self.radius_ref_width <= 0:
            raise ConfigError("noise.radius_ref_width must be a positive image width in pixels (or null)")


#: Named severities. "paper" is RECONSTRUCTION.md's corruption (erode/dilate 1-3 px per view, one object
#: missing in 10 % of views, a spurious blob in 6 %); "paper256" is the same with pixel sizes scaled to a
#: capture's width relative to the 256 px prototype images.
PRESETS: dict[str, NoiseConfig] = {
    "none": NoiseConfig(),
    "mild": NoiseConfig(boundary_radius_px=(0.0, 1.0), boundary_mode="object", jagged_amplitude_px=0.5,
                        p_jagged_view=0.3, p_spurious_view=0.02),
    "moderate": NoiseConfig(boundary_radius_px=(1.0, 2.0), boundary_mode="object", jagged_amplitude_px=1.0,
                            p_jagged_view=0.5, p_merge_view=0.05, p_missing_view=0.05, p_spurious_view=0.04),
    "severe": NoiseConfig(boundary_radius_px=(2.0, 4.0), boundary_mode="object", jagged_amplitude_px=2.0,
                          p_jagged_view=1.0, p_merge_view=0.15, p_missing_view=0.15, p_spurious_view=0.10),
    "paper": NoiseConfig(boundary_radius_px=(1.0, 3.0), boundary_mode="view", p_missing_view=0.10,
                         p_spurious_view=0.06),
    "paper256": NoiseConfig(boundary_radius_px=(1.0, 3.0), boundary_mode="view", p_missing_view=0.10,
                            p_spurious_view=0.06, radius_ref_width=256),
}


#: Mean silhouette IoU vs GT each preset gives on ``synthetic.sphere_capture(n_views=50, size_px=256)``
#: (three spheres of ~12-16 px radius), over seeds 0-7: measured (low, high) with a small margin. Bigger
#: objects in pixels give higher IoU for the same preset (the same scene at 640 px: paper 0.85).
PRESET_EXPECTED_IOU: dict[str, tuple[float, float]] = {
    "none": (1.0, 1.0),
    "mild": (0.90, 0.96),
    "moderate": (0.75, 0.82),
    "severe": (0.57, 0.65),
    "paper": (0.68, 0.76),
    "paper256": (0.68, 0.76),
}


def noise_preset(name: str) -> NoiseConfig:
    """The named :class:`NoiseConfig`; UnknownNameError lists the presets."""
    if name not in PRESETS:
        raise UnknownNameError("noise preset", name, PRESETS)
    return PRESETS[name]


def _pick_views(rng: np.random.Generator, n_views: int, fraction: float) -> set[int]:
    k = int(round(fraction * n_views))
    if k <= 0:
        return set()
    return {int(i) for i in rng.choice(n_views, size=min(k, n_views), replace=False)}


def _signed_distance(obj_hxw: np.ndarray) -> np.ndarray:
    """Signed distance (px) to the boundary of a bool mask: < 0 inside, > 0 outside, pixel boundary at 0."""
    m = obj_hxw.astype(np.uint8)
    d_in = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_out = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(obj_hxw, -(d_in - 0.5), d_out - 0.5).astype(np.float32)


def _noise_field(rng: np.random.Generator, hw: tuple[int, int], scale_px: float) -> np.ndarray:
    """Smooth zero-mean unit-std noise (H, W) with correlation length ~``scale_px`` pixels."""
    white = rng.standard_normal(hw).astype(np.float32)
    blurred = cv2.GaussianBlur(white, (0, 0), sigmaX=scale_px, borderType=cv2.BORDER_REFLECT)
    std = float(blurred.std())
    return blurred / std if std > 0 else blurred


def _object_slices(m: np.ndarray) -> list[tuple[int, tuple[slice, slice]]]:
    """(id, bounding-box slices) of every instance id > 0 present in ``m``, ascending ids."""
    return [(k, sl) for k, sl in enumerate(ndimage.find_objects(m), start=1) if sl is not None]


def _present_ids(m: np.ndarray) -> list[int]:
    return [int(i) for i in np.nonzero(np.bincount(m.ravel()))[0] if i > 0]


def _disk(radius_px: float) -> np.ndarray:
    r = max(int(np.ceil(radius_px)), 1)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


class MaskCorruptor:
    """Applies a :class:`NoiseConfig` to instance masks with an explicit random generator."""

    def __init__(self, config: NoiseConfig, rng: np.random.Generator | int | None) -> None:
        self.config = config
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

    def corrupt(self, masks_vxhxw: np.ndarray) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """Corrupt (V, H, W) int instance masks; returns the new int32 masks and per-view event logs."""
        c = self.config
        gt = np.asarray(masks_vxhxw).astype(np.int32)
        V, H, W = gt.shape
        s = W / c.radius_ref_width if c.radius_ref_width else 1.0
        rng = self.rng
        jag = _pick_views(rng, V, c.p_jagged_view) if c.jagged_amplitude_px > 0 else set()
        merge = _pick_views(rng, V, c.p_merge_view)
        missing = _pick_views(rng, V, c.p_missing_view)
        spurious = _pick_views(rng, V, c.p_spurious_view)
        if gt.size and gt.min() < 0:
            raise SegmentationError("instance masks must be >= 0 (0 = background)")
        counts = [np.bincount(m.ravel()) for m in gt]
        ids_all = sorted({int(i) for c_v in counts for i in np.nonzero(c_v)[0] if i > 0})
        areas = [int(c_v[i]) for c_v in counts for i in np.nonzero(c_v)[0] if i > 0]
        r_med = float(np.sqrt(np.median(areas) / np.pi)) if areas else 0.03 * min(H, W)
        spurious_id = (max(ids_all) if ids_all else 0) + 1
        out = np.zeros_like(gt)
        events: list[dict[str, Any]] = []
        for v in range(V):
            ev: dict[str, Any] = {}
            m = self._boundary(gt[v], s, v in jag, ev)
            if v in merge:
                m = self._merge(m, c.merge_max_gap_px * s, ev)
            if v in missing:
                ids = _present_ids(m)
                if ids:
                    k = ids[int(rng.integers(len(ids)))]
                    m[m == k] = 0
                    ev["missing"] = k
            if v in spurious:
                m = self._blob(m, r_med, spurious_id, ev)
            out[v] = m
            events.append(ev)
        return out, events

    def _boundary(self, m: np.ndarray, s: float, jagged: bool, ev: dict[str, Any]) -> np.ndarray:
        c, rng = self.config, self.rng
        lo, hi = c.boundary_radius_px
        noise = _noise_field(rng, m.shape, c.jagged_scale_px * s) * (c.jagged_amplitude_px * s) if jagged else None
        if hi <= 0 and noise is None:
            return m.copy()

        def draw() -> float:
            r = float(rng.uniform(lo, hi)) * s
            return r if rng.random() < c.p_dilate else -r

        view_offset = draw()
        offsets = {}
        out = np.zeros_like(m)
        H, W = m.shape
        for k, sl in _object_slices(m):
            off = draw() if c.boundary_mode == "object" else view_offset
            offsets[k] = round(off, 3)
            # work in the object's box padded by the largest possible boundary move (exact, much faster)
            pad = int(np.ceil(abs(off) + (8.0 * c.jagged_amplitude_px * s if noise is not None else 0.0))) + 2
            ys = slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, H))
            xs = slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, W))
            mc, oc = m[ys, xs], out[ys, xs]
            f = _signed_distance(mc == k)
            if noise is not None:
                f = f + noise[ys, xs]
            new = f < off
            # dilation grows only into background (or this object's own pixels); first come, first served
            oc[new & ((mc == 0) | (mc == k)) & (oc == 0)] = k
        ev["offset_px"] = offsets
        if noise is not None:
            ev["jagged"] = True
        return out

    def _merge(self, m: np.ndarray, max_gap: float, ev: dict[str, Any]) -> np.ndarray:
        ids = _present_ids(m)
        best: tuple[float, int, int] | None = None
        for i, a in enumerate(ids):
            d_a = cv2.distanceTransform((m != a).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            for b in ids[i + 1:]:
                gap = float(d_a[m == b].min())
                if gap <= max_gap and (best is None or gap < best[0]):
                    best = (gap, a, b)
        if best is None:
            return m
        gap, a, b = best
        union = ((m == a) | (m == b)).astype(np.uint8)
        closed = cv2.morphologyEx(union, cv2.MORPH_CLOSE, _disk(gap / 2.0 + 1.0)) > 0
        out = m.copy()
        out[closed & ((m == 0) | (m == a) | (m == b))] = a
        ev["merged"] = [a, b]
        return out

    def _blob(self, m: np.ndarray, r_med: float, blob_id: int, ev: dict[str, Any]) -> np.ndarray:
        rng = self.rng
        H, W = m.shape
        a = max(r_med * float(rng.uniform(*self.config.spurious_size_range)), 1.0)
        b = max(a * float(rng.uniform(0.5, 1.0)), 1.0)
        margin = int(np.ceil(a))
        cx = int(rng.integers(min(margin, W - 1), max(W - margin, margin + 1)))
        cy = int(rng.integers(min(margin, H - 1), max(H - margin, margin + 1)))
        angle = float(rng.uniform(0.0, 180.0))
        canvas = np.zeros((H, W), np.uint8)
        cv2.ellipse(canvas, (cx, cy), (int(round(a)), int(round(b))), angle, 0.0, 360.0, 1, thickness=-1)
        out = m.copy()
        out[(canvas > 0) & (m == 0)] = blob_id
        ev["spurious"] = {"center_px": [cx, cy], "axes_px": [round(a, 2), round(b, 2)], "id": blob_id}
        return out


def corrupt_masks(
    masks_vxhxw: np.ndarray, config: NoiseConfig | str, rng: np.random.Generator | int | None
) -> np.ndarray:
    """Corrupt (V, H, W) instance masks with a config or preset name and a seed / Generator."""
    cfg = noise_preset(config) if isinstance(config, str) else config
    return MaskCorruptor(cfg, rng).corrupt(masks_vxhxw)[0]


@dataclass(frozen=True)
class NoisyConfig:
    """The ``noisy`` segmenter: GT masks corrupted by a preset, optionally with some fields replaced.

    ``overrides`` maps NoiseConfig field names to values, e.g. ``{"p_missing_view": 0.2}``.
    """

    preset: str = "paper"
    seed: int = 0
    overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(f"noisy.preset {self.preset!r} is unknown; valid presets: {', '.join(sorted(PRESETS))}")
        self.noise()  # validates the overrides

    def noise(self) -> NoiseConfig:
        """The preset with ``overrides`` applied (validated)."""
        valid = {f.name for f in dataclasses.fields(NoiseConfig)}
        unknown = sorted(set(self.overrides) - valid)
        if unknown:
            raise ConfigError(f"noisy.overrides: unknown key(s) {unknown}; valid keys: {sorted(valid)}")
        vals = {k: tuple(v) if isinstance(v, list) else v for k, v in self.overrides.items()}
        try:
            return dataclasses.replace(PRESETS[self.preset], **vals)
        except TypeError as exc:
            raise ConfigError(f"noisy.overrides: {exc}") from exc


class NoisySegmenter(Segmenter):
    """Ground-truth masks passed through :class:`MaskCorruptor`; reports the IoU against GT."""

    name = "noisy"

    def __init__(self, config: NoisyConfig | None = None) -> None:
        self.config = config or NoisyConfig()

    def segment(self, capture: Capture) -> SegmentationResult:
        t0 = time.perf_counter()
        gt = gt_masks(capture)
        noise = self.config.noise()
        masks, events = MaskCorruptor(noise, np.random.default_rng(self.config.seed)).corrupt(gt)
        t1 = time.perf_counter()
        quality = mask_quality(masks, gt)
        return SegmentationResult(
            masks_vxhxw=masks,
            timings={"corrupt": t1 - t0, "total": time.perf_counter() - t0},
            info={"segmenter": self.name, "preset": self.config.preset, "seed": self.config.seed,
                  "noise": dataclasses.asdict(noise), "quality": quality, "events": events},
        )
