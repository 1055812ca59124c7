"""Checks on a plug-in's output before the planner sees it: each failure is a PluginError naming the plug-in,
the object and what to fix (shapes, NaNs, points outside the workspace, millimetres, a camera frame)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from torm.errors import PluginError
from torm.methods.interface import ObjectEstimate

#: fewest points an object estimate may have
MIN_POINTS = 10
#: how far (m) outside the workspace box points may lie before the output is refused
WORKSPACE_MARGIN_M = 0.10


def validate_estimates(method: str, estimates: Any, workspace_bounds_2x3: np.ndarray,
                       margin_m: float = WORKSPACE_MARGIN_M) -> list[ObjectEstimate]:
    """``estimates`` as a list of :class:`ObjectEstimate`, or a :class:`PluginError` naming ``method``."""
    if not isinstance(estimates, Sequence) or isinstance(estimates, (str, bytes, np.ndarray)):
        raise PluginError(f"method {method!r}: perceive() returned {type(estimates).__name__}; return a list of "
                          "torm.methods.ObjectEstimate (an empty list when it found nothing)")
    lo, hi = np.asarray(workspace_bounds_2x3, np.float64)
    out = []
    for k, e in enumerate(estimates):
        where = f"method {method!r}, object {k}"
        if not isinstance(e, ObjectEstimate):
            raise PluginError(f"{where}: {type(e).__name__} is not a torm.methods.ObjectEstimate")
        p = np.asarray(e.points_nx3)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < MIN_POINTS:
            raise PluginError(f"{where}: points_nx3 has shape {p.shape}; need (N, 3) with N >= {MIN_POINTS}")
        if not np.all(np.isfinite(p)):
            raise PluginError(f"{where}: {int((~np.isfinite(p)).any(axis=1).sum())} point(s) are NaN or inf; drop "
                              "pixels without depth before back-projecting")
        if e.normals_nx3 is not None:
            n = np.asarray(e.normals_nx3)
            if n.shape != p.shape or not np.all(np.isfinite(n)):
                raise PluginError(f"{where}: normals_nx3 has shape {n.shape} (points {p.shape}) or non-finite values")
            if np.any(np.linalg.norm(n, axis=1) < 1e-6):
                raise PluginError(f"{where}: some normals are zero vectors; give unit normals or None")
        if not 0.0 <= float(e.confidence) <= 1.0:
            raise PluginError(f"{where}: confidence {e.confidence} must lie in [0, 1]")
        extent = float(np.ptp(p, axis=0).max())
        if extent > 2.0:
            raise PluginError(f"{where}: the object spans {extent:.1f} units; the harness works in metres (points "
                              "in millimetres?)")
        outside = np.mean(np.any((p < lo - margin_m) | (p > hi + margin_m), axis=1))
        if outside > 0.5:
            c = p.mean(axis=0)
            raise PluginError(f"{where}: {100 * outside:.0f} % of its points lie outside the workspace "
                              f"{lo.round(2).tolist()}..{hi.round(2).tolist()} m (centre {c.round(3).tolist()}): "
                              "points must be in the world frame (robot base), not a camera frame")
        out.append(e)
    return out
