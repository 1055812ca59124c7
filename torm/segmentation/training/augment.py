"""Training-time augmentation for transfer to real cameras: scale and the sensor effects renders lack.

Pure numpy / OpenCV functions of one sample, each driven by an explicit ``numpy.random.Generator``:

- :func:`zoom`: crop a window ``1/s`` of the output size around a random point and resize it to the output size
  (objects ``s`` times larger: real captures stand closer, or use a longer lens, than the rig); targets follow
  (masks nearest, heatmap linear, centre offsets scaled by ``s``).
- :func:`sensor_effects`: what a real camera adds after the optics, in the order it happens: vignetting, lateral
  chromatic aberration (red and blue scaled about the image centre), exposure (linear gain), white balance
  (per-channel gains), defocus / motion blur, shot + read noise, gamma, JPEG compression. Ranges are in
  :data:`SENSOR_RANGES`; every effect fires with probability ``p`` (its last entry).

Images are float32 RGB 0..255 (H, W, 3) in and out.
"""

from __future__ import annotations

import cv2
import numpy as np

#: (low, high, probability) of each sensor effect
SENSOR_RANGES: dict[str, tuple[float, float, float]] = {
    "vignetting": (0.0, 0.45, 0.5),  # brightness lost at the corners (fraction)
    "chromatic_px": (0.0, 1.5, 0.4),  # red / blue displacement at the image corner (px)
    "exposure": (0.45, 1.8, 0.8),  # linear gain
    "white_balance": (0.75, 1.3, 0.7),  # per-channel gain (red and blue; green 1)
    "blur_sigma_px": (0.3, 1.4, 0.35),  # Gaussian blur
    "noise": (0.0, 0.08, 0.7),  # shot-noise scale: sigma = sqrt(k * I) + read noise
    "gamma": (0.75, 1.35, 0.5),  # output = 255 (I / 255) ** gamma
    "jpeg_quality": (30.0, 95.0, 0.5),
}


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x / 255.0, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def sensor_effects(img_hxwx3: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> tuple[np.ndarray,
                                                                                                      dict]:
    """``img`` (H, W, 3) float32 RGB 0..255 with random sensor effects; returns (image, what was applied).

    ``strength`` scales every effect's probability (0 = none)."""
    R = SENSOR_RANGES
    applied: dict[str, float] = {}

    def fire(key: str) -> float | None:
        lo, hi, p = R[key]
        if rng.random() < p * strength:
            v = float(rng.uniform(lo, hi))
            applied[key] = v
            return v
        return None

    h, w = img_hxwx3.shape[:2]
    lin = _srgb_to_linear(img_hxwx3.astype(np.float32))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cy, cx = (h - 1) / 2, (w - 1) / 2
    r2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / (cy**2 + cx**2)
    if (v := fire("vignetting")) is not None:
        lin = lin * (1.0 - v * r2)[..., None]
    if (v := fire("chromatic_px")) is not None:  # lateral CA: red and blue magnified / shrunk about the centre
        scale = v / max(np.hypot(cx, cy), 1.0)
        for c, sgn in ((0, 1.0), (2, -1.0)):
            s = 1.0 + sgn * scale
            M = np.float32([[s, 0, cx * (1 - s)], [0, s, cy * (1 - s)]])
            lin[..., c] = cv2.warpAffine(lin[..., c], M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    if (v := fire("exposure")) is not None:
        lin = lin * v
    if (v := fire("white_balance")) is not None:
        lin = lin * np.array([v, 1.0, rng.uniform(*R["white_balance"][:2])], np.float32)
    if (v := fire("blur_sigma_px")) is not None:
        lin = cv2.GaussianBlur(lin, (0, 0), v)
    if (v := fire("noise")) is not None:
        sigma = np.sqrt(np.clip(lin, 0, None) * v * 0.05) + rng.uniform(0.0, 0.01)
        lin = lin + rng.normal(0.0, 1.0, lin.shape).astype(np.float32) * sigma
    out = _linear_to_srgb(lin)
    if (v := fire("gamma")) is not None:
        out = 255.0 * np.power(np.clip(out / 255.0, 0, 1), v)
    if (v := fire("jpeg_quality")) is not None:
        ok, buf = cv2.imencode(".jpg", np.clip(out, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, int(v)])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32)
    return np.clip(out, 0, 255).astype(np.float32), applied


def zoom(img_hxwx3: np.ndarray, tgt_cxhxw: np.ndarray, s: float, rng: np.random.Generator,
         offset_channels: tuple[int, int] | None = None, nearest_channels: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Magnify by ``s`` >= 1: a random ``(H/s, W/s)`` window resized back to (H, W).

    Targets ``tgt`` (C, H, W): the first ``nearest_channels`` (foreground, boundary) resized nearest, the rest
    linearly; ``offset_channels`` (dy, dx channel indices, in px) are multiplied by ``s``."""
    if s <= 1.0:
        return img_hxwx3, tgt_cxhxw
    h, w = img_hxwx3.shape[:2]
    wh, ww = max(16, int(round(h / s))), max(16, int(round(w / s)))
    y0, x0 = int(rng.integers(0, h - wh + 1)), int(rng.integers(0, w - ww + 1))
    img = cv2.resize(img_hxwx3[y0:y0 + wh, x0:x0 + ww], (w, h), interpolation=cv2.INTER_LINEAR)
    out = np.empty((tgt_cxhxw.shape[0], h, w), np.float32)
    for c in range(tgt_cxhxw.shape[0]):
        interp = cv2.INTER_NEAREST if c < nearest_channels else cv2.INTER_LINEAR
        out[c] = cv2.resize(np.ascontiguousarray(tgt_cxhxw[c, y0:y0 + wh, x0:x0 + ww], np.float32), (w, h),
                            interpolation=interp)
    if offset_channels is not None:
        for c in offset_channels:
            out[c] *= h / wh if c == offset_channels[0] else w / ww
    return img.astype(np.float32), out
