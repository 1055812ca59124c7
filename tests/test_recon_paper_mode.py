"""Paper mode (DMTet-Multi) as the paper runs it: no silent rescue, the narrow band against the full evaluation,
eq. (3) and eq. (4) against hand-computed values."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_recon_dmtet import BOUNDS, _capture  # tests/ is on sys.path under pytest

from torm.errors import ConfigError, ReconstructionError
from torm.reconstruction import losses
from torm.reconstruction.api import ReconstructionConfig, reconstruct
from torm.reconstruction.crossing_band import build_band
from torm.reconstruction.dmtet import DMTetConfig, _Clock, _Field, _Surface, downsample_masks, optimise_dmtet
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.raster import face_adjacency, render_silhouettes
from torm.reconstruction.tetgrid import build_tet_grid


@pytest.fixture(autouse=True)
def _one_thread(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setenv("TORM_THREADS", "1")
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def scene():
    cap = _capture(n_views=8, hw=48)
    masks, K = downsample_masks(cap.masks() > 0, cap.Ks(), 48)
    return cap, masks, K, np.linalg.inv(cap.poses())


def _two_spheres_cells(grid) -> torch.Tensor:
    v = grid.verts_vx3.double()
    cell = float(np.mean(grid.cell_size))
    d1 = (v - torch.tensor([0.46, -0.09, 0.05])).norm(dim=1) - 0.07
    d2 = (v - torch.tensor([0.64, 0.08, 0.05])).norm(dim=1) - 0.07
    return (torch.minimum(d1, d2) / cell).float().clamp(-3.0, 3.0)


# ----------------------------------------------------------------------------------------------------------
# Rescue off: an empty mesh is reported as empty
# ----------------------------------------------------------------------------------------------------------
def test_without_rescue_an_empty_mesh_is_reported_empty(scene):
    cap, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 12)
    outside = np.full(grid.n_verts, 0.05)  # every vertex outside: no surface at step 0
    cfg = DMTetConfig(param="vertex", start="hull", loss="init", iterations=10, eval_every=0)
    res = optimise_dmtet(grid, K, T, masks, cfg, init_sdf_v=outside, table_z=0.0)
    h = res.history
    assert res.mesh.is_empty and h["collapsed_at"] == [0.0] and h["iou_all"][-1] == 0.0
    assert h["empty_steps"] == [1.0] and h["rescued_steps"] == [0.0] and len(h["loss"]) == 1
    assert res.timings["steps_run"] == 1.0
    rescued = optimise_dmtet(grid, K, T, masks, replace(cfg, rescue=True), init_sdf_v=outside, table_z=0.0)
    assert rescued.history["rescued_steps"][0] >= 1 and rescued.history["collapsed_at"] == [-1.0]
    assert len(rescued.history["loss"]) == 10 and not rescued.mesh.is_empty


def test_paper_mode_reconstruct_raises_on_a_vanished_mesh():
    cap = _capture(n_views=6, hw=40)
    dm = DMTetConfig(param="vertex", iterations=5, sphere_scale=0.01, eval_every=0)  # dome smaller than a cell
    with pytest.raises(ReconstructionError, match="empty"):
        reconstruct(cap, ReconstructionConfig(mode="paper", grid_res=12, mask_res=40, dmtet=dm))


def test_rescue_changes_nothing_when_the_mesh_never_vanishes(scene):
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 12)
    cfg = DMTetConfig(param="vertex", iterations=8, views_per_batch=2, eval_every=0)
    a = optimise_dmtet(grid, K, T, masks, cfg, table_z=0.0)
    b = optimise_dmtet(grid, K, T, masks, replace(cfg, rescue=True), table_z=0.0)
    assert a.history["empty_steps"] == [0.0] and a.history["loss"] == b.history["loss"]
    assert np.array_equal(a.mesh.faces_fx3, b.mesh.faces_fx3)


def test_threads_apply_during_the_run_and_the_callers_setting_comes_back(scene):
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 12)
    cfg = DMTetConfig(param="vertex", iterations=3, views_per_batch=2, eval_every=0, threads=2)
    torch.set_num_threads(1)
    res = optimise_dmtet(grid, K, T, masks, cfg, table_z=0.0)
    assert res.timings["torch_threads"] == 2.0 and torch.get_num_threads() == 1
    keep = optimise_dmtet(grid, K, T, masks, replace(cfg, threads=0), table_z=0.0)
    assert keep.timings["torch_threads"] == 1.0 and torch.get_num_threads() == 1
    # the thread count does not change the result beyond float reduction order
    assert np.allclose(res.history["loss"], keep.history["loss"], rtol=1e-4, atol=1e-6)
    with pytest.raises(ConfigError, match="threads"):
        DMTetConfig(threads=-1)


# ----------------------------------------------------------------------------------------------------------
# Narrow band: the fast path against the full (reference) evaluation
# ----------------------------------------------------------------------------------------------------------
def test_band_structure_on_a_plane():
    grid = build_tet_grid([[0, 0, 0], [1, 1, 1]], 8)
    x = grid.verts_vx3[:, 0].double()
    s = (x - 0.41) * 8  # a plane between lattice columns i = 3 and 4, SDF in cells
    band = build_band(grid.tets_tx4, s, grid.grid_shape, 1)
    tets = grid.tets_tx4
    n_in = (s < 0)[tets].sum(1)
    crossing = torch.nonzero((n_in > 0) & (n_in < 4), as_tuple=True)[0]
    assert set(crossing.tolist()) <= set(band.tet_ids_b.tolist())  # every crossing tet is a band tet
    assert bool(band.in_band_v[band.tets_bx4.reshape(-1)].all())  # every vertex of a band tet is in the band
    # by hand: crossing tets span columns 3-4, dilated by one ring -> core columns 2-5, band tets reach 1-6
    i_col = torch.round(x * 8).long()
    assert set(i_col[band.vert_ids_n].tolist()) == {1, 2, 3, 4, 5, 6}
    out_tets = torch.ones(len(tets), dtype=torch.bool)
    out_tets[band.tet_ids_b] = False
    shared = set(tets[out_tets].reshape(-1).tolist()) & set(band.vert_ids_n.tolist())
    assert set(band.vert_ids_n[band.boundary_n].tolist()) == shared
    assert set(i_col[band.vert_ids_n[band.boundary_n]].tolist()) == {1, 6}
    assert not band.boundary_flipped(s[band.vert_ids_n])
    s2 = s.clone()
    s2[band.vert_ids_n[band.boundary_n][0]] *= -1  # a boundary vertex changes sign
    assert band.boundary_flipped(s2[band.vert_ids_n])
    far = torch.nonzero(~band.in_band_v, as_tuple=True)[0][:3]
    s2[far] *= -1
    assert band.misses(s2) == 3
    everything = build_band(tets, s, grid.grid_shape, 8)
    assert everything.n_tets == grid.n_tets and not bool(everything.boundary_n.any())
    assert build_band(tets, torch.ones_like(s), grid.grid_shape, 2).n_verts == 0  # no surface, no band


@pytest.mark.parametrize("bf16", ["on", "off"])
def test_band_gives_the_full_mesh_and_the_same_gradients(scene, bf16):
    """The band (in float32, or with its rows away from the surface in bfloat16) gives the full evaluation's mesh."""
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 20)
    cfg = DMTetConfig(param="mlp", mlp_hidden=64, mlp_fit_iters=300, mlp_fit_lr=3e-3, band_rings=1, bf16=bf16)
    fixed = torch.zeros(grid.n_verts, dtype=torch.bool)
    fld = _Field(grid, _two_spheres_cells(grid), fixed, cfg, torch.Generator().manual_seed(0))

    def loss_and_grads(mv, mf, s, verts, surf=None):
        pred = render_silhouettes(mv, mf, K[:2], T[:2], 48, 48, adjacency_fx3=face_adjacency(mf.numpy(), len(mv)))
        loss = losses.envelope_mask_loss(pred, torch.from_numpy(masks[:2]), 2.0).sum()
        loss = loss + 0.1 * fld.eikonal(s, verts, mv, torch.Generator().manual_seed(1))
        for p in fld.params:
            p.grad = None
        loss.backward()
        if surf is not None:
            surf.backward_field()  # the banded path's second stage: crossing-tet vertices -> MLP weights
        return float(loss.detach()), [p.grad.clone() for p in fld.params]

    s, verts = fld.evaluate()
    mv_ref, mf_ref = marching_tets(verts, grid.tets_tx4, s * fld.cell)
    assert len(mf_ref) > 100  # the fit holds the two spheres
    l_ref, g_ref = loss_and_grads(mv_ref, mf_ref, s, verts)
    surf = _Surface(fld, grid, cfg, _Clock())
    s_b, verts_b, mv_b, mf_b = surf.extract(0)
    assert surf.band.n_verts < 0.5 * grid.n_verts  # the band really is narrow here
    assert torch.equal(mf_b, mf_ref)
    assert torch.allclose(mv_b, mv_ref, atol=1e-6)
    if bf16 == "on":  # the first step has no crossing set yet: every row went through bfloat16 first
        assert surf.stats["bf16_rows"] == surf.band.n_verts and surf.stats["bf16_late_rows"] > 0
        assert surf.stats["bf16_err_max"] < 0.5 * cfg.bf16_sign_margin  # measured on the rows seen both ways
        s_b2, _, mv_b2, mf_b2 = surf.extract(1)  # the next step starts from the crossing set in float32
        assert torch.equal(mf_b2, mf_ref) and torch.equal(mv_b2, mv_b)
        assert surf.stats["bf16_rows"] < 2 * surf.band.n_verts
        s_b, verts_b, mv_b, mf_b = surf.extract(2)
    l_b, g_b = loss_and_grads(mv_b, mf_b, s_b, verts_b, surf)
    assert 0 < surf.stats["backprop_verts"] < surf.stats["grad_verts"]  # only the silhouettes' vertices
    assert l_b == pytest.approx(l_ref, rel=1e-5)
    # The two paths sum the same per-vertex contributions in different orders and through different kernels
    # (oneDNN picks AVX2, AVX-512 or AMX code paths by CPU), so element-wise agreement to a fixed atol is not a
    # property of the arithmetic (it failed on a Sapphire Rapids / AMX CPU). What is: a float32 sum of n terms is off
    # by about sqrt(n) * u * sum|terms| with high probability (Higham & Mary 2019, "A new approach to probabilistic
    # rounding error analysis"; u = float32 eps), n = the full grid's vertex count. Tested norm-wise, as LAPACK's
    # tests do, against a threshold of 30 (room for sum|terms| > |sum| where contributions cancel): 2.4e-4 of the
    # largest gradient at n = 4,410. Measured on AVX-512 (AMD EPYC): ratios <= 0.12; a dropped or doubled
    # band vertex moves a weight's gradient by a whole contribution, far above that.
    u = torch.finfo(torch.float32).eps
    n = grid.n_verts
    for a, b in zip(g_b, g_ref, strict=True):
        ratio = float((a - b).abs().max() / (n ** 0.5 * u * b.abs().max()))
        assert ratio < 30, f"banded vs full gradients differ by {ratio:.1f} x sqrt(n) u ||g|| (n = {n})"


