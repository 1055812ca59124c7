"""Top-level reconstruction: a capture with silhouettes -> a :class:`torm.types.Reconstruction`.

Modes (:func:`mode_label` gives the name every table and record uses):

- ``"fast"`` (default), **TORM-fast (consensus + narrow-band projective hull)**:
  1. *consensus*: the projective visual hull (:mod:`torm.reconstruction.visual_hull`) on a coarse lattice
     (``grid_res``) with a vote tolerance of ``vote_views`` views, so a few bad masks cannot carve an
     object away; its connected components are the objects;
  2. *mask repair* (:func:`torm.reconstruction.objects.repair_masks`): a view whose silhouette misses
     most of a consensus object gets that object's footprint, so it carves everything else but not it;
  3. *narrow band* (:mod:`torm.reconstruction.adaptive_grid`): the strict (``fine_vote_views``) projective
     hull of the repaired silhouettes, evaluated coarse-to-fine only near its surface, from ``band_base_res``
     cells over ``band_levels`` 2x refinements, then marching tets. The projective SDF places the surface
     with sub-cell accuracy; with a one-pixel-scale finest cell it beats a voxel carve at equal time
     (``benchmarks/results/recon_vs_carve.md``).
  With ``refine_iters > 0`` steps 3-4 are replaced by the earlier design, **TORM-fast (hull + DMTet
  refinement)**: the tolerant hull on the dense ``grid_res`` tet grid refined by DMTet steps.
- ``"paper"``, **TORM-paper (DMTet-Multi)**: the paper's method (MLP f(v), oversized sphere start, envelope
  loss with the alpha schedule); the :class:`DMTetConfig` in ``config.dmtet`` is used as given except
  ``start="sphere"``.
- ``"carve"``: the survivors-only voxel carve (:mod:`torm.reconstruction.carve`) at ``carve_res``, a baseline.
- ``"paper"`` runs as the paper does: 5000 steps, **no rescue** (a mesh that vanishes raises
  ReconstructionError naming the step; ``DMTetConfig.rescue`` re-seeds it from the silhouettes, not in the paper).

Then, in every mode: marching tets / cubes -> connected components -> small components and cavities dropped
-> per-object checks (:func:`torm.reconstruction.objects.check_objects`: a component seen by fewer than
``min_views_per_object`` views, or cut by the box, is recorded in ``info["rejected_objects"]`` and not
returned) -> the same number of surface samples per object. The checks never follow an instance id
across views (a real segmenter's ids do not correspond between views).

Defaults and where they come from (measured here unless a source is named; figures in
``benchmarks/results/recon_vs_carve.md`` unless stated):

=================================  ==========================  ============================================
setting                            default                     source
=================================  ==========================  ============================================
consensus vote (``vote_views``)    0 below 12 views, else      RECONSTRUCTION.md: ~15 % of the views beat
                                   15 % of the views           segmenter-like corrupted masks
fine vote candidates               0 and 8 % of the views      rw4, noisy "paper" masks: Chamfer 3.59 mm
                                                               strict, 2.13 at 4 of 50 views, 2.60 at 8
``RIM_TOL_PX``                     1.5 px                      strict hull's missed rim: 0.44-0.45 px on GT
                                                               masks (rw1, rw4, syn12), 3.3-5.9 px on the
                                                               noisy "paper" masks
``cell_px`` / band levels          1.5 px -> 192 cells here    per-stage ablation: Chamfer flat from 192 to
                                                               384 cells at 3x the time
``facet_frac``                     0.3 of the hull's facet     per-level ablation on the recorded cases: 9
                                   width (:func:`hull_facet_m`) views (glass10) Chamfer 3.059 mm at 48 cells,
                                                               3.072 at 192; 8 views (ring8) 1.907 at 48, 2.001
                                                               at 96; rw4 (40 views) 0.836 at 192, 0.871 at 96.
                                                               Checked on bottles20 (16 views, not used to choose)
                                                               and all 20 sim scenes (unchanged: 192 cells)
``band``                           0.4 cell diagonals          identical meshes at 0.25-1.0 on rw4 and
                                                               syn12 (closure pass as the safety net)
``max_band_cells``                 120 000                     2x the largest sim scene (syn12: 57.5k surface
                                                               cells at 192); bounds the time when objects
                                                               fill many pixels (glass10 case)
``min_band_res``                   96 cells                    80 px masks: input-view IoU 0.883 at 48
                                                               cells, 0.914 at 96
``skip_cut_views``                 False                       ring8 case: held-out IoU 0.957 (False) vs
                                                               0.951 (True), volume IoU 0.846 vs 0.832
``min_views_per_object``           max(3, 20 % of the views)   issue #17: a phantom blob in a box corner
                                                               few views see; ring8: phantoms in 1-2 of 8
=================================  ==========================  ============================================

Inputs that adapt to the capture (``None`` = automatic, logged and recorded in ``info``):
bounds (config, else the capture's ``workspace_bounds``, else :func:`torm.reconstruction.bounds.auto_bounds`),
table (``no_table``, else ``table_z``, else the capture's ``table_height``; none when it has none),
vote tolerance (:func:`auto_vote_views`), band levels (:func:`auto_band_levels`), views per object.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Annotated, Literal

import numpy as np
from scipy import ndimage

from torm.capture.lens import no_evidence_masks
from torm.config import Range, check_finite
from torm.errors import CaptureError, ConfigError, ReconstructionError
from torm.mesh import sample_objects
from torm.mesh.split import signed_volume, split_components
from torm.reconstruction.adaptive_grid import narrow_band_hull
from torm.reconstruction.bounds import BOUNDS_HINT, auto_bounds
from torm.reconstruction.carve import carve_visual_hull
from torm.reconstruction.dmtet import DMTetConfig, downsample_masks, optimise_dmtet, silhouette_iou
from torm.reconstruction.objects import check_objects, consensus_objects, repair_masks, unexplained_views
from torm.reconstruction.raster import render_mask_fast
from torm.reconstruction.tetgrid import build_tet_grid, cells_per_axis
from torm.reconstruction.visual_hull import ProjectiveSDF, visual_hull_sdf
from torm.runtime import configure_threads
from torm.types import Capture, ObjectPointCloud, Reconstruction, TriMesh

log = logging.getLogger(__name__)

#: The box (m) of the simulated table scene (CONTEXT.md); kept for callers that want it explicitly.
#: ``reconstruct()`` no longer falls back to it: a capture without bounds gets automatic ones.
DEFAULT_BOUNDS = ((0.33, -0.22, -0.005), (0.77, 0.22, 0.20))

MODES = ("fast", "paper", "carve")
#: Views below which no vote tolerance is used (every view must agree), and the tolerated fraction above.
#: 15 % of the views is the tolerance RECONSTRUCTION.md measured to beat segmenter-like corrupted masks.
VOTE_MIN_VIEWS = 12
VOTE_FRACTION = 0.15
#: Tolerated fraction of the views tried besides 0 in the narrow-band hull (rw4 with the noisy segmenter's
#: "paper" masks, 50 views: 4 views gave Chamfer 2.13 mm, 8 views 2.60, strict 3.59; recon_vs_carve.md).
FINE_VOTE_FRACTION = 0.08
#: Input views (evenly spaced) on which the fit is evaluated and unexplained silhouette regions are looked for.
EVAL_VIEWS = 8
#: The strict narrow-band hull is kept unless its projection misses a silhouette rim wider than this (px).
RIM_TOL_PX = 1.5


@dataclass
class _EvalViews:
    """Evenly spaced input views at ``mask_res``: indices, coverage masks (n, h, w), K, world-to-camera."""

    index: np.ndarray
    masks: np.ndarray
    K: np.ndarray
    T_cw: np.ndarray
    renders: list = field(default_factory=list)  # renders of the selected mesh when already made (fast mode)
    unknown: np.ndarray | None = None  # (n, h, w) bool: pixels with no evidence (no source after undistortion)
#: Above this many distinct ids in one view a mask is probably not an instance map (a warning is logged).
MAX_IDS_PER_VIEW = 48


@dataclass(frozen=True)
class ReconstructionConfig:
    """Reconstruction settings (``None`` = chosen from the capture; see the module docstring).

    Attributes:
        mode: ``"fast"``, ``"paper"`` or ``"carve"`` (see the module docstring).
        grid_res: cells along the longest box axis of the dense tet grid (paper mode, refinement) and of the
            consensus lattice of fast mode.
        bounds: reconstruction box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (m); None = the capture's
            ``workspace_bounds``, else automatic from the cameras and masks.
        table_z: table-top height (m); None = the capture's ``table_height`` (no table when it has none).
        no_table: no table plane at all (objects may extend below z = 0), whatever the capture says.
        vote_views: views that may call a point outside before the consensus hull carves it (never half
            or more of the views that see it); None = :func:`auto_vote_views`.
        vote_tolerance: the same as a fraction of the views seeing a point (the earlier setting); when
            given it replaces ``vote_views``.
        fine_vote_views: views that may disagree in the narrow-band hull of the repaired masks (0 = strict);
            None = :func:`fine_vote_candidates`, evaluated in one pass, the one whose surface fits the input
            silhouettes best is kept (strict on consistent masks, tolerant on eroded/dilated ones).
        repair_coverage: a view whose silhouette covers less than this fraction of a consensus object's
            projection is taken to have missed it (its mask is repaired for that object).
        skip_cut_views: a view in which an object is cut by the image border does not carve that object
            (it still carves everything else); False: it carves it where it sees it.
        band_base_res: cells along the longest box axis of the narrow band's level 0.
        band_levels: 2x refinements of the band; None = :func:`auto_band_levels`.
        cell_px: auto levels: the finest cell projects to about this many pixels at the median view depth.
        max_band_res, min_band_res: auto levels give at most / at least this many cells along the longest axis.
        facet_frac: auto levels: the finest cell is no smaller than this fraction of the hull's facet width
            (:func:`hull_facet_m`; about 1 cm for a 4.5 cm glass seen by 9 views), whatever ``cell_px`` and
            ``min_band_res`` ask; 0 = off. With many views the pixel rule decides.
        max_band_cells: the band stops refining before its finest level would hold more surface cells than this
            (time and mesh size grow with them; the largest sim scene, syn12, needs 58k at 192 cells); None = no cap.
        band: cells within this many cell diagonals of the surface are refined.
        carve_res: voxels along the longest axis in ``"carve"`` mode.
        hull_mask_res: longest mask side (px) of the dense-grid hull (refinement path); 0 = full resolution
            (the consensus and the narrow band always use the full-resolution masks).
        refine_iters: DMTet refinement steps in fast mode (0 = the narrow-band hull, no refinement).
        refine_loss: loss of the refinement (``"robust"`` = per-view robust-weighted L2, or ``"init"``).
        refine_lr, refine_lr_min: refinement learning rates (cells per step).
        mask_res: longest side (px) of the masks supervising DMTet and of the fit evaluation on input views.
        min_component: components with fewer faces than this are dropped (specks).
        min_component_volume: components enclosing less than this volume (m^3) are dropped; so are inner
            cavities (components with negative signed volume).
        min_views_per_object: a component must lie in at least this many views; None = max(3, 20 % of them).
        points_per_object: surface samples per object point cloud.
        ignore_empty_views: leave out views whose mask is entirely empty when at most half the views are
            (a segmenter that found nothing in a view says nothing about where the objects are not).
        dmtet: the DMTet-Multi settings (paper mode; refinement overrides start/loss/iterations/lr).
        seed: seeds view sampling, the MLP and the surface sampling.
    """

    mode: Literal["fast", "paper", "carve"] = "fast"
    grid_res: int = 48
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    table_z: float | None = None
    no_table: bool = False
    vote_views: int | None = None
    vote_tolerance: float | None = None
    fine_vote_views: int | None = None
    repair_coverage: float = 0.5
    skip_cut_views: bool = False
    band_base_res: int = 24
    band_levels: int | None = None
    cell_px: float = 1.5
    max_band_res: int = 384
    min_band_res: int = 96
    max_band_cells: Annotated[int | None, Range(1, 10_000_000, "surface cells; ~0.5 kB each")] = 120_000
    facet_frac: float = 0.3
    band: float = 0.4
    carve_res: int = 128
    hull_mask_res: Annotated[int, Range(0, 4096, "mask side in px; cameras here are <= 1280 px")] = 0
    refine_iters: Annotated[int, Range(0, 100_000, "DMTet steps (~26 ms each on 2 cores)")] = 0
    refine_loss: Literal["robust", "init"] = "robust"
    refine_lr: float = 0.02
    refine_lr_min: float = 0.002
    mask_res: Annotated[int, Range(8, 4096, "mask side in px; cameras here are <= 1280 px")] = 256
    min_component: int = 20
    min_component_volume: float = 1e-7
    min_views_per_object: int | None = None
    points_per_object: Annotated[int, Range(1, 1 << 18, "128x the default; ~0.1 kB per point in the planner")] = 2048
    ignore_empty_views: bool = True
    dmtet: DMTetConfig = field(default_factory=DMTetConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        check_finite(self, "ReconstructionConfig")  # ranges and NaN / inf (torm.config), also when built in Python
        if self.mode not in MODES:
            raise ConfigError(f"ReconstructionConfig.mode={self.mode!r}; valid choices: {', '.join(MODES)}")
        if self.refine_loss not in ("robust", "init"):
            raise ConfigError(f"ReconstructionConfig.refine_loss={self.refine_loss!r}; valid choices: robust, init")
        if not 4 <= self.grid_res <= 256:
            raise ConfigError(f"ReconstructionConfig.grid_res must be in [4, 256] cells, got {self.grid_res}")
        if not (4 <= self.band_base_res <= self.max_band_res <= 2048 and 2 <= self.carve_res <= 1024
                and self.min_band_res <= self.max_band_res):
            raise ConfigError("ReconstructionConfig: need 4 <= band_base_res <= max_band_res <= 2048, "
                              "min_band_res <= max_band_res and carve_res in [2, 1024]")
        if self.bounds is not None:
            b = np.asarray(self.bounds, dtype=np.float64)
            if b.shape != (2, 3) or not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
                raise ConfigError(
                    "ReconstructionConfig.bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min"
                )
        if self.vote_tolerance is not None and not 0.0 <= self.vote_tolerance < 1.0:
            raise ConfigError(f"ReconstructionConfig.vote_tolerance must be in [0, 1), got {self.vote_tolerance}")
        if (self.vote_views is not None and self.vote_views < 0) or (self.fine_vote_views or 0) < 0:
            raise ConfigError("ReconstructionConfig: vote_views and fine_vote_views are view counts >= 0")
        if self.band_levels is not None and not 0 <= self.band_levels <= 6:
            raise ConfigError(f"ReconstructionConfig.band_levels must be in [0, 6] (or null), got {self.band_levels}")
        if not 0.0 <= self.facet_frac <= 4.0:
            raise ConfigError(f"ReconstructionConfig.facet_frac must be in [0, 4] (0 = off), got {self.facet_frac}")
        if not (self.cell_px > 0 and self.band > 0 and 0 < self.repair_coverage <= 1):
            raise ConfigError("ReconstructionConfig: cell_px > 0, band > 0 and repair_coverage in (0, 1] required")
        if self.hull_mask_res < 0 or (0 < self.hull_mask_res < 8) or self.mask_res < 8:
            raise ConfigError("ReconstructionConfig: mask_res >= 8 px and hull_mask_res 0 (full) or >= 8 px")
        if self.refine_iters < 0 or self.min_component < 0 or self.min_component_volume < 0:
            raise ConfigError("ReconstructionConfig: refine_iters, min_component and min_component_volume must be >= 0")
        if self.min_views_per_object is not None and self.min_views_per_object < 1:
            raise ConfigError("ReconstructionConfig.min_views_per_object must be >= 1 (or null for automatic)")
        if not (0 < self.refine_lr_min <= self.refine_lr):
            raise ConfigError("ReconstructionConfig: need 0 < refine_lr_min <= refine_lr")
        if self.points_per_object < 1:
            raise ConfigError("ReconstructionConfig.points_per_object must be >= 1")
        if self.no_table and self.table_z is not None:
            raise ConfigError("ReconstructionConfig: give either no_table=true or table_z, not both")


def mode_label(config: ReconstructionConfig) -> str:
    """The name of what runs, for tables and records: ``TORM-fast (...)``, ``TORM-paper (DMTet-Multi)``, ..."""
    if config.mode == "paper":
        return "TORM-paper (DMTet-Multi)"
    if config.mode == "carve":
        return f"voxel carve {config.carve_res}^3 (baseline)"
    if config.refine_iters > 0:
        return "TORM-fast (hull + DMTet refinement)"
    return "TORM-fast (consensus + narrow-band projective hull)"


# ----------------------------------------------------------------------------------------------------------
# Settings chosen from the capture
# ----------------------------------------------------------------------------------------------------------
def auto_vote_views(n_views: int) -> int:
    """Views that may disagree in the consensus hull: 0 below :data:`VOTE_MIN_VIEWS` views (every view must
    agree: with few views each one matters), else ``round(VOTE_FRACTION * n_views)``."""
    return 0 if n_views < VOTE_MIN_VIEWS else int(round(VOTE_FRACTION * n_views))


def fine_vote_candidates(n_views: int) -> tuple[int, ...]:
    """Tolerances (views) tried by the narrow-band hull: strict, and ``FINE_VOTE_FRACTION`` of the views
    from :data:`VOTE_MIN_VIEWS` views on."""
    return (0,) if n_views < VOTE_MIN_VIEWS else (0, max(1, int(round(FINE_VOTE_FRACTION * n_views))))


def view_depths(Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray, point_3: np.ndarray) -> np.ndarray:
    """(V,) camera z (m) of a world point in every view."""
    T_cw = np.linalg.inv(T_world_cam_vx4x4)
    return np.einsum("vj,j->v", T_cw[:, 2, :3], point_3) + T_cw[:, 2, 3]


def hull_facet_m(objects_points: list[np.ndarray], step_m: float, T_world_cam_vx4x4: np.ndarray) -> float:
    """Typical facet width (m) of the visual hull: the median over objects of ``r * delta``.

    ``r`` is the radius of the largest ball inside the object (the maximum of the Euclidean distance
    transform of its lattice points ``(P, 3)`` m, spacing ``step_m``, less half a step; a torus gives its
    tube's radius, a cup its outer radius as its hull fills the cavity) and ``delta`` (rad) the median angle
    between a view's direction from the object's centre and its
    nearest neighbour's. Two views ``delta`` apart bound a round cross-section of radius ``r`` by tangent
    planes that meet about ``r * delta`` apart: the hull is made of facets that wide, and silhouettes say
    nothing about the surface at a finer scale between views. 0.0 when there is no object or fewer than 2
    views.
    """
    C = np.asarray(T_world_cam_vx4x4, dtype=np.float64)[:, :3, 3]
    if len(C) < 2:
        return 0.0
    out = []
    for pts in objects_points:
        if len(pts) == 0:
            continue
        ijk = np.round((pts - pts.min(0)) / step_m).astype(np.int64) + 1
        occ = np.zeros(tuple(ijk.max(0) + 2), dtype=bool)
        occ[tuple(ijk.T)] = True
        r = step_m * (float(ndimage.distance_transform_edt(occ).max()) - 0.5)
        d = C - pts.mean(0)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        cos = d @ d.T
        np.fill_diagonal(cos, -1.0)
        out.append(r * float(np.median(np.arccos(np.clip(cos.max(1), -1.0, 1.0)))))
    return float(np.median(out)) if out else 0.0


def auto_band_levels(bounds_2x3: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray, base_res: int,
                     cell_px: float, max_res: int, min_res: int = 96, facet_cell_m: float = 0.0) -> int:
    """2x refinements so that the finest cell projects to about ``cell_px`` pixels at the median depth of the
    box centre, with at least ``min_res`` and at most ``max_res`` cells along the longest axis (the sub-cell
    accuracy of the projective SDF still pays below a pixel: 80 px masks, 16 views: input-view IoU 0.883 at
    48 cells, 0.914 at 96, 0.920 at 192); then no finer than ``facet_cell_m`` (m; ``facet_frac`` times
    :func:`hull_facet_m`), the scale below which few views carry no information, whatever the pixels say.
    Each bound rounds to the nearest level in log2 (a finest cell within sqrt(2) of the target)."""
    b = np.asarray(bounds_2x3, dtype=np.float64)
    z = view_depths(Ks_vx3x3, T_world_cam_vx4x4, b.mean(0))
    z = z[z > 1e-3]
    f = float(np.mean(Ks_vx3x3[:, [0, 1], [0, 1]]))
    base_cell = float((b[1] - b[0]).max()) / base_res
    target = cell_px * (float(np.median(z)) if len(z) else base_cell * f) / f
    lv = max(0, round(math.log2(max(base_cell / target, 1.0))))
    lv = max(lv, math.ceil(math.log2(max(min_res / base_res, 1.0))))
    if facet_cell_m > 0:
        lv = min(lv, max(0, round(math.log2(max(base_cell / facet_cell_m, 1.0)))))
    return int(min(lv, max(0, math.floor(math.log2(max_res / base_res)))))


def resolve_table(capture: Capture, config: ReconstructionConfig) -> float | None:
    """Table height (m) or None (no table plane): ``no_table`` > ``table_z`` > the capture's ``table_height``."""
    if config.no_table:
        return None
    if config.table_z is not None:
        return float(config.table_z)
    return None if capture.table_height is None else float(capture.table_height)


def resolve_bounds(capture: Capture, config: ReconstructionConfig, sil_vxhxw: np.ndarray, Ks: np.ndarray,
                   poses: np.ndarray, table_z: float | None, vote_views: int) -> tuple[np.ndarray, str]:
    """(box (2, 3) m, source): ``config.bounds`` > the capture's ``workspace_bounds`` > automatic."""
    if config.bounds is not None:
        b, src = np.asarray(config.bounds, dtype=np.float64), "config (ReconstructionConfig.bounds / --bounds)"
    elif capture.workspace_bounds is not None:
        b, src = np.asarray(capture.workspace_bounds, dtype=np.float64), "capture (workspace_bounds)"
    else:
        b = auto_bounds(sil_vxhxw, Ks, poses, table_z=table_z, vote_views=vote_views)
        src = "automatic (silhouette cones)"
    if table_z is not None and table_z >= b[1, 2]:
        raise ReconstructionError(
            f"the table plane z = {table_z} m lies above the reconstruction box {b.tolist()} ({src}); set the table "
            "height (table_height in transforms.json, ReconstructionConfig.table_z) or --no-table (table_height: null)"
        )
    return b, src


# ----------------------------------------------------------------------------------------------------------
# Input validation
# ----------------------------------------------------------------------------------------------------------
def validate_capture(capture: Capture) -> np.ndarray:
    """Check the masks and cameras as a whole and return the (V, H, W) int32 instance masks.

    Per-object problems (an object missing in many views, cut by the image border or the box) are not
    errors: they are checked on the reconstructed components and reported per object. Raises
    :class:`ReconstructionError` naming the view (index and name) and what to fix.
    """
    try:
        masks = capture.masks()
    except CaptureError as exc:
        raise ReconstructionError(f"cannot reconstruct: {exc}") from exc
    V, H, W = masks.shape
    if V < 2:
        raise ReconstructionError(f"need at least 2 views with masks to reconstruct, got {V}")
    for i, v in enumerate(capture.views):
        if not (np.all(np.isfinite(v.K)) and np.all(np.isfinite(v.T_world_cam))):
            raise ReconstructionError(f"view {i} ({v.name!r}): NaN/inf in K or the pose; fix the calibration")
        cx, cy = v.K[0, 2], v.K[1, 2]
        if not (0.0 < cx < W and 0.0 < cy < H):
            raise ReconstructionError(
                f"view {i} ({v.name!r}): the principal point ({cx:.1f}, {cy:.1f}) px lies outside the {W}x{H} mask; "
                "the intrinsics belong to another image size - rescale K or the masks"
            )
    if not masks.any():
        raise ReconstructionError(
            f"all {V} masks are empty: nothing to reconstruct; check the segmentation (prompts, thresholds)"
        )
    n_ids = [int(np.count_nonzero(np.bincount(m.ravel())[1:])) for m in masks[:: max(1, V // 8)]]
    if max(n_ids) > MAX_IDS_PER_VIEW:
        log.warning("a mask holds %d instance ids (more than %d): is it a soft (greyscale) mask read as ids? Only "
                    "the silhouettes (id > 0) shape the reconstruction", max(n_ids), MAX_IDS_PER_VIEW)
    return masks


# ----------------------------------------------------------------------------------------------------------
# Mesh post-processing
# ----------------------------------------------------------------------------------------------------------
def _split(mesh: TriMesh, config: ReconstructionConfig) -> tuple[list[TriMesh], int]:
    """Components without the small ones and inner cavities (negative signed volume: a bubble of "outside"
    inside an object, which silhouettes cannot observe); returns them and the number dropped."""
    comps = split_components(mesh.verts_vx3, mesh.faces_fx3)
    keep = [m for m in comps if len(m.faces_fx3) >= config.min_component
            and signed_volume(m.verts_vx3, m.faces_fx3) >= max(config.min_component_volume, 1e-300)]
    return keep, len(comps) - len(keep)


def _concat(meshes: list[TriMesh]) -> TriMesh:
    if not meshes:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    offs = np.cumsum([0] + [len(m.verts_vx3) for m in meshes])[:-1]
    return TriMesh(np.concatenate([m.verts_vx3 for m in meshes]),
                   np.concatenate([m.faces_fx3 + o for m, o in zip(meshes, offs, strict=True)]))


# ----------------------------------------------------------------------------------------------------------
# The modes
# ----------------------------------------------------------------------------------------------------------
def _consensus(sil, Ks, poses, bounds, table_z, vote, config, info, timings,
               unknown=None) -> tuple[np.ndarray, ProjectiveSDF]:
    """Fast mode, steps 1-2: consensus objects on the ``grid_res`` lattice, then the repaired silhouettes.

    Returns the repaired (V, H, W) silhouettes and their strict (``fine_vote_views``) projective SDF, which
    shares the distance transforms of the views the repair left alone. ``unknown`` ((V, H, W) bool or None):
    pixels without evidence, where a view abstains (:class:`ProjectiveSDF`).
    """
    t = time.perf_counter()
    field_ = ProjectiveSDF(sil, Ks, poses, roi_bounds_2x3=bounds, vote_views=vote, unknown_vxhxw=unknown)
    timings["distance_transforms"] = time.perf_counter() - t
    t = time.perf_counter()
    n = np.asarray(cells_per_axis(bounds, config.grid_res))
    step = (bounds[1] - bounds[0]) / n
    axes = [bounds[0][a] + (np.arange(n[a]) + 0.5) * step[a] for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    val, _ = field_(pts)
    if table_z is not None:
        val = np.maximum(val, table_z - pts[:, 2])
    objs = consensus_objects(val, pts, tuple(int(x) for x in n), float(step.max()))
    timings["consensus"] = time.perf_counter() - t
    if not objs:
        n_empty = int((~sil.reshape(len(sil), -1).any(axis=1)).sum())
        hint = (f"{n_empty} view(s) have entirely empty masks and carve everything (ignore_empty_views=true leaves "
                "them out); " if n_empty else "")
        raise ReconstructionError(
            f"nothing reconstructed: {hint}the masks' silhouette cones do not meet inside the reconstruction box "
            f"{np.round(bounds, 4).tolist()} ({info['bounds_source']}) even with {vote} dissenting views allowed; "
            f"check the camera poses, or the box: {BOUNDS_HINT} (or leave it unset for automatic bounds)")
    t = time.perf_counter()
    repaired, changed = repair_masks(sil, Ks, poses, objs, min_coverage=config.repair_coverage,
                                     skip_cut=config.skip_cut_views)
    fine = field_.derive(vote_views=config.fine_vote_views or 0, masks_vxhxw=repaired, changed_views=changed)
    timings["repair"] = time.perf_counter() - t
    info["consensus_objects"] = len(objs)
    info["hull_facet_m"] = hull_facet_m([o.points_px3 for o in objs], float(step.max()), poses)
    info["repaired_views"] = changed
    info["consensus_missing_views"] = [o.missing_views for o in objs]
    if changed:
        log.info("mask repair: %d view(s) whose mask missed a consensus object: %s", len(changed), changed[:10])
    return repaired, fine


def rim_miss_px(mesh: TriMesh, ev: _EvalViews, full_width: int) -> tuple[float, list[np.ndarray]]:
    """(Mean width (px of the full-resolution masks) of the silhouette rim the mesh's projection misses.

    Per evaluation view: silhouette pixels the rendered mesh does not cover, divided by the silhouette's
    boundary length (its pixels with a 4-neighbour outside), scaled to full resolution; mean over views.
    Consistent silhouettes are each exactly the projection of their strict visual hull, so for them this
    is a fraction of a pixel; eroded or dilated masks leave a rim of about their error. Also returns the
    renders (h, w) bool of the evaluation views.
    """
    h, w = ev.masks.shape[1:]
    out, renders = [], []
    for i in range(len(ev.K)):
        m = ev.masks[i] > 0.5
        r = render_mask_fast(mesh.verts_vx3, mesh.faces_fx3, ev.K[i], ev.T_cw[i], h, w)
        renders.append(r)
        if not m.any():
            continue
        inner = m.copy()
        inner[1:] &= m[:-1]
        inner[:-1] &= m[1:]
        inner[:, 1:] &= m[:, :-1]
        inner[:, :-1] &= m[:, 1:]
        out.append((m & ~r).sum() / max(int((m & ~inner).sum()), 1))
    return (float(np.mean(out)) * full_width / w if out else 0.0), renders


def _fast_band(fine: ProjectiveSDF, Ks, poses, bounds, table_z, config, ev, W_full, info, timings) -> TriMesh:
    levels = config.band_levels
    if levels is None:
        levels = auto_band_levels(bounds, Ks, poses, config.band_base_res, config.cell_px, config.max_band_res,
                                  config.min_band_res, config.facet_frac * info.get("hull_facet_m", 0.0))
    tols = (config.fine_vote_views,) if config.fine_vote_views is not None else fine_vote_candidates(len(Ks))
    t = time.perf_counter()
    meshes, grid = narrow_band_hull(fine, bounds, config.band_base_res, levels, table_z=table_z, band=config.band,
                                    tolerances=tols, max_cells=config.max_band_cells)
    timings["narrow_band"] = time.perf_counter() - t - grid.stats["marching_tets_s"]
    timings["marching_tets"] = grid.stats["marching_tets_s"]
    best = 0
    if len(meshes) > 1:
        t = time.perf_counter()
        miss, strict_renders = rim_miss_px(meshes[0], ev, W_full)
        # strict unless its projection misses a rim wider than RIM_TOL_PX: then the masks disagree (eroded/dilated)
        best = 1 if miss > RIM_TOL_PX else 0
        ev.renders = strict_renders if best == 0 else []
        info["strict_rim_miss_px"] = miss
        timings["select_tolerance"] = time.perf_counter() - t
    info.update(band_levels=grid.stats["levels_used"], band_levels_planned=levels, fine_vote_views=tols[best],
                grid_cells=list(grid.res), grid_verts=grid.n_verts,
                band_cells=len(grid.cells_cx3), cell_m=float(grid.cell_size.max()), band_stats=grid.stats)
    return meshes[best]


def _dense_grid_modes(sil, Ks, poses, bounds, table_z, vote, config, info, timings, history,
                      unknown=None) -> TriMesh:
    """Fast mode with DMTet refinement, or paper mode, on the dense grid_res tet grid.

    ``sil`` counts no-evidence pixels (``unknown``, (V, H, W) bool or None) as inside, which is right for the hull
    (they never carve); DMTet's mask loss gives them weight 0 instead (they pull neither way)."""
    t = time.perf_counter()
    grid = build_tet_grid(bounds, config.grid_res)
    timings["grid"] = time.perf_counter() - t
    info.update(grid_cells=list(grid.res), grid_verts=grid.n_verts, cell_m=float(grid.cell_size.max()))
    T_cw = np.linalg.inv(poses)
    sup_masks, sup_K = downsample_masks(sil if unknown is None else sil & ~unknown, Ks, config.mask_res)
    weights = None if unknown is None else downsample_masks(~unknown, Ks, config.mask_res)[0]
    if config.mode == "fast":
        t = time.perf_counter()
        if config.hull_mask_res:
            hull_masks, hull_K = downsample_masks(sil, Ks, config.hull_mask_res)
            hull_masks = hull_masks >= 0.5
        else:
            hull_masks, hull_K = sil, Ks
        vt = {"vote_tol": config.vote_tolerance} if config.vote_tolerance is not None else {"vote_views": vote}
        sdf = visual_hull_sdf(hull_masks, hull_K, poses, grid, table_z=table_z, workspace_bounds_2x3=bounds, **vt)
        timings["visual_hull"] = time.perf_counter() - t
        dcfg = replace(config.dmtet, param="vertex", start="hull", loss=config.refine_loss,
                       iterations=config.refine_iters, lr=config.refine_lr, lr_min=config.refine_lr_min,
                       alpha_max=1.0, alpha_min=1.0, mask_res=config.mask_res, seed=config.seed)
        res = optimise_dmtet(grid, sup_K, T_cw, sup_masks, dcfg, init_sdf_v=sdf.numpy(), table_z=table_z,
                             weights_vxhxw=weights)
    else:
        dcfg = replace(config.dmtet, start="sphere", mask_res=config.mask_res, seed=config.seed)
        res = optimise_dmtet(grid, sup_K, T_cw, sup_masks, dcfg, table_z=table_z, weights_vxhxw=weights)
    history.update(res.history)
    timings["dmtet"] = res.timings["total_s"]
    info["dmtet_ms_per_step"] = res.timings["ms_per_step"]
    info["dmtet_timings"] = res.timings
    h = res.history
    info["empty_steps"] = int(h.get("empty_steps", [0])[0])
    info["rescued_steps"] = int(h.get("rescued_steps", [0])[0])
    info["collapsed_at"] = int(h.get("collapsed_at", [-1])[0])
    if "full_passes" in h:
        bv = h.get("band_verts", [])
        info["dmtet_band"] = {"full_passes": int(h["full_passes"][0]), "band_misses": int(h["band_misses"][0]),
                              "band_verts_mean": float(np.mean(bv)) if len(bv) else None}
    return res.mesh


def _carve(sil, Ks, poses, bounds, table_z, config, info, timings) -> TriMesh:
    t = time.perf_counter()
    r = carve_visual_hull(sil, Ks, poses, bounds, config.carve_res, table_z=table_z)
    timings["carve"] = time.perf_counter() - t
    info.update(grid_cells=list(r.occupancy.shape), cell_m=r.pitch)
    return r.mesh


# ----------------------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------------------
def reconstruct(capture: Capture, config: ReconstructionConfig | None = None) -> Reconstruction:
    """Reconstruct every object seen in the capture's silhouettes (instance mask > 0).

    Returns a :class:`Reconstruction` whose ``timings`` hold seconds per stage, whose ``history`` holds the
    DMTet curves (empty without DMTet) and whose ``info`` has the mode's name (``mode_label``), the box and
    its source, the table, the settings chosen from the capture, the fit on the input views
    (``silhouette_iou_mean``/``_min``, at ``mask_res``), ``rejected_objects`` (components that failed a check,
    with the reason) and ``unexplained_views`` (views whose silhouette holds a region no object covers).

    Raises:
        ReconstructionError: inconsistent inputs (named view and reason), a box/table problem (naming the key
            or flag to set), or no object reconstructed at all.
    """
    config = config or ReconstructionConfig()
    threads = configure_threads()
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    t = time.perf_counter()
    inst = validate_capture(capture)
    unknown = no_evidence_masks(capture)  # (V, H, W) bool or None: pixels without a source after undistortion
    Ks, poses = capture.Ks(), capture.poses()
    # A view whose mask is entirely empty while most views see objects is a segmenter miss, not evidence that
    # the workspace is empty: with one object in the scene, such views alone could carve it away.
    empty = ~inst.reshape(len(inst), -1).any(axis=1)
    ignored = np.flatnonzero(empty).tolist() if config.ignore_empty_views and empty.sum() <= len(inst) // 2 else []
    if ignored:
        log.info("ignoring %d view(s) with empty masks: %s", len(ignored), ignored[:10])
        keep = np.flatnonzero(~empty)
        inst, Ks, poses = inst[keep], Ks[keep], poses[keep]
        unknown = None if unknown is None else unknown[keep]
    # A pixel without evidence says nothing, like a point outside the image (visual_hull's outside_image="unknown"):
    # for the intersection of silhouette cones that is "inside" (it never carves); the fit ignores those pixels.
    sil = inst > 0 if unknown is None else (inst > 0) | unknown
    V = len(sil)
    vote = config.vote_views if config.vote_views is not None else auto_vote_views(V)
    if config.vote_tolerance is not None:
        vote = int(math.floor(config.vote_tolerance * V))
    table_z = resolve_table(capture, config)
    timings["validate"] = time.perf_counter() - t
    t = time.perf_counter()
    # the automatic box closes the silhouette cones around what the masks show: no-evidence pixels (the border an
    # undistortion leaves) are not object there, or every cone would touch the image border
    bounds, bounds_src = resolve_bounds(capture, config, inst > 0, Ks, poses, table_z, vote)
    timings["bounds"] = time.perf_counter() - t
    info: dict = {"mode": config.mode, "mode_label": mode_label(config), "threads": threads,
                  "bounds": bounds.tolist(), "bounds_source": bounds_src, "table_z": table_z, "n_views": V,
                  "vote_views": vote, "ignored_empty_views": ignored}
    log.info("reconstruct: %s, %d views, box %s (%s), %s, vote tolerance %d views, %d torch thread(s)",
             info["mode_label"], V, np.round(bounds, 3).tolist(), bounds_src,
             "no table" if table_z is None else f"table z = {table_z} m", vote, threads)
    history: dict[str, list[float]] = {}
    idx = np.unique(np.linspace(0, V - 1, min(V, EVAL_VIEWS)).round().astype(np.int64))
    ev_unknown = None
    if unknown is None:
        sup, sup_K = downsample_masks(sil[idx], Ks[idx], config.mask_res)
    else:
        sup, sup_K = downsample_masks(sil[idx] & ~unknown[idx], Ks[idx], config.mask_res)
        ev_unknown = downsample_masks(unknown[idx], Ks[idx], config.mask_res)[0] > 0.0
        sup[ev_unknown] = 0.0
        info["no_evidence_px"] = int(unknown.sum())
    ev = _EvalViews(idx, sup, sup_K, np.linalg.inv(poses[idx]), unknown=ev_unknown)
    if config.mode == "carve":
        mesh = _carve(sil, Ks, poses, bounds, table_z, config, info, timings)
    else:
        repaired, fine = _consensus(sil, Ks, poses, bounds, table_z, vote, config, info, timings, unknown)
        if config.mode == "fast" and config.refine_iters == 0:
            mesh = _fast_band(fine, Ks, poses, bounds, table_z, config, ev, sil.shape[2], info, timings)
        else:
            mesh = _dense_grid_modes(repaired if config.mode == "fast" else sil, Ks, poses, bounds, table_z, vote,
                                     config, info, timings, history, unknown)
    if mesh.is_empty:
        collapsed = info.get("collapsed_at", -1)
        vanished = (f" (DMTet-Multi's mesh vanished at step {collapsed}; DMTetConfig.rescue re-seeds it "
                    "from the silhouettes, which the paper does not)") if collapsed >= 0 else ""
        raise ReconstructionError(
            "no object reconstructed: the final mesh is empty" + vanished + "; check masks/cameras (poses, intrinsics, "
            f"mask ids) and the reconstruction box {np.round(bounds, 4).tolist()} ({bounds_src}); {BOUNDS_HINT}")

    t = time.perf_counter()
    comps, dropped = _split(mesh, config)
    H, W = sil.shape[1:]
    n_min = config.min_views_per_object or max(3, math.ceil(0.2 * V))
    checks = check_objects(comps, Ks, poses, (H, W), bounds, min_views=n_min, box_tol=0.75 * info["cell_m"],
                           floor_z=table_z, unknown_vxhxw=unknown)
    objects = [m for m, c in zip(comps, checks, strict=True) if c["ok"]]
    info["rejected_objects"] = [c for c in checks if not c["ok"]]
    info["dropped_components"] = dropped
    info["min_views_per_object"] = n_min
    for c in info["rejected_objects"]:
        log.warning("object at %s not reconstructed: %s", np.round(c["centroid"], 3).tolist(), c["reason"])
    timings["checks"] = time.perf_counter() - t
    if not objects:
        why = "; ".join(c["reason"] for c in info["rejected_objects"][:3])
        raise ReconstructionError(
            f"no object reconstructed: {len(comps)} component(s) found, none passed the checks"
            + (f" ({why})" if why else f" (all below min_component={config.min_component} faces / "
               f"{config.min_component_volume} m^3)") + "; check masks/cameras")

    t = time.perf_counter()
    h, w = ev.masks.shape[1:]
    scene = _concat(objects)
    if ev.renders and not info["rejected_objects"] and not dropped:
        renders = np.stack(ev.renders)  # the selected mesh was rendered already and every component was kept
    else:
        renders = np.stack([render_mask_fast(scene.verts_vx3, scene.faces_fx3, ev.K[i], ev.T_cw[i], h, w)
                            for i in range(len(ev.K))])
    if ev.unknown is not None:  # pixels without evidence count neither way
        renders = renders & ~ev.unknown
    ious = [silhouette_iou(r, m) for r, m in zip(renders, ev.masks, strict=True)]
    info["silhouette_iou_mean"] = float(np.mean(ious))
    info["silhouette_iou_min"] = float(np.min(ious))
    info["silhouette_iou_views"] = f"{len(ev.K)} of the {V} input views (the fit, not a held-out score)"
    unexplained = unexplained_views(ev.masks > 0.5, renders, max(9, int(2e-3 * h * w)))
    info["unexplained_views"] = sorted(int(ev.index[i]) for i in unexplained)
    if unexplained:
        log.warning("in %d of %d views a silhouette region is covered by no reconstructed object (e.g. views %s): "
                    "an object other views' masks carved away (missed by the segmenter there?) or outside the box",
                    len(unexplained), V, sorted(unexplained)[:8])
    timings["evaluate"] = time.perf_counter() - t

    t = time.perf_counter()
    clouds: tuple[ObjectPointCloud, ...] = sample_objects(objects, config.points_per_object,
                                                         np.random.default_rng(config.seed))
    timings["sample"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    log.info("reconstruct (%s): %d objects (%d rejected), input-view IoU %.3f, %.2f s", info["mode_label"],
             len(objects), len(info["rejected_objects"]), info["silhouette_iou_mean"], timings["total"])
    return Reconstruction(scene_mesh=scene, object_meshes=tuple(objects), point_clouds=clouds,
                          timings=timings, history=history, info=info)


__all__ = ["DEFAULT_BOUNDS", "MODES", "ReconstructionConfig", "auto_band_levels", "auto_vote_views",
           "fine_vote_candidates", "hull_facet_m", "mode_label",
           "reconstruct", "resolve_bounds", "resolve_table", "validate_capture"]
