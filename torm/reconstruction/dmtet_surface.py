"""DMTet-Multi's surface: differentiable marching tets of the field's current state, its silhouettes and the
gradients back to the field (:mod:`torm.reconstruction.dmtet`).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from torm.reconstruction.band_march import BandMarchWork, band_march, surface_points
from torm.reconstruction.crossing_band import Band, build_band
from torm.reconstruction.dmtet_config import GRAD_SPLIT_ROWS, DMTetConfig
from torm.reconstruction.dmtet_field import _BF16, _Field
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.tetgrid import TetGrid

log = logging.getLogger(__name__)




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
