"""``statistical``: a fast D455 model for throughput runs: per-pixel outcomes on glass, stereo noise elsewhere.

Opaque surfaces: the exact z-depth plus the D455's stereo error ``sigma_z = z^2 sigma_d / (f B)`` and its
range limits (:class:`sim.depth.d455.D455Sensor`).

Glass (the first surface hit is glass): each pixel gets one of three outcomes, as a real D4xx does on
transparent objects (REALISM.md):

- ``missing``: no reading (0);
- ``see-through``: the first opaque surface behind the glass along the same ray (Intel: the camera "will
  project the light onto the first opaque object behind the transparent surface"), with the opaque noise;
- ``near-surface``: the true glass surface plus an error drawn from N(0, ``near_sigma_m``) truncated to
  +-``near_max_m``.

The outcome probabilities depend on the incidence angle (between the viewing ray and the glass normal,
from the exact depth: :func:`sim.depth.geometry.incidence_deg`) through a table of angle bins. The table
is the *shape* measured by active-stereo simulation (Mitsuba 3 + SGBM, REALISM.md: camera tilt 0 / 45 /
60 deg) with one logit offset per outcome, shared by all bins, calibrated so that the mix over the glass
pixels of the **syn** suite equals the real D435 mix of ClearGrasp's frames (missing 51.6 %, see-through
26.8 %, within 3 cm 21.4 %); the **rw** suite is held out for the benchmark
(``benchmarks/depth_sensor.py --calibrate`` recomputes the offsets and writes
``benchmarks/results/depth_sensor_calibration.json``).

Spatial correlation: real failures come in blobs. Outcomes are drawn through a Gaussian copula: the
latent value of a pixel is ``sqrt(rho) g_obj + sqrt(1 - rho) f(pixel)``, ``g_obj`` one N(0, 1) draw per
(view, object), ``f`` a unit-variance Gaussian random field (white noise smoothed by a Gaussian of std
``correlation_px / 2`` px at 848 px image width, i.e. correlation ``exp(-r^2 / correlation_px^2)``: 1/e at
``r = correlation_px``); ``u = Phi(latent)`` is uniform per pixel, so the marginal probabilities are exactly
the table's, and a pixel is missing when ``u < p_missing``, see-through when ``u < p_missing + p_see``.

Parameters and their sources: ``sim/depth/README.md`` (table "statistical").

Limits, stated: no refraction offset in the see-through reading (it reads the opaque surface on the
unbent ray), no invalid band from the stereo baseline's occlusion, white (uncorrelated) opaque noise.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.special import ndtr, ndtri

from sim.depth.base import DepthScene
from sim.depth.d455 import D455Sensor
from sim.depth.geometry import incidence_deg
from torm.errors import ConfigError

#: Outcome names on glass pixels, in the order of the probability columns.
OUTCOMES = ("missing", "see_through", "near_surface")
#: Reference image width (px) at which ``correlation_px`` is stated (the D455's depth stream).
REFERENCE_WIDTH = 848
#: Stereo-measured outcome shares per bin (REALISM.md; see the module docstring), rows = bins.
ANCHOR_SHAPE = ((0.0225, 0.955, 0.0225), (0.367, 0.366, 0.268), (0.63, 0.08, 0.28))
#: Logit offsets (missing, see-through) relative to near-surface, fit on the syn suite to the real mix
#: (``benchmarks/results/depth_sensor_calibration.json``).
CALIBRATED_OFFSETS = (0.3114, 0.0288)
#: The real D435 mix on transparent objects (ClearGrasp real-val/d435, REALISM.md), renormalised over the
#: three outcomes (the 0.1 % "shallower by > 3 cm" dropped).
REAL_MIX = {"missing": 0.516, "see_through": 0.268, "near_surface": 0.214}


def bin_probabilities(anchor: tuple[tuple[float, float, float], ...], offsets: tuple[float, float]) -> np.ndarray:
    """(B, 3) outcome probabilities per bin: softmax(log anchor + (offset_missing, offset_see, 0))."""
    a = np.asarray(anchor, dtype=np.float64)
    logits = np.log(a / a.sum(axis=1, keepdims=True)) + np.array([offsets[0], offsets[1], 0.0])
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


@dataclass(frozen=True)
class StatisticalDepthConfig:
    """Parameters of the statistical model (sources in the module docstring).

    Attributes:
        bin_edges_deg: incidence-angle bin edges (deg), increasing, from 0 to 90.
        anchor_shape: per bin, (missing, see-through, near-surface) shares measured by stereo simulation.
        offsets: logit offsets (missing, see-through) relative to near-surface, shared by every bin.
        near_sigma_m: std (m) of a near-surface reading's error before truncation.
        near_max_m: truncation of the near-surface error (m).
        object_share: rho, the share of the latent variance common to one object in one view, [0, 1).
        correlation_px: correlation length (px at 848 px width) of the outcome field; 0 = independent pixels.
        sensor: the D455 depth imager (noise, range limits).
    """

    bin_edges_deg: tuple[float, ...] = (0.0, 22.5, 52.5, 90.0)
    anchor_shape: tuple[tuple[float, float, float], ...] = ANCHOR_SHAPE
    offsets: tuple[float, float] = CALIBRATED_OFFSETS
    near_sigma_m: float = 0.0167
    near_max_m: float = 0.03
    object_share: float = 0.40
    correlation_px: float = 7.0
    sensor: D455Sensor = field(default_factory=D455Sensor)

    def __post_init__(self) -> None:
        e = tuple(float(x) for x in self.bin_edges_deg)
        if len(e) < 2 or e[0] != 0.0 or e[-1] != 90.0 or any(b <= a for a, b in zip(e, e[1:], strict=False)):
            raise ConfigError(f"statistical.bin_edges_deg must increase from 0 to 90 deg, got {self.bin_edges_deg}")
        object.__setattr__(self, "bin_edges_deg", e)
        shape = tuple(tuple(float(p) for p in row) for row in self.anchor_shape)
        if len(shape) != len(e) - 1 or any(len(r) != 3 or min(r) <= 0 for r in shape):
            raise ConfigError(f"statistical.anchor_shape needs {len(e) - 1} rows of 3 positive shares "
                              f"(missing, see-through, near-surface), got {self.anchor_shape}")
        object.__setattr__(self, "anchor_shape", shape)
        if len(self.offsets) != 2 or not all(math.isfinite(o) for o in self.offsets):
            raise ConfigError(f"statistical.offsets must be 2 finite logits (missing, see-through), got {self.offsets}")
        object.__setattr__(self, "offsets", tuple(float(o) for o in self.offsets))
        if not (self.near_sigma_m > 0 and self.near_max_m > 0):
            raise ConfigError("statistical.near_sigma_m and near_max_m must be > 0 m")
        if not 0.0 <= self.object_share < 1.0:
            raise ConfigError(f"statistical.object_share must be in [0, 1), got {self.object_share}")
        if self.correlation_px < 0:
            raise ConfigError(f"statistical.correlation_px must be >= 0, got {self.correlation_px}")

    def probabilities(self) -> np.ndarray:
        """(B, 3) outcome probabilities per incidence bin (columns :data:`OUTCOMES`)."""
        return bin_probabilities(self.anchor_shape, self.offsets)


def angle_bins(angle_deg: np.ndarray, edges: tuple[float, ...]) -> np.ndarray:
    """Bin index per pixel; undefined angles (NaN: silhouette edges, isolated pixels) go to the last bin."""
    a = np.where(np.isfinite(angle_deg), angle_deg, 90.0)
    return np.clip(np.searchsorted(np.asarray(edges[1:-1]), a, side="right"), 0, len(edges) - 2)


def correlated_field(shape: tuple[int, int], sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) Gaussian random field with unit variance: white noise smoothed by a Gaussian of std ``sigma_px``."""
    white = rng.standard_normal(shape)
    if sigma_px <= 0:
        return white
    f = gaussian_filter(white, sigma_px, mode="reflect", truncate=4.0)
    r = int(4.0 * sigma_px + 0.5)
    delta = np.zeros((2 * r + 1, 2 * r + 1))
    delta[r, r] = 1.0
    std = float(np.sqrt(np.sum(gaussian_filter(delta, sigma_px, mode="constant", truncate=4.0) ** 2)))
    return f / std


