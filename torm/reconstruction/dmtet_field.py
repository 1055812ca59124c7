"""DMTet-Multi's field: the SDF (grid cells) and deformation (m) of every tet-grid vertex, from per-vertex tensors or
the paper's MLP, evaluated in full or on the band of crossing tets, in float32 or bfloat16
(:mod:`torm.reconstruction.dmtet`).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import nn

from torm.reconstruction import losses
from torm.reconstruction.dmtet_config import BF16_CHUNK, MLP_CHUNK, SPLIT_MIN_ROWS, DMTetConfig
from torm.reconstruction.mlp import SDFDeformMLP
from torm.reconstruction.tetgrid import TetGrid

log = logging.getLogger(__name__)




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


