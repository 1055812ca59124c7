"""Semi-global matching of a rectified IR pair into z-depth (OpenCV ``StereoSGBM``), renderer-independent.

Starts from SAPIEN's published active-stereo settings (simsense, T-RO 2023; REALISM.md): 7x7 blocks, 128
disparities, P1 8, P2 32, uniqueness 15, left-right check 1, median 3. SAPIEN's P1/P2 are penalties on a
per-pixel census cost; OpenCV's SGBM cost is a Birchfield-Tomasi SAD summed over the block, so the penalties
are scaled the way OpenCV documents them: ``P1 = 8 * channels * block^2`` and ``P2 = 32 * channels * block^2``
(392 and 1568 for a 7x7 monochrome block). Depth = f B / d on the left (reference) camera's pixel grid;
disparities at or below 0 and those OpenCV marks invalid give no reading (0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torm.errors import ConfigError


@dataclass(frozen=True)
class SGBMSettings:
    """OpenCV ``StereoSGBM`` settings (SAPIEN's, P1/P2 scaled per OpenCV; see the module docstring)."""

    block_size: int = 7
    num_disparities: int = 128
    p1_per_pixel: int = 8
    p2_per_pixel: int = 32
    uniqueness_ratio: int = 15
    disp12_max_diff: int = 1
    median: int = 3

    def __post_init__(self) -> None:
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ConfigError(f"sgbm.block_size must be odd and >= 1, got {self.block_size}")
        if self.num_disparities < 16 or self.num_disparities % 16:
            raise ConfigError(f"sgbm.num_disparities must be a positive multiple of 16, got {self.num_disparities}")
        if not 0 < self.p1_per_pixel < self.p2_per_pixel:
            raise ConfigError("sgbm needs 0 < p1_per_pixel < p2_per_pixel")
        if self.median not in (0, 1, 3, 5):
            raise ConfigError(f"sgbm.median must be 0, 1, 3 or 5 (px), got {self.median}")

    @property
    def P1(self) -> int:
        """OpenCV's P1 for a monochrome image: ``8 * block^2``."""
        return self.p1_per_pixel * self.block_size ** 2

    @property
    def P2(self) -> int:
        """OpenCV's P2 for a monochrome image: ``32 * block^2``."""
        return self.p2_per_pixel * self.block_size ** 2


def disparity(left_hxw: np.ndarray, right_hxw: np.ndarray, s: SGBMSettings | None = None) -> np.ndarray:
    """(H, W) float32 disparity (px) of a rectified uint8 pair, left = reference; NaN = no match."""
    import cv2

    s = s or SGBMSettings()
    if left_hxw.shape != right_hxw.shape or left_hxw.ndim != 2:
        raise ConfigError(f"stereo pair images must be equal 2-D arrays, got {left_hxw.shape} and {right_hxw.shape}")
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=s.num_disparities, blockSize=s.block_size,
                                 P1=s.P1, P2=s.P2, disp12MaxDiff=s.disp12_max_diff, uniquenessRatio=s.uniqueness_ratio,
                                 speckleWindowSize=0, speckleRange=0, mode=cv2.STEREO_SGBM_MODE_SGBM)
    raw = sgbm.compute(np.ascontiguousarray(left_hxw, np.uint8), np.ascontiguousarray(right_hxw, np.uint8))
    if s.median > 1:
        raw = cv2.medianBlur(raw, s.median)
    d = raw.astype(np.float32) / 16.0
    d[raw <= 0] = np.nan
    return d


def depth_from_disparity(disp_hxw: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """(H, W) float32 z-depth (m) = f B / d; 0 where the disparity is NaN or <= 0."""
    d = np.asarray(disp_hxw, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(np.isfinite(d) & (d > 0), focal_px * baseline_m / d, 0.0)
    return z.astype(np.float32)


def register_depth(depth_ir_hxw: np.ndarray, K_ir: np.ndarray, T_world_ir: np.ndarray, K_col: np.ndarray,
                   T_world_col: np.ndarray, shape_col: tuple[int, int]) -> np.ndarray:
    """Reproject a depth image of the IR camera onto the colour camera's grid (nearest surface wins), z-depth m.

    Like ``rs.align(rs.stream.color)``: every valid IR pixel becomes a 3-D point that is projected into the
    colour camera; pixels no point lands in get 0. Frames: OpenCV camera-to-world poses (m).
    """
    from torm.geometry import backproject_depth

    H, W = shape_col
    z = np.nan_to_num(np.asarray(depth_ir_hxw, dtype=np.float64), nan=0.0)
    ok = z > 0
    p_ir = backproject_depth(z, K_ir)[ok]
    T = np.linalg.inv(T_world_col) @ T_world_ir
    p = p_ir @ T[:3, :3].T + T[:3, 3]
    front = p[:, 2] > 1e-6
    p = p[front]
    u = np.floor(K_col[0, 0] * p[:, 0] / p[:, 2] + K_col[0, 2]).astype(np.int64)
    v = np.floor(K_col[1, 1] * p[:, 1] / p[:, 2] + K_col[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out = np.full(H * W, np.inf)
    np.minimum.at(out, v[inside] * W + u[inside], p[inside, 2])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(H, W).astype(np.float32)
