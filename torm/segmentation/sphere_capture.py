"""A synthetic multi-view capture of spheres on a table, with exact instance masks (no renderer).

Used by tests and quick experiments of the segmentation stage: the masks are exact ray-sphere
intersections, so corrupted masks can be compared with known ground truth and the multi-view
consistency checks see geometrically consistent silhouettes.
"""

from __future__ import annotations

import numpy as np

from torm.geometry import look_at_cv
from torm.types import CameraView, Capture

#: Default scene like RECONSTRUCTION.md's prototype: three objects ~3 cm in radius, 8 cm apart (m).
DEFAULT_SPHERES = ((0.47, 0.0, 0.03, 0.03), (0.55, 0.0, 0.035, 0.035), (0.63, 0.0, 0.025, 0.025))


def hemisphere_eyes(n_views: int, radius: float, center: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) camera positions (m) on the upper hemisphere (elevation 20-75 deg) around ``center``."""
    az = rng.uniform(0.0, 2 * np.pi, n_views)
    el = np.deg2rad(rng.uniform(20.0, 75.0, n_views))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return center + radius * d


def sphere_capture(
    n_views: int = 20,
    size_px: int = 256,
    fov_deg: float = 60.0,
    radius: float = 0.5,
    spheres: tuple[tuple[float, float, float, float], ...] = DEFAULT_SPHERES,
    seed: int = 0,
    with_rgb: bool = False,
) -> Capture:
    """A square-image capture of spheres (x, y, z, r in m) seen from a hemisphere of ``radius`` m.

    Object k (1-based, in ``spheres`` order) has mask value k; nearer spheres occlude farther ones.
    With ``with_rgb`` each view also gets a grey uint8 image with brighter sphere pixels.
    """
    rng = np.random.default_rng(seed)
    center = np.array([0.55, 0.0, 0.0])
    f = (size_px / 2) / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[f, 0, size_px / 2], [0, f, size_px / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(size_px) + 0.5, np.arange(size_px) + 0.5)
    rays_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], axis=-1)
    rays_cam /= np.linalg.norm(rays_cam, axis=-1, keepdims=True)
    sph = np.asarray(spheres, dtype=np.float64)
    views = []
    for i, eye in enumerate(hemisphere_eyes(n_views, radius, center, rng)):
        T = look_at_cv(eye, center)
        d = rays_cam @ T[:3, :3].T
        best_t = np.full(u.shape, np.inf)
        mask = np.zeros(u.shape, np.int32)
        for k, (x, y, z, r) in enumerate(sph, start=1):
            oc = eye - np.array([x, y, z])
            b = d @ oc
            disc = b * b - (oc @ oc - r * r)
            t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
            hit = (t > 0) & (t < best_t)
            mask[hit] = k
            best_t[hit] = t[hit]
        rgb = None
        if with_rgb:
            rgb = np.full((size_px, size_px, 3), 90, np.uint8)
            rgb[mask > 0] = 200
        views.append(CameraView(K=K, T_world_cam=T, rgb=rgb, mask=mask, name=f"view_{i:03d}"))
    return Capture(
        views=tuple(views), scenario="synthetic_spheres", seed=seed,
        object_ids=tuple(range(1, len(sph) + 1)), object_names=tuple(f"sphere{k}" for k in range(1, len(sph) + 1)),
        table_height=0.0, workspace_bounds=np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]]),
        metadata={"mask_source": "synthetic spheres (ground truth)"},
    )