class StatisticalDepth:
    """The statistical D455 model (see the module docstring)."""

    name = "statistical"
    needs_first_surface = True

    def __init__(self, config: StatisticalDepthConfig | None = None) -> None:
        self.config = config or StatisticalDepthConfig()
        self._p = self.config.probabilities()

    def outcomes(self, scene: DepthScene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) int8 outcome per pixel (-1 not glass, else the index into :data:`OUTCOMES`) and the incidence
        angle (deg, NaN where undefined)."""
        cfg = self.config
        H, W = scene.shape
        ang = np.full((H, W), np.nan)
        rows, cols = np.nonzero(scene.glass)
        if len(rows):  # normals only where there is glass (its bounding box plus a 1-pixel margin)
            r0, r1 = max(rows.min() - 1, 0), min(rows.max() + 2, H)
            c0, c1 = max(cols.min() - 1, 0), min(cols.max() + 2, W)
            K = scene.K.copy()
            K[0, 2] -= c0
            K[1, 2] -= r0
            ang[r0:r1, c0:c1] = incidence_deg(scene.depth_first[r0:r1, c0:c1], K, scene.instance[r0:r1, c0:c1])
        b = angle_bins(ang, cfg.bin_edges_deg)
        field_ = correlated_field((H, W), 0.5 * cfg.correlation_px * W / REFERENCE_WIDTH, rng)
        ids = scene.instance.astype(np.int64)
        g = rng.standard_normal(int(ids.max(initial=0)) + 1)
        latent = math.sqrt(cfg.object_share) * g[ids] + math.sqrt(1.0 - cfg.object_share) * field_
        u = ndtr(latent)
        p = self._p[b]
        out = np.where(u < p[..., 0], 0, np.where(u < p[..., 0] + p[..., 1], 1, 2)).astype(np.int8)
        out[~scene.glass] = -1
        return out, ang

    def sensor_depth(self, scene: DepthScene, rng: np.random.Generator) -> np.ndarray:
        """(H, W) float32 sensor z-depth (m), 0 = no reading."""
        cfg = self.config
        sensor = cfg.sensor
        outcome, _ = self.outcomes(scene, rng)
        first = np.nan_to_num(scene.depth_first.astype(np.float64), nan=0.0)
        opaque_read = sensor.measure_opaque(np.where(outcome == -1, first, scene.depth_opaque), rng)
        # near-surface: truncated normal error on the true glass surface (inverse-CDF sampling)
        a = ndtr(cfg.near_max_m / cfg.near_sigma_m)
        u = rng.uniform(1.0 - a, a, size=first.shape)
        near = first + cfg.near_sigma_m * ndtri(u)
        near_ok = (first >= sensor.min_range_m) & (first <= sensor.max_range_m)
        out = np.where(outcome == 2, np.where(near_ok, near, 0.0), opaque_read)
        out[outcome == 0] = 0.0
        return out.astype(np.float32)

    def record(self) -> dict[str, Any]:
        cfg = self.config
        d = asdict(cfg)
        d.pop("sensor")
        return {"name": self.name, **d, "outcomes": list(OUTCOMES),
                "bin_probabilities": self._p.round(4).tolist(), "real_mix_target": dict(REAL_MIX),
                "sensor": cfg.sensor.record()}
