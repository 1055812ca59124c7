"""The compiled band march gives the mesh of :func:`marching_tets` on the whole grid: same vertices in the same
order, same faces, same gradients; hand-built single-tet cases and the empty cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torm.reconstruction.band_march import BandMarchWork, band_march, interpolate_surface, surface_points
from torm.reconstruction.crossing_band import build_band, build_band_reference
from torm.reconstruction.marching_tets import NUM_TRI_16, marching_tets
from torm.reconstruction.tetgrid import build_tet_grid

BOUNDS = [[-0.1, -0.08, 0.0], [0.1, 0.08, 0.12]]


def _band_inputs(grid, s_v: torch.Tensor, rings: int):
    band = build_band(grid.tets_tx4, s_v, grid.grid_shape, rings)
    local = torch.full((grid.n_verts,), -1, dtype=torch.int64)
    local[band.vert_ids_n] = torch.arange(band.n_verts)
    return band, local[band.tets_bx4].numpy(), grid.tet_edges_tx6[band.tet_ids_b].numpy()


@pytest.mark.parametrize(("seed", "rings"), [(0, 0), (1, 1), (2, 2)])
def test_band_march_equals_full_marching_tets(seed, rings):
    grid = build_tet_grid(BOUNDS, 9, use_cache=False)
    g = torch.Generator().manual_seed(seed)
    v = grid.verts_vx3.double()
    # two blobs plus noise: several components, every tet case, vertices exactly at zero excluded by chance
    s = torch.minimum((v - torch.tensor([-0.04, 0.0, 0.05])).norm(dim=1) - 0.035,
                      (v - torch.tensor([0.05, 0.01, 0.06])).norm(dim=1) - 0.03)
    s = (s + 0.004 * torch.randn(len(s), generator=g, dtype=torch.float64)).float()
    verts = (grid.verts_vx3 + 0.002 * torch.randn(grid.n_verts, 3, generator=g)).float()
    band, tets_l, edges_b = _band_inputs(grid, s, rings)
    bm = band_march(s[band.vert_ids_n], tets_l, edges_b, len(grid.edges_ex2))
    vc = band.vert_ids_n[torch.from_numpy(bm.vert_ids_c)]

    s_full = s.clone().requires_grad_(True)
    v_full = verts.clone().requires_grad_(True)
    mv_ref, mf_ref = marching_tets(v_full, grid.tets_tx4, s_full)
    s_c = s[vc].clone().requires_grad_(True)
    v_c = verts[vc].clone().requires_grad_(True)
    mv = interpolate_surface(v_c, s_c, bm.edge_a_m, bm.edge_b_m)

    assert len(mf_ref) > 50
    assert torch.equal(torch.from_numpy(bm.faces_fx3), mf_ref)
    assert torch.equal(mv, mv_ref)
    # every crossing tet's vertex, and nothing else
    n_in = (s < 0)[grid.tets_tx4].sum(-1)
    want = torch.unique(grid.tets_tx4[(n_in > 0) & (n_in < 4)].reshape(-1))
    assert torch.equal(vc, want)
    assert (bm.edge_a_m < bm.edge_b_m).all()

    w = torch.randn(mv.shape, generator=g)
    (mv_ref * w).sum().backward()
    (mv * w).sum().backward()
    torch.testing.assert_close(s_c.grad, s_full.grad[vc], rtol=0, atol=0)
    torch.testing.assert_close(v_c.grad, v_full.grad[vc], rtol=0, atol=0)
    assert float(s_full.grad.abs().sum()) == pytest.approx(float(s_c.grad.abs().sum()), rel=1e-6)
    # the compiled version: the same points and gradients up to rounding, also with the SDF in another unit
    s_k = s[vc].clone().requires_grad_(True)
    v_k = verts[vc].clone().requires_grad_(True)
    mv_k = surface_points(v_k, s_k * 0.01, bm.edge_a_m, bm.edge_b_m)
    torch.testing.assert_close(mv_k, mv.detach(), rtol=1e-5, atol=1e-7)
    (mv_k * w).sum().backward()
    torch.testing.assert_close(v_k.grad, v_c.grad, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s_k.grad, s_c.grad, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("case", range(16))
def test_band_march_single_tet_every_case(case):
    tets = np.array([[0, 1, 2, 3]], dtype=np.int64)
    edges = np.arange(6, dtype=np.int64)[None]  # one tet: edge ids in TET_EDGES_6x2 order are 0..5
    s = np.array([-1.0 if (case >> k) & 1 else 1.0 for k in range(4)], dtype=np.float32)
    bm = band_march(s, tets, edges, 6)
    ref_v, ref_f = marching_tets(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), torch.from_numpy(tets),
                                 torch.from_numpy(s))
    assert len(bm.faces_fx3) == NUM_TRI_16[case] == len(ref_f)
    assert np.array_equal(bm.faces_fx3, ref_f.numpy())
    crossing = 0 < case < 15
    assert len(bm.vert_ids_c) == (4 if crossing else 0)
    assert len(bm.edge_a_m) == len(ref_v)


def test_band_march_empty_and_bad_input():
    tets = np.array([[0, 1, 2, 3]], dtype=np.int64)
    edges = np.arange(6, dtype=np.int64)[None]
    for s in (np.ones(4, np.float32), -np.ones(4, np.float32)):
        bm = band_march(s, tets, edges, 6)
        assert bm.faces_fx3.shape == (0, 3) and len(bm.vert_ids_c) == 0 and len(bm.edge_a_m) == 0
        mv = interpolate_surface(torch.zeros((0, 3)), torch.zeros(0), bm.edge_a_m, bm.edge_b_m)
        assert mv.shape == (0, 3)
    bm = band_march(np.ones(0, np.float32), np.zeros((0, 4), np.int64), np.zeros((0, 6), np.int64), 6)
    assert bm.faces_fx3.shape == (0, 3)
    with pytest.raises(ValueError, match="edges"):
        band_march(np.ones(4, np.float32), tets, np.zeros((1, 5), np.int64), 6)
    with pytest.raises(ValueError, match=r"\(Nb,\)"):
        band_march(np.ones((4, 1), np.float32), tets, edges, 6)


def test_band_march_reused_work_gives_the_fresh_result():
    """One :class:`BandMarchWork` across calls on different fields (and band sizes) changes nothing; a work object
    of another grid is refused."""
    grid = build_tet_grid(BOUNDS, 9, use_cache=False)
    n_edges = len(grid.edges_ex2)
    work = BandMarchWork(n_edges)
    v = grid.verts_vx3.float()
    g = torch.Generator().manual_seed(3)
    for radius, rings in ((0.03, 1), (0.06, 2), (0.02, 0), (0.03, 1)):
        s = (v - torch.tensor([0.0, 0.0, 0.06])).norm(dim=1) - radius + 0.003 * torch.randn(len(v), generator=g)
        band, tets_l, edges_b = _band_inputs(grid, s, rings)
        fresh = band_march(s[band.vert_ids_n], tets_l, edges_b, n_edges)
        again = band_march(s[band.vert_ids_n], tets_l, edges_b, n_edges, work)
        assert len(fresh.faces_fx3) > 0
        for a, b in zip(fresh, again, strict=True):
            assert np.array_equal(a, b)
        assert (work.slot == -1).all()
    with pytest.raises(ValueError, match="BandMarchWork"):
        band_march(s[band.vert_ids_n], tets_l, edges_b, n_edges + 1, work)


@pytest.mark.parametrize("rings", [0, 1, 2, 8])
def test_compiled_band_equals_the_torch_reference(rings):
    """:func:`build_band` (compiled) gives every field of :func:`build_band_reference`, on a lattice with unequal
    axes (so an axis mix-up in the dilation shows), and the empty band."""
    grid = build_tet_grid([[-0.1, -0.05, 0.0], [0.1, 0.08, 0.06]], 11, use_cache=False)
    assert len(set(grid.grid_shape)) == 3
    g = torch.Generator().manual_seed(rings)
    v = grid.verts_vx3.float()
    s = torch.minimum((v - torch.tensor([-0.04, 0.0, 0.03])).norm(dim=1) - 0.025,
                      (v - torch.tensor([0.05, 0.02, 0.02])).norm(dim=1) - 0.02)
    s = s + 0.004 * torch.randn(len(s), generator=g)
    for field in (s, torch.ones_like(s)):
        fast = build_band(grid.tets_tx4, field, grid.grid_shape, rings)
        ref = build_band_reference(grid.tets_tx4, field, grid.grid_shape, rings)
        for name in ("tet_ids_b", "tets_bx4", "vert_ids_n", "boundary_n", "inside_n", "in_band_v", "inside_v"):
            a, b = getattr(fast, name), getattr(ref, name)
            assert a.dtype == b.dtype and torch.equal(a, b), name
        assert fast.rings == ref.rings == rings
    assert build_band(grid.tets_tx4, s, grid.grid_shape, rings).n_tets > 0
    with pytest.raises(ValueError, match="rings"):
        build_band(grid.tets_tx4, s, grid.grid_shape, -1)
    with pytest.raises(ValueError, match="lattice"):
        build_band(grid.tets_tx4, s[:-1], grid.grid_shape, 1)