@pytest.mark.parametrize(("split_rows", "bf16"), [(2, "off"), (10**9, "off"), (2, "on")])
def test_banded_run_follows_the_reference_run(scene, monkeypatch, split_rows, bf16):
    """The band (with its gradient pass in two halves from ``split_rows`` rows up) follows the full evaluation."""

    import torm.reconstruction.dmtet_surface as surface  # where the gradient pass reads it

    monkeypatch.setattr(surface, "GRAD_SPLIT_ROWS", split_rows)
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 16)
    cfg = DMTetConfig(param="mlp", iterations=12, views_per_batch=2, eval_every=6, mlp_hidden=32, mlp_fit_iters=60,
                      mlp_fit_lr=3e-3, full_pass_every=4, bf16=bf16)
    ref = optimise_dmtet(grid, K, T, masks, replace(cfg, narrow_band=False), table_z=0.0)
    fast = optimise_dmtet(grid, K, T, masks, cfg, table_z=0.0)
    assert fast.history["full_passes"][0] >= 3 and ref.history["full_passes"] == [0.0]
    assert fast.history["band_misses"] == [0.0]
    assert fast.history["n_faces"] == ref.history["n_faces"]
    assert np.allclose(fast.history["loss"], ref.history["loss"], rtol=1e-4)
    assert np.allclose(fast.history["iou_all"], ref.history["iou_all"], atol=1e-6)


