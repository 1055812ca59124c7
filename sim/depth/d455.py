"""The Intel RealSense D455 depth sensor: constants with their sources, and its opaque-surface error model.

Every number here is cited; :func:`sensor_record` puts them into trial records. Units: m, px, deg.

Parameters and their sources: ``sim/depth/README.md`` (table "D455") and :data:`SOURCES`.

Check against the datasheet: at 848 x 480, f = 424 / tan(43.5 deg) = 446.8 px, so at 4 m
``sigma_z = 16 * 0.08 / (446.8 * 0.095) = 0.030 m`` (0.75 %), inside the datasheet's "RMS < 2 % at 4 m";
at 0.5 m (our capture radius) it is 0.47 mm. Min-Z = 446.8 * 0.095 / 126 = 0.337 m (Intel quotes "close to
34 cm" at 848 x 480, issue 9241). The sensor depth is registered to the colour camera (``rs.align``), so
it lives on the colour pixel grid while its noise follows the depth imager's focal length.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from torm.errors import ConfigError

#: Where each D455 constant comes from (recorded in trial records and the docs table).
SOURCES: dict[str, str] = {
    "baseline_m": "D455 datasheet: stereo baseline 95 mm",
    "depth_hfov_deg": "D455 datasheet: depth FOV 87 x 58 deg",
    "depth_vfov_deg": "D455 datasheet: depth FOV 87 x 58 deg",
    "depth_width": "librealsense issues 9241/11180: 848x480 is the D455's optimal depth resolution",
    "depth_height": "librealsense issues 9241/11180: 848x480 is the D455's optimal depth resolution",
    "subpixel_rms_px": "Intel white paper 'Tuning depth cameras for best performance' rev 2.0: subpixel RMS ~0.08",
    "disparity_range_px": "same white paper: MinZ = f B / 126",
    "max_range_m": "D455 datasheet: ideal range 0.6-6 m",
}


@dataclass(frozen=True)
class D455Sensor:
    """The depth imager of a D455 (see the module docstring for every value's source).

    Attributes:
        baseline_m: stereo baseline (m).
        depth_hfov_deg, depth_vfov_deg: depth field of view (deg).
        depth_width, depth_height: depth stream resolution (px).
        subpixel_rms_px: RMS disparity error of the matcher (px).
        disparity_range_px: disparity search range (px); sets the minimum range ``f B / range``.
        max_range_m: readings beyond this z-depth are dropped (m).
    """

    baseline_m: float = 0.095
    depth_hfov_deg: float = 87.0
    depth_vfov_deg: float = 58.0
    depth_width: int = 848
    depth_height: int = 480
    subpixel_rms_px: float = 0.08
    disparity_range_px: float = 126.0
    max_range_m: float = 6.0

    def __post_init__(self) -> None:
        for name in ("baseline_m", "subpixel_rms_px", "disparity_range_px", "max_range_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"d455.{name} must be > 0, got {getattr(self, name)}")
        if not (0 < self.depth_hfov_deg < 170 and 0 < self.depth_vfov_deg < 170):
            raise ConfigError(f"d455 depth FOV must be in (0, 170) deg, got {self.depth_hfov_deg} x "
                              f"{self.depth_vfov_deg}")
        if self.depth_width < 8 or self.depth_height < 8:
            raise ConfigError(f"d455 depth stream {self.depth_width}x{self.depth_height} is too small")

    @property
    def focal_px(self) -> float:
        """Depth imager focal length (px) at the depth stream resolution."""
        return 0.5 * self.depth_width / math.tan(math.radians(self.depth_hfov_deg) / 2)

    @property
    def min_range_m(self) -> float:
        """Min-Z (m): the nearest z-depth the disparity search reaches, ``f B / disparity_range``."""
        return self.focal_px * self.baseline_m / self.disparity_range_px

    def sigma_z(self, z_m: np.ndarray) -> np.ndarray:
        """Depth RMS error (m) at z-depth ``z_m`` (m): ``z^2 sigma_d / (f B)``."""
        z = np.asarray(z_m, dtype=np.float64)
        return z * z * self.subpixel_rms_px / (self.focal_px * self.baseline_m)

    def measure_opaque(self, z_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """What the sensor reports for exact opaque z-depths ``z_m`` (H, W) m: Gaussian stereo noise, range limits.

        0 (no reading) where ``z_m`` is 0/NaN (no surface) or outside [min_range_m, max_range_m]. float32 m.
        """
        z = np.nan_to_num(np.asarray(z_m, dtype=np.float64), nan=0.0)
        out = z + rng.standard_normal(z.shape) * self.sigma_z(z)
        ok = (z > 0) & (z >= self.min_range_m) & (z <= self.max_range_m)
        return np.where(ok, out, 0.0).astype(np.float32)

    def record(self) -> dict[str, object]:
        """The parameters, derived values and their sources (JSON-ready)."""
        return {**asdict(self), "focal_px": self.focal_px, "min_range_m": self.min_range_m,
                "sigma_z_at_0.5m": float(self.sigma_z(np.array(0.5))), "sources": dict(SOURCES)}
