"""Tet grid and marching tetrahedra: orientation, tiling, caching, cases, watertightness, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torm.errors import ReconstructionError
from torm.reconstruction import tetgrid
from torm.reconstruction.marching_tets import (
    NUM_TRI_16,
    marching_tets,
    marching_tets_reference,
    marching_tets_with_info,
)
from torm.reconstruction.tetgrid import build_tet_grid, cells_per_axis

BOX = np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]])


@pytest.fixture(autouse=True)
def _cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path / "cache"))
    tetgrid.clear_tet_grid_cache()
    yield
    tetgrid.clear_tet_grid_cache()


# ---------------------------------------------------------------- tet grid


def test_cells_per_axis_longest_axis_and_explicit():
    assert cells_per_axis(BOX, 32) == (32, 32, 15)
    assert cells_per_axis(np.array([[0, 0, 0], [1, 0.001, 1]]), 10) == (10, 1, 10)
    assert cells_per_axis(BOX, (4, 5, 6)) == (4, 5, 6)
    with pytest.raises(ReconstructionError):
        cells_per_axis(BOX, 0)
    with pytest.raises(ReconstructionError):
        build_tet_grid([[0, 0, 0], [1, -1, 1]], 4)


def test_grid_volumes_positive_and_sum_to_box():
    g = build_tet_grid(BOX, (5, 4, 3))
    vol = g.tet_volumes_t().numpy()
    assert g.n_tets == 6 * 5 * 4 * 3 and g.n_verts == 6 * 5 * 4
    assert vol.min() > 0
    np.testing.assert_allclose(vol.sum(), np.prod(BOX[1] - BOX[0]), rtol=1e-5)
    np.testing.assert_allclose(g.cell_size, (BOX[1] - BOX[0]) / [5, 4, 3])
    lattice = g.verts_vx3.reshape(*g.grid_shape, 3).numpy()
    np.testing.assert_allclose(lattice[2, 3, 1], BOX[0] + [2, 3, 1] * g.cell_size, atol=1e-6)


def test_grid_tiling_is_conforming():
    g = build_tet_grid(BOX, (4, 3, 3))
    t = g.tets_tx4.numpy()
    faces = np.sort(np.concatenate([t[:, [1, 2, 3]], t[:, [0, 2, 3]], t[:, [0, 1, 3]], t[:, [0, 1, 2]]]), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2  # never more than two tets on a face
    # faces used once lie on the box boundary, interior faces are shared by exactly 2 tets
    uf, counts = np.unique(faces, axis=0, return_counts=True)
    lat = g.verts_vx3.numpy()[uf]  # (F, 3, 3)
    on_boundary = np.zeros(len(uf), dtype=bool)
    for ax in range(3):
        for side in (0, 1):
            on_boundary |= np.all(np.abs(lat[:, :, ax] - g.bounds[side, ax]) < 1e-6, axis=1)
    assert np.all(on_boundary[counts == 1]) and not np.any(on_boundary[counts == 2])
    # boundary area = box surface area (each boundary cell face is split into 2 triangles)
    nx, ny, nz = g.res
    assert (counts == 1).sum() == 2 * 2 * (nx * ny + ny * nz + nx * nz)


def test_edges_match_unique_tet_edges():
    g = build_tet_grid(BOX, (3, 4, 2))
    t = g.tets_tx4.numpy()
    e = np.sort(t[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
    ref = np.unique(e, axis=0)
    np.testing.assert_array_equal(g.edges_ex2.numpy(), ref)
    assert g.edges_ex2 is g.edges_ex2  # computed once


def test_cache_memory_disk_and_corrupt_file(tmp_path):
    g1 = build_tet_grid(BOX, 6)
    assert build_tet_grid(BOX, 6) is g1  # in-memory LRU
    files = list((tmp_path / "cache" / "tetgrids").glob("*.npz"))
    assert len(files) == 1
    tetgrid.clear_tet_grid_cache()
    g2 = build_tet_grid(BOX, 6)  # from disk
    assert g2 is not g1
    assert torch.equal(g1.verts_vx3, g2.verts_vx3) and torch.equal(g1.tets_tx4, g2.tets_tx4)
    assert g2.tets_tx4.dtype == torch.int64 and g2.verts_vx3.dtype == torch.float32
    files[0].write_bytes(b"this is not an npz file")
    tetgrid.clear_tet_grid_cache()
    g3 = build_tet_grid(BOX, 6)  # corrupt file: rebuilt, not a crash
    assert torch.equal(g1.tets_tx4, g3.tets_tx4)
    tetgrid.clear_tet_grid_cache()
    assert torch.equal(build_tet_grid(BOX, 6).tets_tx4, g1.tets_tx4)  # the rewritten file loads


# ---------------------------------------------------------------- marching tets: single tet cases

REF_TET = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
ONE_TET = torch.tensor([[0, 1, 2, 3]])


def _sdf_for_case(case: int) -> torch.Tensor:
    vals = [-0.3, -0.7, -0.4, -0.6]
    return torch.tensor([vals[i] if (case >> i) & 1 else -vals[i] * 2 for i in range(4)], dtype=torch.float64)


@pytest.mark.parametrize("case", range(16))
def test_single_tet_every_sign_pattern(case):
    sdf = _sdf_for_case(case)
    r = marching_tets_with_info(REF_TET, ONE_TET, sdf)
    n_in = bin(case).count("1")
    expected_tris = {0: 0, 1: 1, 2: 2, 3: 1, 4: 0}[n_in]
    assert r.faces_fx3.shape == (expected_tris, 3) and NUM_TRI_16[case] == expected_tris
    assert r.verts_mx3.shape == ({0: 0, 1: 3, 2: 4, 3: 3, 4: 0}[n_in], 3)
    if expected_tris == 0:
        return
    # every vertex on a crossing edge at the linearly interpolated zero
    for (a, b), p in zip(r.edges_mx2.tolist(), r.verts_mx3, strict=True):
        sa, sb = sdf[a].item(), sdf[b].item()
        assert (sa < 0) != (sb < 0)
        t = sa / (sa - sb)
        torch.testing.assert_close(p, REF_TET[a] + t * (REF_TET[b] - REF_TET[a]))
    # winding: every triangle's normal points from the inside vertices to the outside ones
    inside = sdf < 0
    out_dir = REF_TET[~inside].mean(0) - REF_TET[inside].mean(0)
    v = r.verts_mx3
    for f in r.faces_fx3:
        n = torch.linalg.cross(v[f[1]] - v[f[0]], v[f[2]] - v[f[0]])
        assert float(n @ out_dir) > 0
        # and each inside vertex is behind the triangle's plane, outside ones in front
        d = (REF_TET - v[f[0]]) @ n
        assert torch.all(d[inside] < 0) and torch.all(d[~inside] > 0)


def test_zero_counts_as_outside():
    sdf = torch.tensor([-1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    v, f = marching_tets(REF_TET, ONE_TET, sdf)
    assert f.shape == (1, 3)
    torch.testing.assert_close(v, REF_TET[1:])  # the crossing points sit on the zero vertices


@pytest.mark.parametrize("value", [1.0, -1.0])
def test_empty_cases(value):
    g = build_tet_grid(BOX, 3)
    v, f = marching_tets(g.verts_vx3, g.tets_tx4, torch.full((g.n_verts,), value))
    assert v.shape == (0, 3) and v.dtype == torch.float32
    assert f.shape == (0, 3) and f.dtype == torch.int64


def test_bad_shapes_raise():
    with pytest.raises(ReconstructionError, match="sdf must be"):
        marching_tets(REF_TET, ONE_TET, torch.zeros(3, dtype=torch.float64))


# ---------------------------------------------------------------- fast vs reference


def _vector_area_per_tet(v: np.ndarray, f: np.ndarray, ft: np.ndarray, n_tets: int) -> np.ndarray:
    out = np.zeros((n_tets, 3))
    np.add.at(out, ft, np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_fast_matches_reference_on_random_grids(seed):
    rng = np.random.default_rng(seed)
    g = build_tet_grid([[0, 0, 0], [1, 1, 1]], (4, 3, 3), use_cache=False)
    verts = g.verts_vx3.double() + torch.from_numpy(rng.uniform(-0.04, 0.04, (g.n_verts, 3)))  # deformed
    vt = verts[g.tets_tx4]
    # the reference orients geometrically, the table topologically: they agree while no tet is inverted
    assert torch.linalg.det(vt[:, 1:] - vt[:, :1]).min() > 0
    sdf = torch.from_numpy(rng.normal(size=g.n_verts))
    sdf[rng.random(g.n_verts) < 0.1] = 0.0  # exact zeros count as outside in both
    fast = marching_tets_with_info(verts, g.tets_tx4, sdf)
    full = marching_tets_with_info(verts, g.tets_tx4, sdf, crossing_only=False)
    rv, rf, rft = marching_tets_reference(verts.numpy(), g.tets_tx4.numpy(), sdf.numpy())
    assert len(rf) == len(fast.faces_fx3) == len(full.faces_fx3) and len(rv) == len(fast.verts_mx3)
    # same surface vertices (the reference numbers them in another order)
    order_f = np.lexsort(fast.verts_mx3.numpy().T)
    order_r = np.lexsort(rv.T)
    np.testing.assert_allclose(fast.verts_mx3.numpy()[order_f], rv[order_r], atol=1e-12)
    # same oriented polygon per tet: the vector area does not depend on the quad's diagonal
    va_fast = _vector_area_per_tet(fast.verts_mx3.numpy(), fast.faces_fx3.numpy(), fast.face_tet_f.numpy(), g.n_tets)
    va_ref = _vector_area_per_tet(rv, rf, rft, g.n_tets)
    np.testing.assert_allclose(va_fast, va_ref, atol=1e-12)
    np.testing.assert_array_equal(np.bincount(fast.face_tet_f.numpy(), minlength=g.n_tets),
                                  np.bincount(rft, minlength=g.n_tets))
    torch.testing.assert_close(fast.verts_mx3, full.verts_mx3)
    # open at the grid boundary but consistently wound
    m = trimesh.Trimesh(fast.verts_mx3.numpy(), fast.faces_fx3.numpy(), process=False)
    assert m.is_winding_consistent


@pytest.mark.parametrize("seed", [0, 1])
def test_edge_table_dedupe_gives_the_sorted_result_on_a_renumbered_subset(seed):
    """marching_tets with the grid's tet-edge ids (flags instead of a sort) on a subset of tets whose vertices
    are renumbered in increasing order (what the narrow band passes) equals the sorting path, bit for bit."""
    rng = np.random.default_rng(seed)
    g = build_tet_grid([[0, 0, 0], [1, 1, 1]], (5, 4, 3), use_cache=False)
    e = g.edges_ex2
    te = g.tets_tx4[:, torch.as_tensor(tetgrid.TET_EDGES_6x2)]
    np.testing.assert_array_equal(e[g.tet_edges_tx6].numpy(), torch.sort(te, dim=-1).values.numpy())
    sdf = torch.from_numpy(rng.normal(size=g.n_verts))
    verts = g.verts_vx3.double() + torch.from_numpy(rng.uniform(-0.02, 0.02, (g.n_verts, 3)))
    whole = marching_tets_with_info(verts, g.tets_tx4, sdf)
    flags = marching_tets_with_info(verts, g.tets_tx4, sdf, tet_edges_tx6=g.tet_edges_tx6, n_edges=len(e))
    assert torch.equal(whole.faces_fx3, flags.faces_fx3) and torch.equal(whole.verts_mx3, flags.verts_mx3)
    sub = torch.from_numpy(np.sort(rng.choice(g.n_tets, g.n_tets // 2, replace=False)))
    used = torch.unique(g.tets_tx4[sub])
    local = torch.full((g.n_verts,), -1, dtype=torch.int64)
    local[used] = torch.arange(len(used))
    a = marching_tets_with_info(verts[used], local[g.tets_tx4[sub]], sdf[used])
    b = marching_tets_with_info(verts[used], local[g.tets_tx4[sub]], sdf[used], tet_edges_tx6=g.tet_edges_tx6[sub],
                                n_edges=len(e))
    assert len(a.faces_fx3) > 10
    assert torch.equal(a.faces_fx3, b.faces_fx3) and torch.equal(a.verts_mx3, b.verts_mx3)
    assert torch.equal(a.edges_mx2, b.edges_mx2) and torch.equal(a.face_tet_f, b.face_tet_f)


def test_gradcheck_tiny_case():
    g = build_tet_grid([[0, 0, 0], [1, 1, 1]], (2, 1, 1), use_cache=False)
    verts = g.verts_vx3.double().clone().requires_grad_(True)
    sdf = torch.tensor([-0.5, 0.4, 0.3, 0.6, -0.7, 0.8, 0.45, -0.35, 0.55, 0.25, 0.65, 0.5],
                       dtype=torch.float64)[: g.n_verts].clone().requires_grad_(True)
    ref_faces = marching_tets(verts, g.tets_tx4, sdf)[1]
    assert len(ref_faces) > 0

    def fn(v, s):
        return marching_tets(v, g.tets_tx4, s)[0]

    assert torch.autograd.gradcheck(fn, (verts, sdf), eps=1e-6, atol=1e-5)


def test_gradients_reach_only_crossing_vertices():
    g = build_tet_grid([[0, 0, 0], [1, 1, 1]], 6, use_cache=False)
    verts = g.verts_vx3.clone().requires_grad_(True)
    sdf = (torch.linalg.norm(g.verts_vx3 - 0.5, dim=1) - 0.3).clone().requires_grad_(True)
    v, f = marching_tets(verts, g.tets_tx4, sdf)
    v.square().sum().backward()
    touched = (sdf.grad != 0)
    e = g.edges_ex2
    crossing = (sdf.detach()[e[:, 0]] < 0) != (sdf.detach()[e[:, 1]] < 0)
    on_crossing = torch.zeros(g.n_verts, dtype=torch.bool)
    on_crossing[e[crossing].reshape(-1)] = True
    assert touched.any() and torch.all(on_crossing[touched])
    assert torch.isfinite(verts.grad).all()


# ---------------------------------------------------------------- closed surfaces


def test_sphere_is_watertight_and_volume_accurate():
    g = build_tet_grid([[-1, -1, -1], [1, 1, 1]], 32, use_cache=False)
    r = 0.6
    sdf = torch.linalg.norm(g.verts_vx3.double(), dim=1) - r
    v, f = marching_tets(g.verts_vx3.double(), g.tets_tx4, sdf)
    m = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward winding
    true = 4 / 3 * np.pi * r**3
    assert abs(m.volume - true) / true < 0.02
    np.testing.assert_allclose(np.linalg.norm(v.numpy(), axis=1), r, atol=0.01)  # near the sphere


def test_three_spheres_in_workspace_watertight():
    g = build_tet_grid(BOX, 32, use_cache=False)
    centres = torch.tensor([[0.45, 0.0, 0.05], [0.55, 0.05, 0.04], [0.65, -0.05, 0.06]])
    sdf = torch.cdist(g.verts_vx3, centres).min(1).values - 0.035
    v, f = marching_tets(g.verts_vx3, g.tets_tx4, sdf)
    m = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert len(m.split(only_watertight=False)) == 3