def test_side_thread_gives_the_same_run(scene, monkeypatch):
    """The side thread (eq. 4 during the render, half of each gradient-free evaluation, half of the band's gradient
    pass) changes no value: the loss history and the final field are bit-identical to the run without it."""

    import torm.reconstruction.dmtet_surface as surface

    monkeypatch.setattr(surface, "GRAD_SPLIT_ROWS", 2)  # the gradient pass in halves at this small size too
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 20)
    cfg = DMTetConfig(param="mlp", iterations=10, views_per_batch=2, eval_every=5, mlp_hidden=32, mlp_fit_iters=60,
                      mlp_fit_lr=3e-3, full_pass_every=4, eikonal_points=64)
    off = optimise_dmtet(grid, K, T, masks, replace(cfg, side_thread="off"), table_z=0.0)
    on = optimise_dmtet(grid, K, T, masks, replace(cfg, side_thread="on"), table_z=0.0)
    assert on.timings["side_thread"] == 1.0 and off.timings["side_thread"] == 0.0
    assert off.history["n_faces"][-1] > 0 and min(off.history["eikonal"]) > 0
    for key in ("loss", "eikonal", "mask_loss", "n_faces", "iou_all"):
        assert on.history[key] == off.history[key], key
    assert np.array_equal(on.sdf_v, off.sdf_v)
    with pytest.raises(ConfigError, match="side_thread"):
        DMTetConfig(side_thread="yes")


