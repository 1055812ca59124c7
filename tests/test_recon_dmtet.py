"""DMTet-Multi optimiser and the top-level reconstruct() on a small synthetic two-object scene."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torm.errors import ConfigError, ReconstructionError
from torm.geometry import invert_T, look_at_cv
from torm.reconstruction.api import ReconstructionConfig, reconstruct
from torm.reconstruction.dmtet import DMTetConfig, downsample_masks, optimise_dmtet
from torm.reconstruction.raster import render_mask
from torm.reconstruction.tetgrid import build_tet_grid
from torm.types import CameraView, Capture

BOUNDS = np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]])
HW = 80


def _objects():
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    s.apply_translation([0.48, -0.07, 0.03])
    b = trimesh.creation.box(extents=[0.05, 0.05, 0.05])
    b.apply_translation([0.62, 0.06, 0.025])
    return [s, b]


def _cameras(n_views=16, hw=HW):
    f = 0.5 * hw / np.tan(np.deg2rad(30.0))  # 60 deg FOV
    K = np.array([[f, 0, hw / 2], [0, f, hw / 2], [0, 0, 1.0]])
    c = np.array([0.55, 0.0, 0.0])
    poses = []
    for i in range(n_views):
        az = 2 * np.pi * i / n_views
        el = np.deg2rad(25 + 40 * ((i * 7) % n_views) / n_views)
        eye = c + 0.5 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        poses.append(look_at_cv(eye, c + np.array([0, 0, 0.03])))
    return K, poses


def _capture(objs=None, n_views=16, hw=HW, K_override=None):
    objs = _objects() if objs is None else objs
    K, poses = _cameras(n_views, hw)
    views = []
    for i, T_wc in enumerate(poses):
        m = np.zeros((hw, hw), np.int32)
        for k, o in enumerate(objs):
            m[render_mask(o.vertices, o.faces, K, invert_T(T_wc), hw, hw)] = k + 1
        Kv = K_override if (K_override is not None and i == 3) else K
        views.append(CameraView(K=Kv, T_world_cam=T_wc, mask=m, name=f"v{i}"))
    return Capture(views=tuple(views), workspace_bounds=BOUNDS, table_height=0.0)


@pytest.fixture(autouse=True)
def _one_thread(monkeypatch):
    """reconstruct() calls configure_threads(): keep it at 1 thread on the shared 2-core test machine."""
    import torch

    before = torch.get_num_threads()
    monkeypatch.setenv("TORM_THREADS", "1")
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def capture():
    return _capture()


def test_fast_mode_reconstructs_both_objects(capture):
    rec = reconstruct(capture, ReconstructionConfig(grid_res=32, mask_res=HW, points_per_object=256))
    assert rec.info["silhouette_iou_mean"] > 0.9
    assert rec.n_objects == 2
    assert all(len(p.points_nx3) == 256 for p in rec.point_clouds)
    centres = sorted(m.verts_vx3.mean(0)[0] for m in rec.object_meshes)
    assert centres[0] == pytest.approx(0.48, abs=0.01) and centres[1] == pytest.approx(0.62, abs=0.01)
    assert rec.timings["total"] > 0 and "narrow_band" in rec.timings


def test_fast_mode_with_refinement_keeps_quality(capture):
    cfg = ReconstructionConfig(grid_res=32, mask_res=HW, refine_iters=30, points_per_object=64)
    rec = reconstruct(capture, cfg)
    assert rec.n_objects == 2 and rec.info["silhouette_iou_mean"] > 0.9
    assert len(rec.history["loss"]) == 30


def test_paper_mode_vertex_param_grows_iou_and_finds_both(capture):
    dm = DMTetConfig(param="vertex", iterations=240, views_per_batch=4, eval_every=40)
    rec = reconstruct(capture, ReconstructionConfig(mode="paper", grid_res=32, mask_res=HW, dmtet=dm,
                                                    points_per_object=64))
    iou = rec.history["iou_all"]
    assert iou[0] < 0.3 and iou[-1] > 0.9  # from the oversized dome to a tight fit
    # monotone-ish: every evaluation is at least the best earlier one minus a small slack
    assert all(b >= max(iou[: i + 1]) - 0.05 for i, b in enumerate(iou[1:]))
    assert rec.n_objects == 2
    assert rec.history["alpha"][0] == 3.0 and rec.history["alpha"][-1] == 1.0


def test_empty_mesh_mid_run_is_survived_with_the_rescue(capture):
    sil = capture.masks() > 0
    masks, K = downsample_masks(sil, capture.Ks(), 48)
    grid = build_tet_grid(BOUNDS, 20)
    cfg = DMTetConfig(param="vertex", start="hull", loss="init", iterations=40, lr=0.3, lr_min=0.05, eval_every=0,
                      rescue=True)
    res = optimise_dmtet(grid, K, np.linalg.inv(capture.poses()), masks, cfg,
                         init_sdf_v=np.full(grid.n_verts, 0.05), table_z=0.0)  # everything outside: empty
    assert res.history["empty_steps"][0] >= 1 and res.history["rescued_steps"] == res.history["empty_steps"]
    assert len(res.history["loss"]) == 40
    assert len(res.mesh.faces_fx3) > 0 and res.history["iou_all"][-1] > 0.2


def test_downsampled_masks_match_scaled_intrinsics():
    objs = _objects()
    K, poses = _cameras(2, 320)
    T = invert_T(poses[0])
    full = np.zeros((1, 320, 320), bool)
    for o in objs:
        full[0] |= render_mask(o.vertices, o.faces, K, T, 320, 320)
    small, K2 = downsample_masks(full, K[None], 80)
    assert small.shape == (1, 80, 80) and K2[0, 0, 0] == pytest.approx(K[0, 0] / 4)
    # the area-averaged mask equals the coverage rendered directly with the scaled K: same area and centroid
    import torch

    from torm.reconstruction.raster import render_silhouette

    direct = sum(render_silhouette(torch.tensor(o.vertices), o.faces, K2[0], T, 80, 80).numpy() for o in objs)
    assert small[0].sum() == pytest.approx(direct.sum(), rel=0.03)
    yy, xx = np.mgrid[0:80, 0:80]
    for img_a, img_b in ((small[0], direct),):
        ca = np.array([(img_a * xx).sum(), (img_a * yy).sum()]) / img_a.sum()
        cb = np.array([(img_b * xx).sum(), (img_b * yy).sum()]) / img_b.sum()
        assert np.abs(ca - cb).max() < 0.12  # px; an integer-centre convention slip would show as 0.375


def test_bad_inputs_raise_with_view_index():
    objs = _objects()
    empty = _capture(objs=[])
    with pytest.raises(ReconstructionError, match="masks are empty"):
        reconstruct(empty, ReconstructionConfig(grid_res=16))
    K_big = np.array([[200.0, 0, 640], [0, 200.0, 360], [0, 0, 1]])  # intrinsics of a 1280x720 image
    with pytest.raises(ReconstructionError, match="view 3"):
        reconstruct(_capture(K_override=K_big), ReconstructionConfig(grid_res=16))
    far = trimesh.creation.box(extents=[0.05, 0.05, 0.05])
    far.apply_translation([0.55, 0.40, 0.025])  # outside the box in y
    # per-object problems are reported per object; the other objects are still reconstructed
    rec = reconstruct(_capture(objs=[objs[0], far]), ReconstructionConfig(grid_res=16))
    assert rec.n_objects == 1 and rec.object_meshes[0].verts_vx3.mean(0)[0] == pytest.approx(0.48, abs=0.01)
    assert any("ymax" in r["reason"] for r in rec.info["rejected_objects"]) or rec.info["unexplained_views"]
    huge = trimesh.creation.box(extents=[0.5, 0.5, 0.1])
    huge.apply_translation([0.55, 0.0, 0.05])
    with pytest.raises(ReconstructionError, match="touches the reconstruction box.*--bounds"):
        reconstruct(_capture(objs=[huge]), ReconstructionConfig(grid_res=16))


def test_configs_are_validated():
    with pytest.raises(ConfigError):
        DMTetConfig(param="siren")
    with pytest.raises(ConfigError):
        DMTetConfig(lr=0.01, lr_min=0.1)
    with pytest.raises(ConfigError):
        DMTetConfig(max_deform=0.7)
    with pytest.raises(ConfigError):
        ReconstructionConfig(mode="slow")
    with pytest.raises(ConfigError):
        ReconstructionConfig(vote_tolerance=1.5)
    assert DMTetConfig().decay_T == 2500 and DMTetConfig(alpha_decay_iters=7).decay_T == 7
    assert DMTetConfig().iterations == 5000 and DMTetConfig().rescue is False
    with pytest.raises(ConfigError):
        DMTetConfig(init_lr_scale=0.0)
    with pytest.raises(ConfigError):
        DMTetConfig(full_pass_every=0)
    from torm.config import from_dict

    c = from_dict(ReconstructionConfig, {"bounds": [[0.3, -0.2, 0.0], [0.8, 0.2, 0.2]]},
                  overrides=["dmtet.param=vertex", "grid_res=64"])
    assert c.dmtet.param == "vertex" and c.grid_res == 64 and c.bounds[1][2] == 0.2
    with pytest.raises(ConfigError, match="envelope"):
        from_dict(ReconstructionConfig, {}, overrides=["dmtet.loss=l1"])


def test_mlp_param_fits_start_and_takes_eikonal_steps(capture):
    sil = capture.masks() > 0
    masks, K = downsample_masks(sil, capture.Ks(), 48)
    T_cw = np.linalg.inv(capture.poses())
    grid = build_tet_grid(BOUNDS, 16)
    common = dict(iterations=12, views_per_batch=2, eval_every=0, lambda_eikonal=0.1)
    vert = optimise_dmtet(grid, K, T_cw, masks, DMTetConfig(param="vertex", **common), table_z=0.0)
    mlp = optimise_dmtet(grid, K, T_cw, masks, DMTetConfig(param="mlp", mlp_fit_iters=150, mlp_hidden=64,
                                                           mlp_fit_lr=3e-3, **common), table_z=0.0)
    # after its initial fit the MLP renders the same dome as the per-vertex start
    assert mlp.history["n_faces"][0] > 0
    assert mlp.history["iou"][0] == pytest.approx(vert.history["iou"][0], abs=0.03)
    assert all(np.isfinite(mlp.history["eikonal"])) and max(mlp.history["eikonal"]) > 0
    assert mlp.timings["mlp_fit_s"] > 0 and len(mlp.history["loss"]) == 12


def test_progress_bar_only_on_an_interactive_stderr_at_info(monkeypatch):
    """The DMTet bar shows on a TTY when torm logs at INFO, never in a captured (benchmark, CI) stderr."""
    import logging
    import sys

    from torm.reconstruction import dmtet

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(dmtet.log, "isEnabledFor", lambda level: level >= logging.INFO)
    assert not dmtet._progress_bar(5000).disable
    assert dmtet._progress_bar(50).disable  # short refinements stay quiet
    monkeypatch.setattr(dmtet.log, "isEnabledFor", lambda level: level >= logging.WARNING)
    assert dmtet._progress_bar(5000).disable  # -q
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    monkeypatch.setattr(dmtet.log, "isEnabledFor", lambda level: True)
    bar = dmtet._progress_bar(5000)
    assert bar.disable and list(bar) == list(range(5000))
