"""DMTet-Multi: fit a deformable tet grid's SDF to multi-view silhouettes (TORM Sec. III-B, eq. (1)-(5)).

Every grid vertex v_i carries an SDF value s_i and a deformation dv_i, either directly (``param="vertex"``,
about 5x faster per step) or predicted by the paper's 3-layer MLP f(v_i) (``param="mlp"``). Each step:
deformed vertices v'_i = v_i + 0.45 * cell * tanh(dv_i) -> differentiable marching tets -> antialiased
silhouettes of ``views_per_batch`` random views (:mod:`torm.reconstruction.raster`) -> mask loss (eq. 1,
eq. 2 with the alpha schedule of eq. 3, or robust per-view weighted) summed over the batch views plus
the eikonal term (eq. 4), i.e. eq. (5) -> Adam with a decaying learning rate.

With the MLP the field is evaluated only in a narrow band of tets around the current surface
(:mod:`torm.reconstruction.crossing_band`), re-evaluated on the whole grid every ``full_pass_every`` steps and
whenever the band's boundary changes sign; the mesh and all gradients are those of the full evaluation
(``narrow_band=False`` runs the full evaluation every step, the reference path). An empty mesh is reported as
empty: the run stops there (no gradient can reach the field any more), ``history["collapsed_at"]`` holds the
step, and the result's mesh is empty. ``rescue=True`` instead pulls the SDF down inside the batch
silhouettes (a mini visual hull, not in the paper) and counts the steps in ``history["rescued_steps"]``.

Internally SDF values are in units of the mean grid cell edge (so learning rates do not depend on the
grid resolution); inputs and outputs are in metres. Grid vertices on the outer boundary of the box and
below the table plane are held outside (s = +0.5 cell), which keeps every extracted mesh closed.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from functools import partial

import cv2
import numpy as np
import torch

from torm.errors import ConfigError
from torm.reconstruction import losses
from torm.reconstruction.dmtet_config import MLP_CHUNK, DMTetConfig, DMTetResult  # noqa: F401  (re-exported)
from torm.reconstruction.dmtet_field import _BF16, _Field  # noqa: F401  (_Field re-exported for the tests)
from torm.reconstruction.dmtet_surface import _add_grads, _Clock, _Surface  # noqa: F401  (re-exported for the tests)
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.raster import SilhouetteBatch, face_adjacency, render_mask
from torm.reconstruction.tetgrid import TetGrid
from torm.runtime import default_threads
from torm.types import TriMesh

log = logging.getLogger(__name__)



# ----------------------------------------------------------------------------------------------------------
# Supervision helpers
# ----------------------------------------------------------------------------------------------------------
def supervision_size(H: int, W: int, mask_res: int) -> tuple[int, int]:
    """(h, w) with the longest side ``mask_res`` (never upsampled)."""
    s = min(1.0, mask_res / max(H, W))
    return max(1, round(H * s)), max(1, round(W * s))


def downsample_masks(
    masks_vxhxw: np.ndarray, K_vx3x3: np.ndarray, mask_res: int
) -> tuple[np.ndarray, np.ndarray]:
    """Area-average binary/float masks to the longest side ``mask_res`` and scale K to match.

    Returns (coverage (V, h, w) float32 in [0, 1], K (V, 3, 3) float64). With the pixel-centre-at-+0.5
    convention, u' = u * w / W exactly, so K' = diag(w / W, h / H, 1) @ K.
    """
    V, H, W = masks_vxhxw.shape
    h, w = supervision_size(H, W, mask_res)
    m = masks_vxhxw.astype(np.float32)
    if (h, w) != (H, W):
        m = np.stack([cv2.resize(x, (w, h), interpolation=cv2.INTER_AREA) for x in m])
    S = np.diag([w / W, h / H, 1.0])
    return np.clip(m, 0.0, 1.0), np.einsum("ij,vjk->vik", S, np.asarray(K_vx3x3, dtype=np.float64))


def silhouette_iou(pred_hw: np.ndarray, target_hw: np.ndarray) -> float:
    """IoU of two (H, W) coverage maps thresholded at 0.5 (1.0 when both are empty)."""
    p = pred_hw > 0.5
    t = target_hw > 0.5
    union = np.logical_or(p, t).sum()
    return 1.0 if union == 0 else float(np.logical_and(p, t).sum() / union)


def _batch_iou(pred_vxhxw: np.ndarray, target_vxhxw: np.ndarray) -> np.ndarray:
    """(V,) :func:`silhouette_iou` of boolean (V, H, W) stacks, in one pass."""
    inter = np.logical_and(pred_vxhxw, target_vxhxw).sum(axis=(1, 2))
    union = np.logical_or(pred_vxhxw, target_vxhxw).sum(axis=(1, 2))
    return np.where(union == 0, 1.0, inter / np.maximum(union, 1))


def dome_sdf(verts_vx3: np.ndarray, bounds_2x3: np.ndarray, floor_z: float, scale: float) -> np.ndarray:
    """Approximate SDF (m) of a half-ellipsoid standing on z = floor_z, centred on the box, radii scaled."""
    b = np.asarray(bounds_2x3, dtype=np.float64)
    c = np.array([(b[0, 0] + b[1, 0]) / 2, (b[0, 1] + b[1, 1]) / 2, floor_z])
    r = scale * np.array([(b[1, 0] - b[0, 0]) / 2, (b[1, 1] - b[0, 1]) / 2, max(b[1, 2] - floor_z, 1e-6)])
    q = (np.asarray(verts_vx3, dtype=np.float64) - c) / r
    return (np.linalg.norm(q, axis=1) - 1.0) * r.min()


def fixed_outside_mask(grid: TetGrid, table_z: float | None) -> np.ndarray:
    """(V,) bool: grid vertices held outside (box boundary, and below ``table_z`` when given)."""
    v = grid.verts_vx3.numpy().astype(np.float64)
    b = grid.bounds
    tol = 1e-6 + 1e-3 * grid.cell_size.min()
    out = np.any(np.abs(v - b[0]) < tol, axis=1) | np.any(np.abs(v - b[1]) < tol, axis=1)
    if table_z is not None:
        out |= v[:, 2] < table_z - 1e-9
    return out


# ----------------------------------------------------------------------------------------------------------
# The optimiser
# ----------------------------------------------------------------------------------------------------------
def _lr_at(cfg: DMTetConfig, it: int) -> float:
    frac = it / max(1, cfg.iterations - 1)
    if cfg.lr_schedule == "exp":
        return cfg.lr * (cfg.lr_min / cfg.lr) ** frac
    return cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1.0 + math.cos(math.pi * frac))


def _progress_bar(n_steps: int):
    """``range(n_steps)`` with a tqdm bar on an interactive stderr when torm logs at INFO (off with ``-q``, in
    benchmarks and when stderr is a file); long paper-mode runs show steps/s and the time left."""
    import sys

    from tqdm import tqdm

    show = n_steps >= 200 and sys.stderr.isatty() and log.isEnabledFor(logging.INFO)
    return tqdm(range(n_steps), desc="DMTet", unit="step", leave=False, mininterval=1.0, disable=not show)


def optimise_dmtet(
    grid: TetGrid,
    K_vx3x3: np.ndarray,
    T_cam_world_vx4x4: np.ndarray,
    masks_vxhxw: np.ndarray,
    cfg: DMTetConfig,
    init_sdf_v: np.ndarray | None = None,
    table_z: float | None = None,
    weights_vxhxw: np.ndarray | None = None,
) -> DMTetResult:
    """Run DMTet-Multi.

    Args:
        grid: the tet grid (metres, world frame).
        K_vx3x3: intrinsics of the **supervision** masks (see :func:`downsample_masks`).
        T_cam_world_vx4x4: world-to-camera transforms, OpenCV axes.
        masks_vxhxw: silhouette coverage in [0, 1] (union of all objects), float.
        cfg: the optimiser settings.
        init_sdf_v: (V,) start SDF in metres for ``start="hull"`` (negative inside).
        table_z: table height (m); grid vertices below it are held outside (and the dome stands on it).
        weights_vxhxw: optional per-pixel weights of the mask loss in [0, 1], the masks' shape: the share of each
            supervision pixel that holds evidence (0 where the view has no source pixel after undistortion,
            :func:`torm.capture.lens.no_evidence_masks`); None weighs every pixel 1.

    Returns:
        :class:`DMTetResult`. When the mesh vanishes, without ``cfg.rescue`` the run stops at that step with an
        empty mesh (``history["collapsed_at"] = [step]``, else ``[-1]``); with it the step is answered with a
        loss that pulls the SDF down at vertices projecting inside the batch silhouettes
        (``history["rescued_steps"]``). ``history["empty_steps"]`` counts the steps with an empty mesh.
        ``timings["torch_threads"]``: the intra-op threads it ran with (``cfg.threads``, or the caller's for 0).
    """
    with _torch_threads(cfg.threads or torch.get_num_threads()):
        return _optimise(grid, K_vx3x3, T_cam_world_vx4x4, masks_vxhxw, cfg, init_sdf_v, table_z, weights_vxhxw)


def _optimise(grid: TetGrid, K_vx3x3: np.ndarray, T_cam_world_vx4x4: np.ndarray, masks_vxhxw: np.ndarray,
              cfg: DMTetConfig, init_sdf_v: np.ndarray | None, table_z: float | None,
              weights_vxhxw: np.ndarray | None = None) -> DMTetResult:
    """:func:`optimise_dmtet` at the torch thread count already set."""
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    V_views, h, w = masks_vxhxw.shape
    gen = torch.Generator().manual_seed(int(cfg.seed))
    rng = np.random.default_rng(cfg.seed)
    cell = float(np.mean(grid.cell_size))
    if cfg.start == "hull":
        if init_sdf_v is None or len(init_sdf_v) != grid.n_verts:
            raise ConfigError("DMTetConfig.start='hull' needs init_sdf_v with one SDF value (m) per grid vertex")
        sdf0 = np.asarray(init_sdf_v, dtype=np.float64)
    else:
        in_box = table_z is not None and grid.bounds[0, 2] <= table_z < grid.bounds[1, 2]
        floor = table_z if in_box else grid.bounds[0, 2]
        sdf0 = dome_sdf(grid.verts_vx3.numpy(), grid.bounds, floor, cfg.sphere_scale)
    fixed = torch.from_numpy(fixed_outside_mask(grid, table_z))
    t0 = time.perf_counter()
    clamp = cfg.start_band if cfg.param == "vertex" else (cfg.mlp_fit_clamp or np.inf)
    sdf0_cells = np.clip(sdf0 / cell, -clamp, clamp)
    n_fit = cfg.fit_threads or default_threads()[0]
    with _torch_threads(n_fit if cfg.param == "mlp" else torch.get_num_threads()):
        fld = _Field(grid, torch.from_numpy(sdf0_cells), fixed, cfg, gen)
    t_fit = time.perf_counter() - t0
    # the schedule shape is shared; the MLP's weights step at mlp_lr instead of lr (in cells); L_init runs at a
    # lower learning rate from the sphere start (the paper, Sec. IV-B; a hull start is the fast mode's refinement)
    lr_scale = 1.0 if cfg.param == "vertex" else cfg.mlp_lr / cfg.lr
    if cfg.loss == "init" and cfg.start == "sphere":
        lr_scale *= cfg.init_lr_scale
    # not fused: the fused Adam saved 0.17 ms a step but the run then rebuilt the band twice as often (syn12,
    # 2500 steps: 276 vs 126 boundary rebuilds, 37.4 vs 31.5 ms/step)
    opt = torch.optim.Adam(fld.params, lr=cfg.lr * lr_scale)
    masks_t = torch.from_numpy(np.ascontiguousarray(masks_vxhxw, dtype=np.float32))
    masks_in = masks_vxhxw > 0.5
    if weights_vxhxw is not None and np.shape(weights_vxhxw) != masks_vxhxw.shape:
        raise ConfigError(f"DMTet weights {np.shape(weights_vxhxw)} must match the masks {masks_vxhxw.shape}")
    weights_t = None if weights_vxhxw is None else torch.from_numpy(
        np.ascontiguousarray(np.clip(weights_vxhxw, 0.0, 1.0), dtype=np.float32))
    K_all = np.asarray(K_vx3x3, dtype=np.float64)
    T_all = np.asarray(T_cam_world_vx4x4, dtype=np.float64)
    hist: dict[str, list[float]] = {k: [] for k in ("loss", "mask_loss", "eikonal", "iou", "alpha", "lr", "n_faces")}
    hist.update(eval_iter=[], iou_all=[], empty_steps=[0.0], rescued_steps=[0.0], collapsed_at=[-1.0])
    nb = min(cfg.views_per_batch, V_views)
    clock = _Clock()
    surf = _Surface(fld, grid, cfg, clock)
    n_run = 0
    side = None
    if cfg.param == "mlp" and (cfg.side_thread == "on" or (
            cfg.side_thread == "auto" and torch.get_num_threads() == 1 and default_threads()[0] >= 2)):
        side = _side_pool()
    fld.side = side
    eik_side = side if cfg.lambda_eikonal > 0 else None
    # with a side thread, the side thread computes the face adjacency and renders the last view of the batch, then
    # eq. (4) and its gradient, while the main thread rasterises the other views (measured without gain before the
    # sparse loss: the side thread taking views after eq. 4, and the reverse split, eq. 4 on the main thread;
    # 33.2 vs 33.4 ms/step). Without a side thread the views render on the torch threads
    pool = None if side is not None else _render_pool(min(nb, torch.get_num_threads()))
    bar = _progress_bar(cfg.iterations)
    for it in bar:
        n_run = it + 1
        lr = _lr_at(cfg, it) * lr_scale
        for g in opt.param_groups:
            g["lr"] = lr
        alpha = 1.0 if cfg.loss == "init" else losses.alpha_schedule(it, cfg.alpha_max, cfg.alpha_min, cfg.decay_T)
        idx = rng.choice(V_views, size=nb, replace=False)
        s, verts, mv, mf = surf.extract(it)
        tgt = masks_t[idx]
        wgt = None if weights_t is None else weights_t[idx]
        eik_job = None
        if len(mf) == 0:
            hist["empty_steps"][0] += 1
            mask_l = losses.mask_loss_init(torch.zeros_like(tgt), tgt, wgt).sum()
            if not cfg.rescue:
                hist["collapsed_at"][0] = float(it)
                log.warning("DMTet %s/%s: the mesh vanished at step %d of %d; stopping with an empty mesh "
                            "(no gradient reaches the field any more; DMTetConfig.rescue re-seeds it)",
                            cfg.param, cfg.loss, it, cfg.iterations)
                loss = eik = mask_l
            else:
                hist["rescued_steps"][0] += 1
                s_full = s if not surf.banded else fld.evaluate()[0]
                loss = _empty_rescue_loss(s_full, fld.base, K_all[idx], T_all[idx], masks_vxhxw[idx])
                eik = loss * 0.0
            iou = 0.0
        else:
            with clock("render_loss"):
                batch = SilhouetteBatch(mv, mf, K_all[idx], T_all[idx], h, w)
                # eq. (4) and its gradient on the side thread while the views render
                eik_start = None if eik_side is None else partial(
                    eik_side.submit, _eikonal_grads, fld, s, verts, mv.detach(), gen, cfg.lambda_eikonal)
                eik_job = _render_batch(batch, side, pool, eik_start)
                sil = batch.finish()
                # eq. (1) is eq. (2) with alpha = 1 (alpha is 1 for "init"); the graph holds only the edge pixels
                per_view = losses.envelope_mask_loss_sparse(torch.from_numpy(sil.hard_vxhxw), sil.pix_n, sil.delta_n,
                                                            tgt, alpha, wgt)
                if cfg.loss == "robust":
                    per_view = per_view * losses.robust_view_weights(per_view, cfg.robust_kind, cfg.robust_c)
                mask_l = per_view.sum()
                iou = float(np.mean(_batch_iou(sil.values() > 0.5, masks_in[idx])))
            if eik_job is None:
                with clock("eikonal"):
                    eik = fld.eikonal(s, verts, mv, gen) if cfg.lambda_eikonal > 0 else mask_l * 0.0
                loss = cfg.lambda_mask * mask_l + cfg.lambda_eikonal * eik
            else:
                loss = cfg.lambda_mask * mask_l
        with clock("backward_step"):
            opt.zero_grad(set_to_none=True)
            if loss.requires_grad:
                loss.backward()
        surf.backward_field()
        if eik_job is not None:
            with clock("eikonal_wait"):
                eik, eik_grads = eik_job.result()
                _add_grads(fld.params, eik_grads)
                loss = loss + cfg.lambda_eikonal * eik
        with clock("backward_step"):
            if loss.requires_grad or eik_job is not None:
                opt.step()
        hist["loss"].append(float(loss.detach()))
        hist["mask_loss"].append(float(mask_l.detach()))
        hist["eikonal"].append(float(eik.detach()))
        hist["iou"].append(iou)
        hist["alpha"].append(alpha)
        hist["lr"].append(lr)
        hist["n_faces"].append(float(len(mf)))
        if len(mf) == 0 and not cfg.rescue:
            break
        if (it + 1) % 250 == 0:
            log.info("DMTet %s/%s step %d/%d: batch IoU %.3f, %d faces, %.0f ms/step so far", cfg.param, cfg.loss,
                     it + 1, cfg.iterations, iou, len(mf), 1e3 * (time.perf_counter() - t_start - t_fit) / (it + 1))
        if cfg.eval_every and (it + 1) % cfg.eval_every == 0 and it + 1 < cfg.iterations:
            with clock("eval"):
                hist["eval_iter"].append(float(it + 1))
                hist["iou_all"].append(_iou_all(mv.detach().numpy(), mf.numpy(), K_all, T_all, masks_vxhxw))
    bar.close()
    with clock("final"), torch.no_grad():
        s, verts = fld.evaluate()
        mv, mf = marching_tets(verts, grid.tets_tx4, s * cell)
    mesh = TriMesh(mv.numpy().astype(np.float64), mf.numpy())
    hist["eval_iter"].append(float(n_run))
    hist["iou_all"].append(_iou_all(mesh.verts_vx3, mesh.faces_fx3, K_all, T_all, masks_vxhxw))
    for k in ("full_passes", "boundary_rebuilds", "band_misses", "bf16_rows", "f32_rows", "bf16_near_rows",
              "bf16_late_rows", "bf16_sign_errors", "bf16_err_max"):
        hist[k] = [float(surf.stats[k])]
    hist["band_verts"], hist["band_tets"] = surf.stats["band_verts"], surf.stats["band_tets"]
    hist["grad_verts_mean"] = [surf.stats["grad_verts"] / max(1, n_run)]
    hist["backprop_verts_mean"] = [surf.stats["backprop_verts"] / max(1, n_run)]
    total = time.perf_counter() - t_start
    n_it = max(1, n_run)
    timings = {
        "total_s": total,
        # CPU seconds of this process (all threads): robust to other processes sharing the cores
        "total_cpu_s": time.process_time() - cpu_start,
        "mlp_fit_s": t_fit,
        "ms_per_step": 1e3 * (total - t_fit) / n_it if cfg.iterations else 0.0,
        "steps_run": float(n_run),
        "torch_threads": float(torch.get_num_threads()),
        "fit_threads": float(n_fit),
        "side_thread": float(side is not None),
        "bf16": float(surf.mixed),
        "fit_bf16": float(cfg.param == "mlp" and cfg.bf16 != "off" and _BF16),
    }
    for k, v in clock.s.items():
        timings[f"{k}_ms_per_step"] = 1e3 * v / n_it
    # the names earlier result files use
    timings["render_loss_ms_per_step"] = timings.get("render_loss_ms_per_step", 0.0)
    timings["marching_tets_ms_per_step"] = timings.get("marching_tets_ms_per_step", 0.0)
    log.info("DMTet %s/%s/%s: %d of %d steps, %.1f ms/step, final IoU %.3f, %d empty steps, %d rescued",
             cfg.param, cfg.start, cfg.loss, n_run, cfg.iterations, timings["ms_per_step"], hist["iou_all"][-1],
             int(hist["empty_steps"][0]), int(hist["rescued_steps"][0]))
    return DMTetResult(
        sdf_v=(s.detach().numpy().astype(np.float64) * cell),
        verts_vx3=verts.detach().numpy().astype(np.float64),
        mesh=mesh,
        history=hist,
        timings=timings,
    )


@contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads; the previous count is restored after."""
    before = torch.get_num_threads()
    if n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


_POOLS: dict[int, ThreadPoolExecutor] = {}
_SIDE: list[ThreadPoolExecutor] = []


def _forget_pools() -> None:
    """In a forked child the pools' threads do not exist: start new ones on first use (else a submit would wait
    forever)."""
    _POOLS.clear()
    _SIDE.clear()


os.register_at_fork(after_in_child=_forget_pools)


def _side_pool() -> ThreadPoolExecutor:
    """One worker thread for torch work beside the loop, itself on 1 intra-op thread."""
    if not _SIDE:
        _SIDE.append(ThreadPoolExecutor(1, thread_name_prefix="torm-side", initializer=torch.set_num_threads,
                                        initargs=(1,)))
    return _SIDE[0]


def _eikonal_grads(fld: _Field, s: torch.Tensor, verts: torch.Tensor, v0_mx3: torch.Tensor, gen: torch.Generator,
                   lam: float) -> tuple[torch.Tensor, tuple[torch.Tensor | None, ...]]:
    """(eq. (4) detached, gradients of ``lam`` * eq. (4) w.r.t. the field's parameters)."""
    eik = fld.eikonal(s, verts, v0_mx3, gen)
    if not eik.requires_grad:
        return eik.detach(), tuple(None for _ in fld.params)
    grads = torch.autograd.grad(lam * eik, fld.params, allow_unused=True)
    # zeros, not None, for the parameters eq. (4) does not reach (the biases): as a double backward gives them
    return eik.detach(), tuple(torch.zeros_like(p) if g is None else g for p, g in zip(fld.params, grads, strict=True))


def _render_pool(n: int) -> ThreadPoolExecutor | None:
    """A shared pool of ``n`` threads (None for n < 2): the rasteriser's numba kernels release the GIL, so the
    views of a batch render in parallel on the cores torch may use."""
    if n < 2:
        return None
    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(n, thread_name_prefix="torm-raster")
    return _POOLS[n]


def _render_batch(batch: SilhouetteBatch, side: ThreadPoolExecutor | None, pool: ThreadPoolExecutor | None,
                  side_next: Callable[[], Future] | None = None) -> Future | None:
    """Run :meth:`SilhouetteBatch.view` of every view; returns when all are done.

    With a side thread: the side thread computes the face adjacency and renders the last view, then ``side_next()``
    (which queues more work on it; its future is returned) runs, while this thread rasterises the other views (their
    hard passes need no adjacency) and then finds their silhouette edges. Without: the views are mapped over
    ``pool`` (or this thread)."""
    n = batch.n_views
    if side is None:
        adj = face_adjacency(batch.faces_fx3, len(batch.verts))
        for _ in (map if pool is None or n < 2 else pool.map)(partial(batch.view, adjacency_fx3=adj), range(n)):
            pass
        return side_next() if side_next is not None else None
    adj_job = side.submit(face_adjacency, batch.faces_fx3, len(batch.verts))
    last_job = side.submit(lambda: batch.view(n - 1, adj_job.result()))
    nxt = side_next() if side_next is not None else None
    tri = [batch.rasterize_view(i) for i in range(n - 1)]
    adj = adj_job.result()
    for i in range(n - 1):
        batch.view(i, adj, tri[i])
    last_job.result()
    return nxt


def _iou_all(verts: np.ndarray, faces: np.ndarray, K_all: np.ndarray, T_all: np.ndarray, masks: np.ndarray) -> float:
    """Mean hard-silhouette IoU over all views (0 for an empty mesh)."""
    if len(faces) == 0:
        return 0.0
    h, w = masks.shape[1:]
    return float(np.mean([silhouette_iou(render_mask(verts, faces, K_all[i], T_all[i], h, w), masks[i])
                          for i in range(len(K_all))]))


def _empty_rescue_loss(s_cells: torch.Tensor, base_vx3: torch.Tensor, K: np.ndarray, T: np.ndarray,
                       masks: np.ndarray) -> torch.Tensor:
    """With no surface, pull the SDF below -0.5 cell at vertices inside every batch silhouette (a mini hull)."""
    v = base_vx3.numpy().astype(np.float64)
    inside = np.ones(len(v), dtype=bool)
    h, w = masks.shape[1:]
    for i in range(len(K)):
        p = v @ T[i, :3, :3].T + T[i, :3, 3]
        z = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
        with np.errstate(invalid="ignore"):
            u = np.floor(K[i, 0, 0] * p[:, 0] / z + K[i, 0, 2])
            r = np.floor(K[i, 1, 1] * p[:, 1] / z + K[i, 1, 2])
        ok = np.isfinite(u) & np.isfinite(r) & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        hit = np.zeros(len(v), dtype=bool)
        hit[ok] = masks[i][r[ok].astype(np.int64), u[ok].astype(np.int64)] > 0.5
        inside &= hit
    sel = torch.from_numpy(inside)
    if not bool(sel.any()):
        return s_cells.sum() * 0.0
    return torch.relu(s_cells[sel] + 0.5).mean()
