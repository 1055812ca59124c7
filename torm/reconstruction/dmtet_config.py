"""DMTet-Multi's settings and result (:mod:`torm.reconstruction.dmtet`): :class:`DMTetConfig`, :class:`DMTetResult`."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np

from torm.config import Range, check_finite
from torm.errors import ConfigError
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
    iterations: Annotated[int, Range(0, 100_000, "20x the paper's 5000; ~26 ms per step on 2 cores")] = 5000
    views_per_batch: Annotated[int, Range(1, 1024, "views rasterised per step")] = 4
    mask_res: Annotated[int, Range(8, 4096, "mask side in px; cameras here are <= 1280 px")] = 128
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
    eikonal_points: Annotated[int, Range(0, 1 << 20, "points per step")] = 512
    robust_kind: Literal["mad", "gm"] = "mad"
    robust_c: float = 3.0
    sphere_scale: float = 1.3
    start_band: float = 1.0
    mlp_hidden: Annotated[int, Range(1, 4096, "MLP width")] = 128
    mlp_layers: Annotated[int, Range(1, 64, "MLP depth")] = 3
    mlp_pe_freqs: Annotated[int, Range(0, 32, "positional-encoding octaves")] = 4
    mlp_fit_iters: Annotated[int, Range(0, 100_000, "MLP fitting steps")] = 300
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
        check_finite(self, "DMTetConfig")  # ranges and NaN / inf (torm.config), also when built in Python
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