def test_pools_are_forgotten_in_a_forked_child():
    """A forked child must not reuse the parent's pool objects (their threads do not exist there)."""
    import os

    from torm.reconstruction.dmtet import _SIDE, _side_pool

    parent = _side_pool()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: a fresh pool that runs work
        ok = not _SIDE and _side_pool() is not parent and _side_pool().submit(lambda: 7).result(timeout=10) == 7
        os.write(w, b"1" if ok else b"0")
        os._exit(0)
    os.close(w)
    got = os.read(r, 1)
    os.waitpid(pid, 0)
    assert got == b"1"
    assert _side_pool() is parent


def test_split_evaluation_keeps_grad_mode_and_autocast():
    """Half the chunks run on the side thread: same values in float32 and bfloat16, no graph without grad."""
    from torm.reconstruction.dmtet import MLP_CHUNK, _side_pool

    grid = build_tet_grid(BOUNDS, 20)
    assert grid.n_verts > 2 * MLP_CHUNK
    cfg = DMTetConfig(param="mlp", mlp_hidden=16, mlp_fit_iters=0)
    fld = _Field(grid, _two_spheres_cells(grid), torch.zeros(grid.n_verts, dtype=torch.bool), cfg,
                 torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref32, ref16 = fld._mlp_rows(None), fld._mlp_rows(None, bf16=True)
        fld.side = _side_pool()
        got32, got16 = fld._mlp_rows(None), fld._mlp_rows(None, bf16=True)
    assert torch.equal(got32, ref32) and torch.equal(got16, ref16)
    assert got32.dtype == torch.float32 and not got32.requires_grad
    assert got16.dtype == torch.bfloat16
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):  # pre-cast weights: autocast's values
        assert torch.equal(got16, fld.mlp.net(fld.pe))
    # a mixed evaluation (float32 rows, bfloat16 rows padded to BF16_ROW_STEP) gives each row its own value
    a, b = torch.arange(0, 3 * MLP_CHUNK, 3), torch.arange(1, grid.n_verts, 3)
    with torch.no_grad():
        m32, m16 = fld._mlp_rows_mixed(a, b)
    assert torch.equal(m32, ref32[a]) and torch.equal(m16, ref16[b].float())
    with pytest.raises(RuntimeError, match="gradient-free"):
        fld._mlp_rows(a, bf16=True)
    with_grad = fld._mlp_rows(torch.arange(3 * MLP_CHUNK))  # with gradients: one thread, a graph
    assert with_grad.requires_grad


