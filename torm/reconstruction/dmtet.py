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
from dataclasses import dataclass, field
from functools import partial
from typing import Literal

import cv2
import numpy as np
import torch
from torch import nn

from torm.errors import ConfigError
from torm.reconstruction import losses
from torm.reconstruction.band_march import BandMarchWork, band_march, surface_points
from torm.reconstruction.crossing_band import Band, build_band
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.mlp import SDFDeformMLP
from torm.reconstruction.raster import SilhouetteBatch, face_adjacency, render_mask
from torm.reconstruction.tetgrid import TetGrid
from torm.runtime import default_threads
from torm.types import TriMesh

log = logging.getLogger(__name__)

_PARAMS = ("mlp", "vertex")
#: rows of the MLP evaluated at a time (see :meth:`_Field._mlp_rows`)
MLP_CHUNK = 1024
#: gradient-free float32 evaluations of this many rows or more (and under 2 * MLP_CHUNK) are cut in two halves
SPLIT_MIN_ROWS = 256
#: rows of a bfloat16 evaluation at a time (1 thread, 128 hidden: 1024 rows 111 us, 2048 rows 176 us per layer)
BF16_CHUNK = 2048
#: rows from which the band's gradient pass through the MLP runs in two halves (see ``_Surface._chain``)
GRAD_SPLIT_ROWS = 512
_STARTS = ("sphere", "hull")
_LOSSES = ("init", "envelope", "robust")


