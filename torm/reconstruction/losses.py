"""Losses of DMTet-Multi (TORM, Sec. III-B): mask losses (1)-(2), the alpha schedule (3), eikonal (4),
plus a robust per-view weighting used when refining a visual hull against imperfect masks.

Mask tensors are (..., H, W) coverage in [0, 1]; the leading dims are views. Per-view functions
return one value per view so that eq. (5) (sum over the N_view views of a batch) is the caller's sum.
"""

from __future__ import annotations

import torch

from torm.errors import ConfigError


def mask_loss_init(pred_vxhxw: torch.Tensor, target_vxhxw: torch.Tensor,
                   weight_vxhxw: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. (1): per-view mean over pixels of (M_hat - M)^2; shape (V,) (or () for a single (H, W) image).

    ``weight_vxhxw`` (same shape, in [0, 1]): each pixel's weight; 0 where a pixel holds no evidence (no source
    after undistortion: the view abstains there), so neither the object nor the background is pulled there."""
    sq = (pred_vxhxw - target_vxhxw) ** 2
    return (sq if weight_vxhxw is None else sq * weight_vxhxw).mean(dim=(-2, -1))


def envelope_mask_loss(pred_vxhxw: torch.Tensor, target_vxhxw: torch.Tensor, alpha: float,
                       weight_vxhxw: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. (2): per-view mean of (M_hat - alpha * M)^2. alpha > 1 pulls outward harder on object pixels.
    ``weight_vxhxw``: per-pixel weights as in :func:`mask_loss_init` (the slow reference of the sparse path)."""
    sq = (pred_vxhxw - alpha * target_vxhxw) ** 2
    return (sq if weight_vxhxw is None else sq * weight_vxhxw).mean(dim=(-2, -1))


