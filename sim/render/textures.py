"""Procedural table-top textures, randomised per layout seed (linear RGB float32 images, no files).

Patterns (one drawn per seed): ``wood`` (concentric growth rings distorted by value noise, along the table's
x axis), ``stone`` (multi-octave value noise: laminate / stone / speckled resin), ``checker`` (tiles with grout
lines, 4-15 cm), ``solid`` (one colour with faint noise). Colours are drawn in HSV within :data:`TABLE_RANGES`
(covering pale birch to dark walnut, grey and coloured laminates); every image is converted from sRGB to linear.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

#: Ranges the table texture is drawn from: (low, high) for numbers, choices for names.
TABLE_RANGES: dict[str, object] = {
    "pattern": ("wood", "stone", "checker", "solid"),
    "hue_deg": (0.0, 360.0),  # stone/checker/solid; wood uses wood_hue_deg
    "wood_hue_deg": (18.0, 40.0),  # orange-brown wood tones
    "saturation": (0.0, 0.55),
    "value": (0.25, 0.85),  # sRGB value of the base colour
    "contrast": (0.08, 0.35),  # relative brightness swing of the pattern
    "feature_m": (0.004, 0.15),  # ring spacing / noise cell / tile size (m)
}


@dataclass(frozen=True)
class TableTexture:
    """A drawn texture: ``image_hxwx3`` linear RGB in [0, 1] covering the whole table top, and what was drawn."""

    image_hxwx3: np.ndarray
    pattern: str
    params: dict


def _value_noise(rng: np.random.Generator, h: int, w: int, cells: tuple[int, int]) -> np.ndarray:
    """(h, w) smooth value noise in [0, 1]: a (cy+1, cx+1) random lattice, bicubic-smoothstep interpolated."""
    cy, cx = max(1, cells[0]), max(1, cells[1])
    lat = rng.random((cy + 1, cx + 1))
    y = np.linspace(0, cy, h, endpoint=False)
    x = np.linspace(0, cx, w, endpoint=False)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    a = lat[y0][:, x0]
    b = lat[y0][:, x0 + 1]
    c = lat[y0 + 1][:, x0]
    d = lat[y0 + 1][:, x0 + 1]
    top = a + (b - a) * fx[None]
    bot = c + (d - c) * fx[None]
    return top + (bot - top) * fy[:, None]


def _fbm(rng: np.random.Generator, h: int, w: int, cells: tuple[int, int], octaves: int = 4) -> np.ndarray:
    out, amp, tot = np.zeros((h, w)), 1.0, 0.0
    for o in range(octaves):
        out += amp * _value_noise(rng, h, w, (cells[0] * 2**o, cells[1] * 2**o))
        tot += amp
        amp *= 0.5
    return out / tot


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def table_texture(seed: int, size_m: tuple[float, float], px_per_m: float = 600.0, max_px: int = 1024
                  ) -> TableTexture:
    """Draw the table-top texture of layout ``seed`` for a top of ``size_m`` (x, y) metres.

    The image's rows run along the table's y axis and columns along x (``image[v, u]`` with u = x); its
    resolution is ``px_per_m`` capped at ``max_px`` on the longer side.
    """
    rng = np.random.default_rng([int(seed), 0x7AB1E])
    sx, sy = float(size_m[0]), float(size_m[1])
    scale = min(px_per_m, max_px / max(sx, sy))
    w, h = max(8, int(round(sx * scale))), max(8, int(round(sy * scale)))
    R = TABLE_RANGES
    pattern = str(rng.choice(R["pattern"]))
    hue_rng = R["wood_hue_deg"] if pattern == "wood" else R["hue_deg"]
    hue = rng.uniform(*hue_rng) / 360.0
    sat = rng.uniform(*R["saturation"]) if pattern != "wood" else rng.uniform(0.3, 0.6)
    val = rng.uniform(*R["value"])
    contrast = rng.uniform(*R["contrast"])
    feat = float(np.exp(rng.uniform(np.log(R["feature_m"][0]), np.log(R["feature_m"][1]))))
    cells = (max(1, int(round(sy / max(feat, 1e-3) / 4))), max(1, int(round(sx / max(feat, 1e-3) / 4))))
    if pattern == "wood":
        ring_m = float(np.clip(feat, 0.004, 0.03))
        yy = np.repeat(np.linspace(0.0, sy, h)[:, None], w, axis=1)
        warp = _fbm(rng, h, w, (max(2, int(sy / 0.2)), max(2, int(sx / 0.6))), 3)
        t = (yy + 0.04 * warp) / ring_m
        field = 0.5 + 0.5 * np.sin(2 * np.pi * t) ** 3 * (0.6 + 0.4 * _fbm(rng, h, w, (8, 4), 2))
        params = {"ring_m": ring_m}
    elif pattern == "stone":
        field = _fbm(rng, h, w, cells, 5)
        params = {"cell_m": feat}
    elif pattern == "checker":
        tile = float(np.clip(feat, 0.04, 0.15))
        u = np.linspace(0.0, sx, w)[None] / tile
        v = np.linspace(0.0, sy, h)[:, None] / tile
        field = ((np.floor(u) + np.floor(v)) % 2).astype(np.float64)
        grout = (np.minimum(u % 1, 1 - u % 1) < 0.03) | (np.minimum(v % 1, 1 - v % 1) < 0.03)
        field = np.where(grout, -0.5, field)
        params = {"tile_m": tile}
    else:
        field = 0.5 + 0.2 * (_fbm(rng, h, w, cells, 3) - 0.5)
        params = {"cell_m": feat}
    base = np.array(colorsys.hsv_to_rgb(hue, sat, val))
    bright = 1.0 + contrast * (2.0 * field - 1.0)
    srgb = np.clip(base[None, None, :] * bright[..., None], 0.0, 1.0)
    img = srgb_to_linear(srgb).astype(np.float32)
    params.update({"hue_deg": hue * 360.0, "saturation": sat, "value": val, "contrast": contrast})
    return TableTexture(img, pattern, params)
