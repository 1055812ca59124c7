"""Projective visual hull: a sphere seen by synthetic cameras, vote tolerance, table and image-border rules."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torm.errors import ReconstructionError
from torm.geometry import look_at_cv
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.tetgrid import build_tet_grid
from torm.reconstruction.visual_hull import signed_distance_px, visual_hull_sdf, visual_hull_sdf_from_capture
from torm.types import CameraView, Capture

W, H = 320, 180
CENTRE = np.array([0.55, 0.0, 0.08])
RADIUS = 0.06
BOX = np.array([[0.45, -0.10, -0.005], [0.65, 0.10, 0.20]])


def _cameras(n: int, fovx_deg: float = 91.5) -> tuple[np.ndarray, np.ndarray]:
    """n cameras on the upper hemisphere (r = 0.5 m) around the workspace centre, looking at it."""
    fx = (W / 2) / np.tan(np.radians(fovx_deg) / 2)
    K = np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]])
    centre = np.array([0.55, 0.0, 0.0])
    golden = np.pi * (3 - np.sqrt(5))
    Ts = []
    for i in range(n):
        z = 0.2 + 0.75 * (i + 0.5) / n
        r = np.sqrt(1 - z * z)
        eye = centre + 0.5 * np.array([r * np.cos(golden * i), r * np.sin(golden * i), z])
        Ts.append(look_at_cv(eye, centre + [0, 0, 0.05]))
    return np.repeat(K[None], n, 0), np.stack(Ts)


def _sphere_masks(Ks: np.ndarray, Ts: np.ndarray, centre=CENTRE, radius=RADIUS) -> np.ndarray:
    """Exact silhouettes: pixel centre rays that hit the sphere."""
    uu, vv = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    out = []
    for K, T in zip(Ks, Ts, strict=True):
        d = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1) @ T[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        oc = centre - T[:3, 3]
        t = d @ oc
        out.append((oc @ oc - t**2 < radius**2) & (t > 0))
    return np.stack(out)


@pytest.fixture(scope="module")
def scene():
    Ks, Ts = _cameras(24)
    return Ks, Ts, _sphere_masks(Ks, Ts)


@pytest.fixture(scope="module")
def grid():
    return build_tet_grid(BOX, 40, use_cache=False)


def _mesh(grid, sdf) -> trimesh.Trimesh:
    v, f = marching_tets(grid.verts_vx3, grid.tets_tx4, sdf)
    return trimesh.Trimesh(v.numpy().astype(np.float64), f.numpy(), process=False)


def test_signed_distance_transform_boundary_and_extremes():
    sil = np.zeros((9, 9), bool)
    sil[3:6, 3:6] = True
    sd = signed_distance_px(sil, precise=True)
    assert sd[4, 4] == pytest.approx(-1.5)  # 2 px to the nearest outside pixel, boundary half-way
    assert sd[3, 4] == pytest.approx(-0.5) and sd[2, 4] == pytest.approx(0.5) and sd[0, 4] == pytest.approx(2.5)
    assert np.all((sd < 0) == sil)
    assert np.all(signed_distance_px(np.zeros((4, 5), bool)) > 0)
    assert np.all(signed_distance_px(np.ones((4, 5), bool)) < 0)


def test_sphere_hull_contains_sphere_and_matches_volume(scene, grid):
    Ks, Ts, masks = scene
    sdf = visual_hull_sdf(masks, Ks, Ts, grid, table_z=0.0, vote_tol=0.0)
    assert sdf.dtype == torch.float32 and sdf.shape == (grid.n_verts,)
    d = np.linalg.norm(grid.verts_vx3.numpy() - CENTRE, axis=1)
    cell = grid.cell_size.max()
    assert np.all(sdf.numpy()[d < RADIUS - cell] < 0)  # the hull contains the sphere
    assert np.all(sdf.numpy()[d > RADIUS * 1.25] > 0)  # and is tight around it
    # metric scale: near the surface the value approximates the distance to the sphere
    near = np.abs(d - RADIUS) < 0.01
    np.testing.assert_allclose(sdf.numpy()[near], (d - RADIUS)[near], atol=0.004)
    m = _mesh(grid, sdf)
    assert m.is_watertight and m.is_winding_consistent
    true = 4 / 3 * np.pi * RADIUS**3
    assert 0.95 < m.volume / true < 1.06  # a hull is a superset; 24 views make it tight


def test_vote_tolerance_survives_a_blank_mask(scene, grid):
    Ks, Ts, masks = scene
    bad = masks.copy()
    bad[5] = False  # one view's segmenter missed the object
    strict = visual_hull_sdf(bad, Ks, Ts, grid, vote_tol=0.0)
    assert torch.all(strict >= 0)  # carved away entirely
    assert _mesh(grid, strict).faces.shape[0] == 0
    tolerant = visual_hull_sdf(bad, Ks, Ts, grid, vote_tol=0.15)
    m = _mesh(grid, tolerant)
    true = 4 / 3 * np.pi * RADIUS**3
    assert m.is_watertight and 0.95 < m.volume / true < 1.15


def test_table_and_box_clip(scene, grid):
    Ks, Ts, _ = scene
    low = np.array([0.55, 0.0, 0.02])  # sphere sunk into the table
    masks = _sphere_masks(Ks, Ts, centre=low)
    sdf = visual_hull_sdf(masks, Ks, Ts, grid, table_z=0.0, vote_tol=0.0).numpy()
    z = grid.verts_vx3.numpy()[:, 2]
    assert np.all(sdf[z < 0] > 0) and np.any(sdf[z > 0.005] < 0)
    m = _mesh(grid, torch.from_numpy(sdf))
    assert m.is_watertight and m.bounds[0, 2] >= -1e-6  # flat bottom on the table plane
    # the grid boundary is strictly outside (by half a cell), so the surface stays closed there
    on_boundary = np.any(np.isclose(grid.verts_vx3.numpy(), grid.bounds[0], atol=1e-7)
                         | np.isclose(grid.verts_vx3.numpy(), grid.bounds[1], atol=1e-7), axis=1)
    assert np.all(sdf[on_boundary] >= 0.5 * grid.cell_size.min() - 1e-7)


def test_outside_image_unknown_vs_outside(scene, grid):
    Ks, Ts, masks = scene
    # zoomed-in extra view that sees only part of the box: an "outside" rule would carve the rest
    K_zoom = Ks[:1].copy()
    K_zoom[0, 0, 0] = K_zoom[0, 1, 1] = 1200.0
    T_zoom = look_at_cv(np.array([0.55, -0.5, 0.3]), CENTRE + [0, 0, 0.03])[None]
    Ks2, Ts2 = np.concatenate([Ks, K_zoom]), np.concatenate([Ts, T_zoom])
    masks2 = np.concatenate([masks, _sphere_masks(K_zoom, T_zoom)])
    base = visual_hull_sdf(masks, Ks, Ts, grid, vote_tol=0.0)
    unknown = visual_hull_sdf(masks2, Ks2, Ts2, grid, vote_tol=0.0)
    outside = visual_hull_sdf(masks2, Ks2, Ts2, grid, vote_tol=0.0, outside_image="outside")
    assert (unknown < 0).sum() > 0.9 * (base < 0).sum()  # the partial view does not destroy the object
    assert (outside < 0).sum() < 0.7 * (base < 0).sum()  # the classic rule carves what the view misses


def test_from_capture_and_bad_input(scene, grid):
    Ks, Ts, masks = scene
    views = tuple(CameraView(K=K, T_world_cam=T, mask=m.astype(np.int32) * 2) for K, T, m in
                  zip(Ks[:6], Ts[:6], masks[:6], strict=True))
    cap = Capture(views=views, table_height=0.0)
    a = visual_hull_sdf_from_capture(cap, grid, vote_tol=0.0)
    b = visual_hull_sdf(masks[:6], Ks[:6], Ts[:6], grid, vote_tol=0.0)
    torch.testing.assert_close(a, b)
    with pytest.raises(ReconstructionError, match="vote_tol"):
        visual_hull_sdf(masks, Ks, Ts, grid, vote_tol=1.0)
    with pytest.raises(ReconstructionError, match="Ks"):
        visual_hull_sdf(masks, Ks[:3], Ts, grid)
    with pytest.raises(ReconstructionError, match="outside_image"):
        visual_hull_sdf(masks, Ks, Ts, grid, outside_image="maybe")
