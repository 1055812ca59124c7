"""Randomised lab lighting for the physically based renderer: an environment map plus rectangular area lights.

Everything is drawn from the layout seed within :data:`LIGHTING_RANGES` (relative radiance units; the camera's
auto exposure removes the absolute scale):

- **Environment** (a 128 x 64 lat-long map, z up): ceiling radiance ``env_radiance``; walls near the horizon
  ``wall_factor`` of it with value-noise structure (what glass reflects); floor ``floor_factor`` of it;
  1-4 bright rectangles (windows, ceiling fixtures) ``patch_gain`` times the ceiling, 10-40 deg wide, 8-30 deg
  tall, 5-70 deg above the horizon; the whole map rotated about z uniformly.
- **Area lights** (1-2 one-sided rectangles facing the workspace centre, like ceiling LED panels): side
  0.3-1.2 m, 1.0-2.2 m above the table, their centre within 1.2 m (horizontal) of the workspace centre; the
  radiance is set so that the panel's irradiance at the workspace centre is ``area_share`` times the
  environment's (0.3-3: from fill-dominated to key-dominated lighting, giving soft to crisp shadows).
- **Colour temperature** of the environment and of each panel: 3000-6500 K (EN 12464-1's warm, intermediate
  and cool white classes for indoor workplaces), as linear sRGB from Mitchell Charity's blackbody colour
  table (anchors at 3000, 4000, 5000, 6500 K, linearly interpolated), normalised to unit luminance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.render.textures import _fbm, srgb_to_linear

LIGHTING_RANGES: dict[str, tuple[float, float]] = {
    "env_radiance": (0.6, 1.5),
    "wall_factor": (0.25, 0.8),
    "floor_factor": (0.05, 0.3),
    "n_patches": (1, 4),
    "patch_gain": (4.0, 20.0),
    "patch_width_deg": (10.0, 40.0),
    "patch_height_deg": (8.0, 30.0),
    "patch_elevation_deg": (5.0, 70.0),
    "env_rotation_deg": (0.0, 360.0),
    "n_area_lights": (1, 2),
    "area_side_m": (0.3, 1.2),
    "area_height_m": (1.0, 2.2),
    "area_offset_m": (0.0, 1.2),
    "area_share": (0.3, 3.0),
    "colour_temperature_k": (3000.0, 6500.0),
}

# Mitchell Charity's blackbody table (sRGB, gamma-encoded 8-bit) at a few temperatures.
_CCT_K = np.array([3000.0, 4000.0, 5000.0, 6500.0])
_CCT_SRGB = np.array([[255, 180, 107], [255, 209, 163], [255, 228, 206], [255, 249, 253]]) / 255.0
_LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB luminance weights of linear RGB


def colour_temperature_rgb(kelvin: float) -> np.ndarray:
    """(3,) linear sRGB colour of a blackbody at ``kelvin`` (clamped to 3000-6500 K), unit luminance."""
    lin = srgb_to_linear(_CCT_SRGB)
    k = float(np.clip(kelvin, _CCT_K[0], _CCT_K[-1]))
    rgb = np.array([np.interp(k, _CCT_K, lin[:, c]) for c in range(3)])
    return rgb / float(rgb @ _LUMA)


@dataclass(frozen=True, eq=False)
class AreaLight:
    """A one-sided rectangle emitter: centre (3,) m, unit normal (3,) (emitting side), size (2,) m, radiance (3,)."""

    centre: np.ndarray
    normal: np.ndarray
    size: np.ndarray
    radiance: np.ndarray

    def T_world_light(self) -> np.ndarray:
        """(4, 4) pose of the unit rectangle [-1, 1]^2 (z = normal) scaled to ``size`` (Mitsuba ``rectangle``)."""
        n = self.normal / np.linalg.norm(self.normal)
        a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(a, n)
        x /= np.linalg.norm(x)
        y = np.cross(n, x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = x * self.size[0] / 2, y * self.size[1] / 2, n
        T[:3, 3] = self.centre
        return T


@dataclass(frozen=True, eq=False)
class Lighting:
    """Drawn lighting: ``env_hxwx3`` (linear, lat-long, row 0 = zenith, z up, u = azimuth from +x towards +y,
    then rotated by ``env_rotation_deg`` about z), area lights, and the drawn parameters (JSON-ready)."""

    env_hxwx3: np.ndarray
    env_rotation_deg: float
    area_lights: tuple[AreaLight, ...]
    params: dict = field(default_factory=dict)


def _env_irradiance_up(env: np.ndarray) -> float:
    """Luminance irradiance (relative) of the upper hemisphere of a lat-long map on an upward-facing patch."""
    h, w = env.shape[:2]
    theta = (np.arange(h) + 0.5) / h * np.pi  # from zenith
    lum = env @ _LUMA
    weight = np.cos(theta) * np.sin(theta) * (np.pi / h) * (2 * np.pi / w)
    up = theta < np.pi / 2
    return float((lum[up] * weight[up, None]).sum())


def sample_lighting(seed: int, centre: tuple[float, float, float] = (0.55, 0.0, 0.0),
                    env_size: tuple[int, int] = (64, 128)) -> Lighting:
    """Draw the lighting of layout ``seed`` around the workspace ``centre`` (m, world, table top at centre z)."""
    rng = np.random.default_rng([int(seed), 0x11647])
    R = LIGHTING_RANGES
    h, w = env_size
    u = lambda key: float(rng.uniform(*R[key]))  # noqa: E731
    cct_env = u("colour_temperature_k")
    base = u("env_radiance")
    wall, floor = u("wall_factor"), u("floor_factor")
    elev = np.pi / 2 - (np.arange(h) + 0.5) / h * np.pi  # +pi/2 at the top row
    az = (np.arange(w) + 0.5) / w * 2 * np.pi
    # ceiling -> walls: smooth blend over the upper hemisphere, structured by value noise
    blend = np.clip(np.sin(elev), 0.0, 1.0)[:, None] ** 0.7
    noise = 0.6 + 0.8 * _fbm(rng, h, w, (4, 8), 3)
    lum = np.where(elev[:, None] >= 0, base * (wall + (1 - wall) * blend) * noise, base * floor * noise)
    patches = []
    for _ in range(int(rng.integers(R["n_patches"][0], R["n_patches"][1] + 1))):
        pa, pe = rng.uniform(0, 2 * np.pi), np.radians(u("patch_elevation_deg"))
        pw, ph = np.radians(u("patch_width_deg")), np.radians(u("patch_height_deg"))
        gain = u("patch_gain")
        daz = np.abs((az[None, :] - pa + np.pi) % (2 * np.pi) - np.pi)
        inside = (daz < pw / 2) & (np.abs(elev[:, None] - pe) < ph / 2)
        lum = np.where(inside, base * gain, lum)
        patches.append({"azimuth_deg": float(np.degrees(pa)), "elevation_deg": float(np.degrees(pe)),
                        "width_deg": float(np.degrees(pw)), "height_deg": float(np.degrees(ph)), "gain": gain})
    env = (lum[..., None] * colour_temperature_rgb(cct_env)[None, None, :]).astype(np.float32)
    e_env = _env_irradiance_up(env)
    c = np.asarray(centre, dtype=np.float64)
    lights, lp = [], []
    for _ in range(int(rng.integers(R["n_area_lights"][0], R["n_area_lights"][1] + 1))):
        side = np.array([u("area_side_m"), u("area_side_m")])
        r, phi = u("area_offset_m"), rng.uniform(0, 2 * np.pi)
        pos = c + np.array([r * np.cos(phi), r * np.sin(phi), u("area_height_m")])
        to_c = c - pos
        d = float(np.linalg.norm(to_c))
        n = to_c / d
        cos_s = float(abs(n[2]))  # angle between the table normal and the direction to the panel
        share, cct = u("area_share"), u("colour_temperature_k")
        # small-source irradiance at the centre: E = L A cos_l cos_s / d^2, cos_l = 1 (panel faces the centre)
        L = share * e_env * d * d / (side[0] * side[1] * cos_s)
        lights.append(AreaLight(pos, n, side, L * colour_temperature_rgb(cct)))
        lp.append({"centre_m": pos.tolist(), "side_m": side.tolist(), "area_share": share, "cct_k": cct})
    params = {"env_radiance": base, "wall_factor": wall, "floor_factor": floor, "env_cct_k": cct_env,
              "patches": patches, "area_lights": lp}
    rot = u("env_rotation_deg")
    params["env_rotation_deg"] = rot
    return Lighting(env, rot, tuple(lights), params)