# ----------------------------------------------------------------------------------------------------------
# Eq. (3) and eq. (4) against hand-computed values; the L_init learning rate
# ----------------------------------------------------------------------------------------------------------
def test_alpha_and_lr_schedules_in_a_run(scene):
    _, masks, K, T = scene
    grid = build_tet_grid(BOUNDS, 12)
    cfg = DMTetConfig(param="vertex", iterations=6, alpha_max=3.0, alpha_min=1.0, alpha_decay_iters=4, lr=0.2,
                      lr_min=0.2, views_per_batch=2, eval_every=0)
    env = optimise_dmtet(grid, K, T, masks, cfg, table_z=0.0)
    assert env.history["alpha"] == [3.0, 2.5, 2.0, 1.5, 1.0, 1.0]  # eq. (3) by hand: 3 - (3 - 1) / 4 * t
    assert env.history["lr"] == pytest.approx([0.2] * 6)
    init = optimise_dmtet(grid, K, T, masks, replace(cfg, loss="init", init_lr_scale=0.1), table_z=0.0)
    assert init.history["alpha"] == [1.0] * 6 and init.history["lr"] == pytest.approx([0.02] * 6)


def test_mlp_eikonal_term_against_a_hand_computed_linear_field():
    grid = build_tet_grid([[0.0, 0.0, 0.0], [0.32, 0.32, 0.32]], 16)  # cubic cells of 0.02 m
    cfg = DMTetConfig(param="mlp", mlp_hidden=2, mlp_layers=1, mlp_pe_freqs=0, mlp_fit_iters=0)
    fld = _Field(grid, torch.zeros(grid.n_verts), torch.zeros(grid.n_verts, dtype=torch.bool), cfg,
                 torch.Generator().manual_seed(0))
    lin0, lin1 = fld.mlp.net[0], fld.mlp.net[2]
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(3)) * 0.32
    for c, expected in ((4.0, 0.25), (8.0, 0.0), (12.0, 0.25)):
        with torch.no_grad():
            lin0.weight.zero_()
            lin0.bias.copy_(torch.tensor([20.0, 0.0]))
            lin0.weight[0, 0] = c  # hidden unit 0 = c * x_norm + 20 > 0 on [-1, 1]: f_s is linear
            lin1.weight.zero_()
            lin1.bias.zero_()
            lin1.weight[0, 0] = 1.0
        # f_s = c * x_norm + 20 with x_norm = 2 x / 0.32 - 1: |grad f_s| = c * 2 / 0.32 cells per metre
        # = c * 2 * 0.02 / 0.32 cells per cell; eq. (4) = (that - 1)^2: c = 4 -> 0.25, 8 -> 0, 12 -> 0.25
        e = fld.eikonal(torch.zeros(1), grid.verts_vx3, pts, torch.Generator())
        assert float(e.detach()) == pytest.approx(expected, abs=1e-6)
    assert float(fld.eikonal(torch.zeros(1), grid.verts_vx3, pts[:0], torch.Generator())) == 0.0
