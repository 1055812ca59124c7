"""DMTet-Multi reconstruction: tet grid, marching tetrahedra, visual hull, silhouette rasteriser, optimiser.

Entry point: :func:`reconstruct` (a :class:`torm.types.Capture` with masks -> :class:`torm.types.Reconstruction`)
configured by :class:`ReconstructionConfig` (``mode="fast"``: TORM-fast, consensus + narrow-band projective hull;
``"paper"``: TORM-paper, DMTet-Multi; ``"carve"``: the voxel-carve baseline); :func:`mode_label` names what runs.
"""

from torm.reconstruction.adaptive_grid import narrow_band_hull
from torm.reconstruction.api import ReconstructionConfig, mode_label, reconstruct
from torm.reconstruction.bounds import auto_bounds
from torm.reconstruction.carve import carve_visual_hull
from torm.reconstruction.dmtet import DMTetConfig, DMTetResult, optimise_dmtet
from torm.reconstruction.losses import (
    alpha_schedule,
    eikonal_loss_edges,
    envelope_mask_loss,
    envelope_mask_loss_sparse,
    mask_loss_init,
    robust_view_weights,
)
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.raster import (
    SparseSilhouettes,
    render_depth,
    render_mask,
    render_silhouette,
    render_silhouettes,
    render_silhouettes_sparse,
)
from torm.reconstruction.tetgrid import TetGrid, build_tet_grid
from torm.reconstruction.visual_hull import ProjectiveSDF, visual_hull_sdf

__all__ = [
    "DMTetConfig",
    "ProjectiveSDF",
    "auto_bounds",
    "carve_visual_hull",
    "mode_label",
    "narrow_band_hull",
    "DMTetResult",
    "ReconstructionConfig",
    "SparseSilhouettes",
    "TetGrid",
    "alpha_schedule",
    "build_tet_grid",
    "eikonal_loss_edges",
    "envelope_mask_loss",
    "envelope_mask_loss_sparse",
    "mask_loss_init",
    "marching_tets",
    "optimise_dmtet",
    "reconstruct",
    "render_depth",
    "render_mask",
    "render_silhouette",
    "render_silhouettes",
    "render_silhouettes_sparse",
    "robust_view_weights",
    "visual_hull_sdf",
]