@dataclass(frozen=True)
class DMTetConfig:
    """DMTet-Multi optimiser settings; the defaults are the paper's setup (MLP, sphere start, envelope loss).

    Attributes:
        param: ``"vertex"`` (per-vertex SDF + deformation tensors) or ``"mlp"`` (3-layer MLP f(v)).
        start: ``"sphere"`` (oversized dome on the table covering the workspace) or ``"hull"`` (caller's SDF).
        loss: ``"init"`` eq. (1), ``"envelope"`` eq. (2)+(3), ``"robust"`` eq. (2)+(3) with robust per-view weights.
        iterations: optimisation steps. Default 5000: the paper's end-to-end timing ("a sufficiently good
            geometric representation in 5k steps, taking 177.3 s", Sec. IV-D), i.e. what a robot run uses; its
            Table I ablation runs 8000 (``benchmarks/reconstruction.py --table1`` does).
        views_per_batch: N_view of eq. (5), views rendered per step (the paper gives no value).
        mask_res: longest side (px) of the supervision masks, for :func:`downsample_masks` (area average,
            K scaled); :func:`optimise_dmtet` takes masks already at that size and ``reconstruct()``
            sets it from ``ReconstructionConfig.mask_res``.
        lr, lr_min: Adam learning rate at the start and the end of per-vertex parameters (units: cells).
        init_lr_scale: learning-rate factor for ``loss="init"`` (eq. 1) from the sphere start. The paper: "to
            mitigate this collapse, a lower learning rate is applied for L_init" without a value; 0.1 (one
            decade) is our choice, and ``benchmarks/reconstruction.py --table1`` also runs L_init at 1.0.
        lr_schedule: ``"exp"`` (geometric decay lr -> lr_min) or ``"cosine"``.
        lambda_mask, lambda_eikonal: weights of eq. (5).
        alpha_max, alpha_min: envelope coefficient bounds of eq. (3).
        alpha_decay_iters: decay duration of eq. (3) in iterations; None = half the iterations.
        max_deform: deformation limit as a fraction of a cell (tanh-scaled).
        eval_every: IoU over all views every this many steps (0 = only at the end).
        rescue: when the mesh vanishes, pull the SDF below zero inside the batch silhouettes (not in the paper;
            counted in ``history["rescued_steps"]``) instead of stopping with an empty mesh.
        narrow_band: MLP only: each step evaluate the field without gradients on a narrow band of tets around
            the surface and with gradients only on the vertices of crossing tets (the only ones that reach the
            mesh); False = every vertex with gradients every step (the reference path; same mesh, same
            gradients, see tests/test_recon_paper_mode.py).
        band_rings: the band's half-width in cells (lattice steps) around the crossing tets.
        full_pass_every: MLP with a band: evaluate every vertex (no gradient) and rebuild the band every this
            many steps, so that surface appearing outside the band is found.
        eikonal_points: MLP only: zero-crossing points per step at which eq. (4) is evaluated, a uniform random
            subset when there are more (an unbiased estimate of eq. 4's mean; 0 = all of them).
        robust_kind, robust_c: per-view weighting of the ``"robust"`` loss (:func:`losses.robust_view_weights`).
        sphere_scale: dome radii as a multiple of the box half-extents (xy) and height (z).
        start_band: per-vertex parameters: the start SDF is clamped to +-start_band cells, so a surface moves
            one cell in a few steps (a per-vertex SDF far from zero would take 1/lr steps per cell).
        mlp_hidden, mlp_layers, mlp_pe_freqs: MLP size and positional-encoding frequencies.
        mlp_fit_iters, mlp_fit_lr: initial fit of the MLP to the start SDF.
        mlp_fit_clamp: the MLP is fit to the start SDF clamped to +-mlp_fit_clamp cells; 0 = unclamped, the true
            distance as kaolin's DMTet reference pre-trains its MLP on a sphere SDF. A clamp of 1 cell (what
            per-vertex parameters use) lets one uniform output shift of the MLP erase the whole dome: measured on
            syn5, grid 48, the mesh vanished at step 9.
        mlp_lr: Adam step of the MLP weights at the start (decays by the same factor lr_min / lr). The paper
            gives no value. 1e-4, a tenth of kaolin's DMTet tutorial (1e-3), because at 1e-3 one Adam step moves
            the whole MLP surface by about a cell and the dome is erased before it reaches the objects (measured,
            syn4, grid 48, envelope loss: mesh gone at step 26; at 3e-4 at step 112), while the paper describes a
            shrink over thousands of steps (Fig. 6) and an L_init collapse "by about 10k iterations".
        seed: seeds the view sampling and the MLP initialisation.
        threads: torch intra-op threads while the optimisation runs (the caller's setting is restored after);
            0 keeps the caller's setting. 1 because the tensors of a step are small (a band of a few thousand
            vertices): on the 2-core machine paper mode ran syn5 (5000 steps) in 179 s with 1 thread and 263 s with
            2, every stage slower with 2 (2026-12-04, idle, before the side thread and the compiled band march;
            ``benchmarks/results/reconstruction_paper_2threads.json``; a first pair: 191 s and 254 s). The second
            core is used by ``side_thread`` instead.
        fit_threads: torch intra-op threads for the MLP's start fit (``mlp_fit_iters`` steps on batches of 8192
            vertices, large enough to gain from more cores: 6-9 s on 2 threads vs 11 s on 1, syn5, four runs); 0 = what
            :func:`torm.runtime.default_threads` gives (``TORM_THREADS``, else the idle cores). The periodic full
            passes stay on ``threads``: switching them to 2 threads made the whole run slower (29.3 vs 28.1
            ms/step), the idle OpenMP workers competing with the 1-thread loop.
        side_thread: MLP only: a second thread, itself on 1 torch thread, that computes the face adjacency and
            the batch's last view, then eq. (4) and its gradient, while the main thread rasterises the other views,
            and half of every gradient-free field evaluation (the band,
            the full passes) and of the band's gradient pass. Same values as without it: the work is split by rows
            or by independent terms and the parameter gradients are summed in a fixed order
            (tests/test_recon_paper_mode.py). "auto": on when
            the loop runs on 1 torch thread and :func:`torm.runtime.default_threads` gives 2 or more; "on"/"off"
            force it. Measured on syn5, 5000 steps, 2-core AVX-512 machine: 93 s with it (17.3 ms/step;
            ``benchmarks/results/reconstruction_paper.json``; 98-105 s before its share of the gradient pass and
            the compiled band build), 153 s without (28.9 ms/step, ``reconstruction_paper_noside.json``, same
            code; 135 s before the gradient pass was cut in halves, which on one thread cost more: field gradient
            2.8 -> 4.0 ms/step); the final meshes are identical (Chamfer and volume IoU to every digit). Without it
            the views of a batch render on ``threads`` threads.
        bf16: MLP only: bfloat16 where float32 values are not needed.
            (1) With a band, each step the band's vertices that were not vertices of a crossing tet the step before
            are evaluated in bfloat16 (weights and encodings cast once, float32 accumulation; 3x the float32 rows
            per second on this 2-core AVX-512-BF16 machine, 1024-row chunks of the 128-wide layers), the others in
            float32. Only signs are taken from bfloat16 values, and only where ``|s| >= bf16_sign_margin``; closer
            rows and every vertex of a crossing tet are evaluated in float32, so the mesh, its positions and every
            gradient are those of the float32 field as long as no bfloat16 error reaches the margin (the largest
            error seen on rows evaluated both ways is recorded in ``history["bf16_err_max"]`` and a warning is
            logged when it comes within half the margin). The full passes use the same bfloat16 rows. "auto": on
            where the CPU has native bfloat16 (emulated bfloat16 is slower than float32); "on"/"off" force it.
            (2) Where the CPU has native bfloat16 and this is not "off", the MLP's start fit runs under bfloat16
            autocast (float32 weights, loss and Adam): syn12's grid, 300 steps on 2 threads, 1.6-1.8 s instead of
            4.1-5.6 s, fit error 0.280 vs 0.279 cells (mean |f - target| over the grid).
        bf16_sign_margin: cells; see ``bf16``. The largest bfloat16 error measured on syn12's band over a
            5000-step run was 0.090 cells (``history["bf16_err_max"]``); 0.25 is 2.8 times that. With 0.5, 43 % of
            the bfloat16 rows were within the margin and evaluated again (field stage 10.0 ms/step vs 8.5 with 0.2
            on syn12's first 1000 steps; 10.4 with float32 only).
    """

    param: Literal["mlp", "vertex"] = "mlp"
    start: Literal["sphere", "hull"] = "sphere"
    loss: Literal["init", "envelope", "robust"] = "envelope"
    iterations: int = 5000
    views_per_batch: int = 4
    mask_res: int = 128
    lr: float = 0.3
    lr_min: float = 0.02
    lr_schedule: Literal["exp", "cosine"] = "exp"
    init_lr_scale: float = 0.1
    lambda_mask: float = 1.0
    lambda_eikonal: float = 0.01
    alpha_max: float = 3.0
    alpha_min: float = 1.0
    alpha_decay_iters: int | None = None
    max_deform: float = 0.45
    eval_every: int = 250
    rescue: bool = False
    narrow_band: bool = True
    band_rings: int = 1
    full_pass_every: int = 20
    eikonal_points: int = 512
    robust_kind: Literal["mad", "gm"] = "mad"
    robust_c: float = 3.0
    sphere_scale: float = 1.3
    start_band: float = 1.0
    mlp_hidden: int = 128
    mlp_layers: int = 3
    mlp_pe_freqs: int = 4
    mlp_fit_iters: int = 300
    mlp_fit_lr: float = 1e-3
    mlp_fit_clamp: float = 0.0
    mlp_lr: float = 1e-4
    seed: int = 0
    threads: int = 1
    fit_threads: int = 0
    side_thread: Literal["auto", "on", "off"] = "auto"
    bf16: Literal["auto", "on", "off"] = "auto"
    bf16_sign_margin: float = 0.25

    def __post_init__(self) -> None:
        if self.threads < 0:
            raise ConfigError(f"DMTetConfig.threads must be >= 0 (0 keeps the caller's setting), got {self.threads}")
        if self.fit_threads < 0:
            raise ConfigError(f"DMTetConfig.fit_threads must be >= 0 (0 = TORM_THREADS or the idle cores), got "
                              f"{self.fit_threads}")
        for name, valid in (("param", _PARAMS), ("start", _STARTS), ("loss", _LOSSES),
                            ("lr_schedule", ("exp", "cosine")), ("robust_kind", ("mad", "gm")),
                            ("side_thread", ("auto", "on", "off")), ("bf16", ("auto", "on", "off"))):
            if getattr(self, name) not in valid:
                raise ConfigError(f"DMTetConfig.{name}={getattr(self, name)!r}; valid choices: {', '.join(valid)}")
        if self.iterations < 0 or self.views_per_batch < 1 or self.mask_res < 8:
            raise ConfigError("DMTetConfig: need iterations >= 0, views_per_batch >= 1 and mask_res >= 8 px")
        if not (self.lr > 0 and 0 < self.lr_min <= self.lr):
            raise ConfigError(f"DMTetConfig: need 0 < lr_min <= lr, got lr={self.lr}, lr_min={self.lr_min}")
        if self.lambda_mask < 0 or self.lambda_eikonal < 0:
            raise ConfigError("DMTetConfig: lambda_mask and lambda_eikonal must be >= 0")
        if not (self.alpha_max >= self.alpha_min > 0):
            raise ConfigError(f"DMTetConfig: need alpha_max >= alpha_min > 0, got {self.alpha_max}, {self.alpha_min}")
        if self.alpha_decay_iters is not None and self.alpha_decay_iters < 1:
            raise ConfigError("DMTetConfig.alpha_decay_iters must be >= 1 iteration (or null for half the iterations)")
        if not (0.0 <= self.max_deform < 0.5):
            raise ConfigError(f"DMTetConfig.max_deform must be in [0, 0.5) cells, got {self.max_deform}")
        if self.eval_every < 0 or self.robust_c <= 0 or self.sphere_scale <= 0 or self.start_band <= 0:
            raise ConfigError("DMTetConfig: eval_every >= 0, robust_c, sphere_scale and start_band > 0 required")
        if not 0 < self.init_lr_scale <= 1:
            raise ConfigError(f"DMTetConfig.init_lr_scale must be in (0, 1], got {self.init_lr_scale}")
        if self.band_rings < 0 or self.full_pass_every < 1 or self.eikonal_points < 0:
            raise ConfigError("DMTetConfig: band_rings >= 0 cells, full_pass_every >= 1 step, eikonal_points >= 0")
        if not self.bf16_sign_margin > 0:
            raise ConfigError(f"DMTetConfig.bf16_sign_margin must be > 0 cells, got {self.bf16_sign_margin}")
        if self.mlp_lr <= 0 or self.mlp_fit_lr <= 0:
            raise ConfigError("DMTetConfig: mlp_lr and mlp_fit_lr must be > 0")
        if self.mlp_fit_clamp < 0:
            raise ConfigError(f"DMTetConfig.mlp_fit_clamp must be >= 0 cells (0 = unclamped), got {self.mlp_fit_clamp}")
        if self.mlp_hidden < 1 or self.mlp_layers < 1 or self.mlp_pe_freqs < 0 or self.mlp_fit_iters < 0:
            raise ConfigError("DMTetConfig: mlp_hidden, mlp_layers >= 1 and mlp_pe_freqs, mlp_fit_iters >= 0")

    @property
    def decay_T(self) -> int:
        return self.alpha_decay_iters if self.alpha_decay_iters is not None else max(1, self.iterations // 2)


@dataclass
class DMTetResult:
    """Output of :func:`optimise_dmtet`: SDF (V,) m and deformed vertices (V, 3) m on the grid, the mesh,
    per-iteration ``history`` and ``timings`` (``ms_per_step``, ``total_s``, ...)."""

    sdf_v: np.ndarray
    verts_vx3: np.ndarray
    mesh: TriMesh
    history: dict[str, list[float]] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


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
class _Field:
    """SDF (cells) + deformation (m) of every grid vertex, from per-vertex tensors or the MLP."""

    def __init__(self, grid: TetGrid, sdf0_cells: torch.Tensor, fixed_v: torch.Tensor, cfg: DMTetConfig,
                 gen: torch.Generator) -> None:
        self.grid = grid
        self.cfg = cfg
        self.cell = float(np.mean(grid.cell_size))
        self.cell_3 = torch.tensor(grid.cell_size, dtype=torch.float32)
        self.fixed = fixed_v
        self.side: ThreadPoolExecutor | None = None  # set by the optimiser; see DMTetConfig.side_thread
        self.base = grid.verts_vx3.float()
        b = torch.tensor(grid.bounds, dtype=torch.float32)
        self.lo, self.ext = b[0], b[1] - b[0]
        self.x_norm = (self.base - self.lo) / self.ext * 2.0 - 1.0
        if cfg.param == "vertex":
            self.sdf = sdf0_cells.clone().float().requires_grad_(True)
            self.dv = torch.zeros_like(self.base).requires_grad_(True)
            self.params = [self.sdf, self.dv]
            self.mlp = None
        else:
            self.mlp = SDFDeformMLP(cfg.mlp_hidden, cfg.mlp_layers, cfg.mlp_pe_freqs, generator=gen)
            self.params = list(self.mlp.parameters())
            with torch.no_grad():
                self.pe = self.mlp.encode(self.x_norm)  # the grid never moves: its positional encoding is fixed
            self._pe16: torch.Tensor | None = None
            self._fit(sdf0_cells.float(), gen)

    def _fit(self, target_cells: torch.Tensor, gen: torch.Generator) -> None:
        """Fit the MLP to the start SDF (cells) with zero deformation, ``mlp_fit_iters`` Adam steps on random
        batches of grid vertices."""
        opt = torch.optim.Adam(self.params, lr=self.cfg.mlp_fit_lr)
        tgt = target_cells
        n = len(self.x_norm)
        bs = min(n, 8192)
        low = self.cfg.bf16 != "off" and _BF16  # see DMTetConfig.bf16
        for _ in range(self.cfg.mlp_fit_iters):
            idx = torch.randint(0, n, (bs,), generator=gen)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=low):
                out = self.mlp.net(self.pe[idx]).float()
            loss = ((out[:, 0] - tgt[idx]) ** 2).mean() + (out[:, 1:] ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    def evaluate(self, idx: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(sdf (N,) in cells with fixed vertices outside, deformed vertices (N, 3) m) of all vertices or ``idx``."""
        if self.mlp is None:
            s, dv = self.sdf, self.dv
            if idx is not None:
                s, dv = s[idx], dv[idx]
        else:
            out = self._mlp_rows(idx)
            s, dv = out[:, 0], out[:, 1:]
        return self.sdf_of(s, idx), self.verts_of(dv, idx)

    def sdf_of(self, s_raw: torch.Tensor, idx: torch.Tensor | None) -> torch.Tensor:
        """SDF (N,) in cells from the raw output ``s_raw`` of the vertices ``idx`` (all when None): fixed
        vertices held outside at +0.5 cell."""
        fixed = self.fixed if idx is None else self.fixed[idx]
        return torch.where(fixed, torch.full_like(s_raw, 0.5), s_raw)

    def verts_of(self, dv_raw: torch.Tensor, idx: torch.Tensor | None) -> torch.Tensor:
        """Deformed positions (N, 3) m from the raw deformation output ``dv_raw`` of the vertices ``idx``:
        ``base + max_deform * cell * tanh(dv)``."""
        base = self.base if idx is None else self.base[idx]
        return base + self.cfg.max_deform * self.cell_3 * torch.tanh(dv_raw)

    def _mlp_rows(self, idx: torch.Tensor | None, bf16: bool = False) -> torch.Tensor:
        """The MLP on the encoded grid vertices ``idx`` (all when None), ``MLP_CHUNK`` rows at a time: the
        activations of a chunk stay in the CPU cache (measured, 1 thread, 128 hidden: 31k rows 54 ms in one
        piece, 20 ms in chunks of 1024; 8k rows 7.2 vs 5.6 ms). Rows are independent, so the values are those
        of one call up to float rounding. Without gradients, the side thread (if any) evaluates the second half
        of the chunks. ``bf16``: without gradients only, in bfloat16 (:func:`_net_bf16`, ``BF16_CHUNK`` rows at a
        time), returned in bfloat16."""
        grad = torch.is_grad_enabled()
        if bf16 and grad:
            raise RuntimeError("_Field._mlp_rows: bfloat16 rows are for gradient-free evaluations only")
        n = len(self.pe) if idx is None else len(idx)
        chunk = BF16_CHUNK if bf16 else MLP_CHUNK
        if not grad and not bf16 and SPLIT_MIN_ROWS <= n < 2 * MLP_CHUNK:
            # two chunks, so that a side thread takes one (the rows near zero each step, ~600 on syn12); decided
            # without looking at the side thread, so that the values are the same with and without it
            chunk = -(-n // 2)
        starts = list(range(0, n, chunk)) or [0]
        layers = self._bf16_layers() if bf16 else []
        pe = self._pe_bf16() if bf16 else self.pe

        def rows(chunk_starts: list[int]) -> list[torch.Tensor]:
            # grad mode is thread-local: set it in whichever thread runs this
            with torch.set_grad_enabled(grad):
                if bf16:
                    return [_net_bf16_rows(pe, i, chunk, idx, layers) for i in chunk_starts]
                return [self.mlp.net(pe[i:i + chunk] if idx is None else pe[idx[i:i + chunk]]) for i in chunk_starts]

        if self.side is None or grad or len(starts) < 2:
            parts = rows(starts)
        else:
            half = (len(starts) + 1) // 2
            job = self.side.submit(rows, starts[half:])
            parts = rows(starts[:half]) + job.result()
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _mlp_rows_mixed(self, idx32: torch.Tensor, idx16: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Without gradients: the MLP on the vertices ``idx32`` in float32 and on ``idx16`` in bfloat16, both
        returned as float32 ((n32, 4), (n16, 4)). The side thread (if any) takes the bfloat16 chunks and float32
        chunks from the end until it holds about half the work (a 2048-row bfloat16 chunk costs about half a
        1024-row float32 chunk here); which thread runs a chunk does not change its values."""
        layers, pe16 = self._bf16_layers(), self._pe_bf16()
        jobs = [(False, i) for i in range(0, len(idx32), MLP_CHUNK)] + [(True, i) for i in range(0, len(idx16),
                                                                                             BF16_CHUNK)]

        def run(todo: list[tuple[bool, int]]) -> list[torch.Tensor]:
            with torch.no_grad():
                return [_net_bf16_rows(pe16, i, BF16_CHUNK, idx16, layers).float() if lo
                        else self.mlp.net(self.pe[idx32[i:i + MLP_CHUNK]]) for lo, i in todo]

        cost = [0.5 if lo else 1.0 for lo, _ in jobs]
        split = len(jobs)
        if self.side is not None and len(jobs) >= 2:
            side_cost, total = 0.0, sum(cost)
            while split > 1 and side_cost + cost[split - 1] <= total / 2 + 0.25:
                split -= 1
                side_cost += cost[split]
        job = self.side.submit(run, jobs[split:]) if split < len(jobs) else None
        parts = run(jobs[:split]) + (job.result() if job is not None else [])
        n32 = -(-len(idx32) // MLP_CHUNK)
        width = self.mlp.net[-1].out_features
        out32 = torch.cat(parts[:n32]) if n32 else torch.zeros((0, width))
        out16 = torch.cat(parts[n32:]) if len(parts) > n32 else torch.zeros((0, width))
        return out32, out16

    def _bf16_layers(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(bias, weight transposed) of every linear layer of the MLP in bfloat16, from the current weights."""
        with torch.no_grad():
            return [(m.bias.bfloat16(), m.weight.t().contiguous().bfloat16())
                    for m in self.mlp.net if isinstance(m, nn.Linear)]

    def _pe_bf16(self) -> torch.Tensor:
        """The grid's positional encoding in bfloat16 (cast once)."""
        if self._pe16 is None:
            self._pe16 = self.pe.bfloat16()
        return self._pe16

    def eikonal(self, s_cells: torch.Tensor, verts: torch.Tensor, v0_mx3: torch.Tensor,
                gen: torch.Generator) -> torch.Tensor:
        """Eq. (4). Per-vertex: the discrete form on the grid's zero-crossing edges. MLP: |grad_v f_s(v_0)| at
        the zero-crossing points ``v0_mx3`` (the marching-tets vertices, the paper's v_0), ``eikonal_points`` of
        them drawn uniformly when there are more."""
        if self.mlp is None:
            return losses.eikonal_loss_edges(s_cells, verts / self.cell, self.grid.edges_ex2)
        v0 = v0_mx3.detach()
        if len(v0) == 0:
            return s_cells.sum() * 0.0
        n_max = self.cfg.eikonal_points
        if n_max and len(v0) > n_max:
            v0 = v0[torch.randperm(len(v0), generator=gen)[:n_max]]
        # the gradient in closed form (SDFDeformMLP.sdf_input_gradient): 2x faster than a double backward here
        g = self.mlp.sdf_input_gradient((v0 - self.lo) / self.ext * 2.0 - 1.0)
        g_cells = g * 2.0 / self.ext * self.cell  # d(sdf cells) / d(position in cells)
        return losses.eikonal_loss_grad(g_cells)


def _net_bf16(x_nxd: torch.Tensor, layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """The MLP (linear layers with ReLU between) on bfloat16 rows ``x_nxd`` (N, D) with bfloat16 ``(bias, weight^T)``
    layers (:meth:`_Field._bf16_layers`): (N, out) bfloat16, the values CPU autocast gives, without casting the
    weights per call."""
    for i, (b, wt) in enumerate(layers):
        x_nxd = torch.addmm(b, x_nxd, wt)
        if i < len(layers) - 1:
            x_nxd = x_nxd.relu_()
    return x_nxd


#: bfloat16 evaluations are padded to a multiple of this many rows: oneDNN compiles a kernel per matrix shape, and a
#: band whose size changes every step made it compile every step (syn12: the band's field stage slower than float32)
BF16_ROW_STEP = 256


def _net_bf16_rows(pe_nxd: torch.Tensor, start: int, chunk: int, idx: torch.Tensor | None,
                   layers: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """:func:`_net_bf16` on the rows ``start:start + chunk`` of ``pe_nxd`` (or of ``pe_nxd[idx]``), the row count
    padded up to a multiple of ``BF16_ROW_STEP`` (with row 0, dropped from the result)."""
    sel = torch.arange(start, min(start + chunk, len(pe_nxd))) if idx is None else idx[start:start + chunk]
    m = len(sel)
    pad = -m % BF16_ROW_STEP
    if pad:
        sel = torch.cat([sel, sel.new_zeros(pad)])
    return _net_bf16(pe_nxd[sel], layers)[:m]


def _bf16_supported() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - torch builds without oneDNN
        return False


#: native bfloat16 matmuls on this CPU (AVX512-BF16/AMX): what DMTetConfig.bf16="auto" switches on
_BF16 = _bf16_supported()


class _Surface:
    """The mesh of the field each step: a full evaluation, or the MLP on a narrow band (same mesh, cheaper)."""

    def __init__(self, fld: _Field, grid: TetGrid, cfg: DMTetConfig, clock: _Clock) -> None:
        self.fld, self.grid, self.cfg, self.clock = fld, grid, cfg, clock
        self.banded = cfg.param == "mlp" and cfg.narrow_band
        self.band: Band | None = None
        # the band's tets as indices into its vertices, and their grid edge ids (set by every full pass)
        self._tets_local = np.zeros((0, 4), dtype=np.int64)
        self._edges_b = np.zeros((0, 6), dtype=np.int64)
        self.stats = {"full_passes": 0, "boundary_rebuilds": 0, "band_misses": 0, "band_verts": [], "band_tets": [],
                      "grad_verts": 0, "backprop_verts": 0, "bf16_rows": 0, "f32_rows": 0, "bf16_near_rows": 0,
                      "bf16_late_rows": 0, "bf16_sign_errors": 0, "bf16_err_max": 0.0}
        # bfloat16 for the band's rows away from the surface (see DMTetConfig.bf16)
        self.mixed = self.banded and (cfg.bf16 == "on" or (cfg.bf16 == "auto" and _BF16))
        self._hot_v = torch.zeros(grid.n_verts, dtype=torch.bool)  # crossing tets' vertices at the last step
        self._prev_hot: torch.Tensor | None = None
        self._fresh_s: torch.Tensor | None = None  # the bfloat16 full pass of this step, to measure the error
        self._leaves: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        if self.banded:
            self.tet_edges, self.n_edges = grid.tet_edges_tx6, len(grid.edges_ex2)
            self._work = BandMarchWork(self.n_edges)
            self._free = torch.nonzero(~fld.fixed, as_tuple=True)[0]

    def full_pass(self) -> None:
        """Evaluate every vertex without gradients, count band misses, rebuild the band.

        In bfloat16 with ``bf16`` (3x faster than float32 on this MLP here, measured 2026-12-04): these values
        only choose the band and count misses; the band's rows are evaluated again before the mesh is extracted,
        with float32 wherever the mesh needs values or a sign is within ``bf16_sign_margin`` of zero (at most a
        crossing tet whose |s| is within the bfloat16 error of zero and more than a ring away from any other
        crossing tet could be left out of the band until the next pass). The fixed vertices are not evaluated.
        """
        with self.clock("full_pass"), torch.no_grad():
            # the fixed vertices (box faces, below the table: 16 % of syn12's grid) are +0.5 whatever the MLP says
            s = torch.full((self.grid.n_verts,), 0.5)
            s[self._free] = self.fld._mlp_rows(self._free, bf16=self.mixed)[:, 0].float()
            self._fresh_s = s if self.mixed else None
            if self.band is not None:
                self.stats["band_misses"] += self.band.misses(s)
            self.band = build_band(self.grid.tets_tx4, s, self.grid.grid_shape, self.cfg.band_rings)
            local = torch.full((len(s),), -1, dtype=torch.int64)
            local[self.band.vert_ids_n] = torch.arange(self.band.n_verts)
            self._tets_local = local[self.band.tets_bx4].numpy()
            self._edges_b = self.tet_edges[self.band.tet_ids_b].numpy()
        self.stats["full_passes"] += 1
        self.stats["band_verts"].append(float(self.band.n_verts))
        self.stats["band_tets"].append(float(self.band.n_tets))

    def extract(self, it: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sdf cells, deformed vertices m, mesh vertices, mesh faces), differentiable: sdf and vertices of every
        grid vertex ((V,), (V, 3)), or with the band of the crossing tets' vertices only."""
        cell = self.fld.cell
        if not self.banded:
            with self.clock("field"):
                s, verts = self.fld.evaluate()
            with self.clock("marching_tets"):
                mv, mf = marching_tets(verts, self.grid.tets_tx4, s * cell)
            return s, verts, mv, mf
        fresh = self.band is None or it % self.cfg.full_pass_every == 0
        if fresh:
            self.full_pass()
        out = self._band_mesh()
        if len(out[3]) == 0 and not fresh:
            # nothing in the band: look at the whole grid before calling the mesh empty
            self.full_pass()
            out = self._band_mesh()
        return out

    def _band_mesh(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The field on the band without gradients; the mesh from it, with the SDF and position of every crossing
        tet's vertex as leaf tensors (every vertex of a crossing tet is an end of a crossing edge, and no other
        vertex reaches the mesh). :meth:`backward_field` carries their gradients into the MLP. The topology comes
        from :func:`band_march` (compiled); positions are computed for the crossing tets' vertices only.

        With ``bf16`` the rows away from the surface are evaluated in bfloat16 (:meth:`_band_field`) and every
        crossing tet's vertex that was not crossing the step before is evaluated again in float32 after the march;
        if its float32 sign differs from the bfloat16 one (never seen: ``history["bf16_sign_errors"]``), the band
        is marched again. A first attempt under CPU autocast was slower than float32 (12.9 vs about 10 ms/step on
        syn12): autocast casts the weights for every chunk, and oneDNN compiled a kernel for every new row count
        (the band's size changes every step), hence the pre-cast weights and the padded row counts."""
        with self.clock("field"), torch.no_grad():
            out, exact = self._band_field()
            s_n = self.fld.sdf_of(out[:, 0], self.band.vert_ids_n)
        if self.band.boundary_flipped(s_n):
            self.stats["boundary_rebuilds"] += 1
            self.full_pass()
            with self.clock("field"), torch.no_grad():
                out, exact = self._band_field()
                s_n = self.fld.sdf_of(out[:, 0], self.band.vert_ids_n)
        ids = self.band.vert_ids_n
        while True:
            with self.clock("marching_tets"):
                bm = band_march(s_n, self._tets_local, self._edges_b, self.n_edges, self._work)
                vc_n = torch.from_numpy(bm.vert_ids_c)
            if exact is None:
                break
            # crossing tets' vertices that were evaluated in bfloat16 (not crossing at the last step): float32 now
            late = vc_n[~exact[vc_n]]
            if len(late) == 0:
                break
            with self.clock("field"), torch.no_grad():
                fix = self.fld._mlp_rows(ids[late])
                s_fix = self.fld.sdf_of(fix[:, 0], ids[late])
                flipped = int(((s_fix < 0) != (s_n[late] < 0)).sum())
                out[late], s_n[late], exact[late] = fix, s_fix, True
            self.stats["bf16_late_rows"] += len(late)
            if flipped == 0:
                break  # same signs, same topology: only the positions needed float32
            self.stats["bf16_sign_errors"] += flipped  # a bfloat16 sign beyond the margin was wrong: march again
        with self.clock("marching_tets"):
            vc = ids[vc_n]
            with torch.no_grad():
                v_c = self.fld.verts_of(out[vc_n, 1:], vc)
            s_c = s_n[vc_n].requires_grad_(True)
            v_c = v_c.requires_grad_(True)
            mv = surface_points(v_c, s_c, bm.edge_a_m, bm.edge_b_m)  # the SDF's unit cancels
            mf = torch.from_numpy(bm.faces_fx3)
            if self.mixed:
                if self._prev_hot is not None:
                    self._hot_v[self._prev_hot] = False
                self._hot_v[vc] = True
                self._prev_hot = vc
        self._leaves = (vc, s_c, v_c)
        self.stats["grad_verts"] += len(vc)
        return s_c, v_c, mv, mf

    def _band_field(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The MLP's (Nb, 4) float32 outputs on the band's vertices, without gradients, and which rows are float32
        values (None: all of them). With ``bf16``: the vertices of the last step's crossing tets in float32, the
        others in bfloat16, and those whose bfloat16 |s| is below ``bf16_sign_margin`` again in float32; the
        bfloat16 rows' signs are trusted, their values are not used for the mesh (:meth:`_band_mesh`)."""
        ids = self.band.vert_ids_n
        if not self.mixed:
            return self.fld._mlp_rows(ids), None
        hot = self._hot_v[ids]
        f = torch.nonzero(hot, as_tuple=True)[0]
        b = torch.nonzero(~hot, as_tuple=True)[0]
        o32, o16 = self.fld._mlp_rows_mixed(ids[f], ids[b])
        out = torch.empty((len(ids), o32.shape[1]))
        out[f], out[b] = o32, o16
        exact = hot.clone()
        near = b[self.fld.sdf_of(o16[:, 0], ids[b]).abs() < self.cfg.bf16_sign_margin]
        if len(near):
            out[near] = self.fld._mlp_rows(ids[near])
            exact[near] = True
        self.stats["bf16_rows"] += len(b)
        self.stats["f32_rows"] += len(f) + len(near)
        self.stats["bf16_near_rows"] += len(near)
        if self._fresh_s is not None:  # rows this step evaluated both ways: the bfloat16 error
            both = ids[exact]
            if len(both):
                err = float((self.fld.sdf_of(out[exact, 0], both) - self._fresh_s[both]).abs().max())
                if err > self.stats["bf16_err_max"]:
                    self.stats["bf16_err_max"] = err
                    if err > 0.5 * self.cfg.bf16_sign_margin:
                        log.warning("DMTet: a bfloat16 SDF value was %.3f cells off its float32 value, more than half "
                                    "of bf16_sign_margin=%.3f; raise the margin or set bf16='off'", err,
                                    self.cfg.bf16_sign_margin)
            self._fresh_s = None
        return out, exact

    def backward_field(self) -> None:
        """After ``loss.backward()``: chain the gradients that reached the crossing tets' vertices through the MLP,
        re-evaluated with gradients only at the vertices whose gradient is not zero (the mask loss reaches only
        the silhouette's edges). The parameter gradients are those of a full evaluation: a zero upstream
        gradient contributes nothing."""
        if not self.banded or self._leaves is None:
            return
        vc, s_c, v_c = self._leaves
        self._leaves = None
        if s_c.grad is None and v_c.grad is None:
            return
        with self.clock("field_grad"):
            g_s = s_c.grad if s_c.grad is not None else torch.zeros_like(s_c)
            g_v = v_c.grad if v_c.grad is not None else torch.zeros_like(v_c)
            k = torch.nonzero((g_s != 0) | (g_v != 0).any(-1), as_tuple=True)[0]
            self.stats["backprop_verts"] += len(k)
            if len(k):
                self._chain(vc[k], g_s[k], g_v[k])

    def _chain(self, ids: torch.Tensor, g_s: torch.Tensor, g_v: torch.Tensor) -> None:
        """Add to the parameters' ``.grad`` the gradient of sum(g_s * sdf + g_v * position) over the grid vertices
        ``ids``. From ``GRAD_SPLIT_ROWS`` rows up, in two halves whose gradients are summed in a fixed order (the
        side thread, if any, computes the second half meanwhile): the same values with the side thread on or off."""
        params = self.fld.params

        def grads(lo: int, hi: int) -> tuple[torch.Tensor | None, ...]:
            with torch.enable_grad():
                s_k, v_k = self.fld.evaluate(ids[lo:hi])
                return torch.autograd.grad([s_k, v_k], params, [g_s[lo:hi], g_v[lo:hi]], allow_unused=True)

        n = len(ids)
        if n < GRAD_SPLIT_ROWS:
            total = grads(0, n)
        else:
            half = (n + 1) // 2
            job = self.fld.side.submit(grads, half, n) if self.fld.side is not None else None
            first = grads(0, half)
            second = job.result() if job is not None else grads(half, n)
            total = tuple(a if b is None else b if a is None else a + b for a, b in zip(first, second, strict=True))
        _add_grads(params, total)


def _add_grads(params: list[torch.Tensor], grads: tuple[torch.Tensor | None, ...]) -> None:
    """``p.grad += g`` for each parameter (``p.grad = g`` when it has none yet; None gradients skipped)."""
    for p, g in zip(params, grads, strict=True):
        if g is not None:
            p.grad = g if p.grad is None else p.grad + g


class _Clock:
    """Accumulated wall time per stage: ``with clock("stage"): ...``."""

    def __init__(self) -> None:
        self.s: dict[str, float] = {}
        self._name = ""
        self._t = 0.0

    def __call__(self, name: str) -> _Clock:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.s[self._name] = self.s.get(self._name, 0.0) + time.perf_counter() - self._t


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

    Returns:
        :class:`DMTetResult`. When the mesh vanishes, without ``cfg.rescue`` the run stops at that step with an
        empty mesh (``history["collapsed_at"] = [step]``, else ``[-1]``); with it the step is answered with a
        loss that pulls the SDF down at vertices projecting inside the batch silhouettes
        (``history["rescued_steps"]``). ``history["empty_steps"]`` counts the steps with an empty mesh.
        ``timings["torch_threads"]``: the intra-op threads it ran with (``cfg.threads``, or the caller's for 0).
    """
    with _torch_threads(cfg.threads or torch.get_num_threads()):
        return _optimise(grid, K_vx3x3, T_cam_world_vx4x4, masks_vxhxw, cfg, init_sdf_v, table_z)


def _optimise(grid: TetGrid, K_vx3x3: np.ndarray, T_cam_world_vx4x4: np.ndarray, masks_vxhxw: np.ndarray,
              cfg: DMTetConfig, init_sdf_v: np.ndarray | None, table_z: float | None) -> DMTetResult:
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
        eik_job = None
        if len(mf) == 0:
            hist["empty_steps"][0] += 1
            mask_l = losses.mask_loss_init(torch.zeros_like(tgt), tgt).sum()
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
                                                            tgt, alpha)
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