def envelope_mask_loss_sparse(hard_vxhxw: torch.Tensor, pix_n: torch.Tensor, delta_n: torch.Tensor,
                              target_vxhxw: torch.Tensor, alpha: float,
                              weight_vxhxw: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. (2) (eq. (1) with ``alpha = 1``) of the prediction ``hard + delta at pix``, shape (V,), with a graph
    only through ``delta_n``: the value and gradient of :func:`envelope_mask_loss` on the dense prediction (up to
    float rounding) at a cost in proportion to N, not V x H x W.

    Args:
        hard_vxhxw: (V, H, W) prediction without gradient (e.g. a hard 0/1 silhouette).
        pix_n: (N,) int64 distinct flat indices into the V x H x W pixels (``(view * H + row) * W + column``).
        delta_n: (N,) the prediction minus ``hard`` at those pixels (differentiable).
        target_vxhxw: (V, H, W) target masks in [0, 1].
        alpha: the envelope coefficient of eq. (2).
        weight_vxhxw: optional (V, H, W) per-pixel weights (:func:`mask_loss_init`; 0 = no evidence).

    Per pixel, (h + d - a t)^2 = (h - a t)^2 + d (2 (h - a t) + d): the first term is summed over every pixel
    without a graph, the second over the N pixels.
    """
    V, H, W = target_vxhxw.shape
    with torch.no_grad():
        sq = (hard_vxhxw - alpha * target_vxhxw) ** 2
        base = (sq if weight_vxhxw is None else sq * weight_vxhxw).sum(dim=(-2, -1))
        r0 = (hard_vxhxw.reshape(-1)[pix_n] - alpha * target_vxhxw.reshape(-1)[pix_n]).to(delta_n.dtype)
    extra = delta_n * (2.0 * r0 + delta_n)
    if weight_vxhxw is not None:
        extra = extra * weight_vxhxw.reshape(-1)[pix_n].to(delta_n.dtype)
    per_view = torch.zeros(V, dtype=delta_n.dtype, device=delta_n.device).index_add(0, pix_n // (H * W), extra)
    return (base.to(delta_n.dtype) + per_view) / (H * W)


def alpha_schedule(t: float, alpha_max: float = 3.0, alpha_min: float = 1.0, T: float = 500.0) -> float:
    """Eq. (3): alpha_max - (alpha_max - alpha_min) * t / T for 0 <= t < T, then alpha_min.

    ``t`` is the iteration (>= 0) and ``T`` the decay duration in iterations (> 0).
    """
    if T <= 0:
        raise ConfigError(f"alpha_schedule: the decay duration T must be > 0, got {T}")
    if t < 0:
        raise ConfigError(f"alpha_schedule: the iteration t must be >= 0, got {t}")
    if t >= T:
        return float(alpha_min)
    return float(alpha_max - (alpha_max - alpha_min) / T * t)


def zero_crossing_edges(sdf_v: torch.Tensor, edges_ex2: torch.Tensor) -> torch.Tensor:
    """(K, 2) edges whose endpoint SDFs have different signs (s == 0 counts as outside, like marching tets)."""
    inside = sdf_v < 0
    return edges_ex2[inside[edges_ex2[:, 0]] != inside[edges_ex2[:, 1]]]


def eikonal_loss_edges(sdf_v: torch.Tensor, verts_vx3: torch.Tensor, edges_ex2: torch.Tensor) -> torch.Tensor:
    """Eq. (4) for per-vertex SDF values: mean over zero-crossing edges of (|grad s| - 1)^2.

    Discretisation: on a crossing edge (i, j) the SDF is linear between the deformed vertices v'_i and
    v'_j, so the directional derivative along the edge, |s_i - s_j| / |v'_i - v'_j|, estimates |grad s| at
    the crossing point v_0 (exact when the edge is parallel to the gradient, a lower bound otherwise).
    ``sdf_v`` and ``verts_vx3`` must use the same length unit. Returns 0 (with a graph) when no edge
    crosses zero.
    """
    e = zero_crossing_edges(sdf_v, edges_ex2)
    if len(e) == 0:
        return sdf_v.sum() * 0.0
    ds = (sdf_v[e[:, 0]] - sdf_v[e[:, 1]]).abs()
    dl = (verts_vx3[e[:, 0]] - verts_vx3[e[:, 1]]).norm(dim=1).clamp_min(1e-12)
    return ((ds / dl - 1.0) ** 2).mean()


def zero_crossing_points(sdf_v: torch.Tensor, verts_vx3: torch.Tensor, edges_ex2: torch.Tensor) -> torch.Tensor:
    """The paper's v_0 = (v'_i s_j - v'_j s_i) / (s_j - s_i) on every zero-crossing edge, (K, 3)."""
    e = zero_crossing_edges(sdf_v, edges_ex2)
    si, sj = sdf_v[e[:, 0], None], sdf_v[e[:, 1], None]
    return (verts_vx3[e[:, 0]] * sj - verts_vx3[e[:, 1]] * si) / (sj - si)


def eikonal_loss_grad(grad_kx3: torch.Tensor) -> torch.Tensor:
    """Eq. (4) from explicit SDF gradients at the zero-crossing points (e.g. an MLP's autograd gradient)."""
    if len(grad_kx3) == 0:
        return grad_kx3.sum() * 0.0
    return ((grad_kx3.norm(dim=1) - 1.0) ** 2).mean()


def robust_view_weights(per_view_loss_v: torch.Tensor, kind: str = "mad", c: float = 3.0) -> torch.Tensor:
    """Per-view weights in (0, 1] that down-weight views whose loss is an outlier (no gradient).

    ``kind="mad"``: r = (l - median) / (1.4826 * MAD); weight 1 for r <= c, else c / r (Huber weight,
    only views worse than typical are down-weighted). ``kind="gm"``: Geman-McClure weight
    1 / (1 + (r / c)^2)^2 on r = max(l - median, 0) / (1.4826 * MAD). With fewer than 3 views, or a
    MAD of 0, every weight is 1. Use it as ``(weights * per_view_loss).sum()``.
    """
    if kind not in ("mad", "gm"):
        raise ConfigError(f"robust_view_weights: kind must be 'mad' or 'gm', got {kind!r}")
    lv = per_view_loss_v.detach()
    w = torch.ones_like(lv)
    if lv.numel() < 3:
        return w
    med = lv.median()
    scale = 1.4826 * (lv - med).abs().median()
    if float(scale) <= 1e-12:
        return w
    r = (lv - med).clamp_min(0.0) / scale
    if kind == "mad":
        return torch.where(r <= c, w, c / r.clamp_min(1e-12))
    return 1.0 / (1.0 + (r / c) ** 2) ** 2
