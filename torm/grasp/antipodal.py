"""Antipodal grasp candidates for all objects in one vectorised pass.

Contact search. For every object, ``n_samples`` surface points ``p1`` (outward normal ``n1``) are drawn.
The opposite contact ``p2`` lies where the line ``p1 - s n1`` (s > 0) first leaves the object:

* with a mesh: exact ray casting against the object's triangles (:mod:`torm.grasp.raycast`: candidate faces
  from a KD-tree over face centroids, then a vectorised numpy Moller-Trumbore test; the first hit on a face
  whose normal points along the ray);
* without a mesh: among the object's points within ``search_radius`` of that line, ahead of ``p1`` and
  with a normal facing away from ``n1`` (an exit surface), the one closest along the line. This runs on
  the stacked (n_obj, N, 3) arrays for all objects at once (one compiled numba loop, no BLAS threads).

With ``far_contacts`` each p1 is also paired with the *last* exit within the stroke when that is a different
surface (farther than ``2 * search_radius`` beyond the first): for a hollow object (a cup) the first exit is
the inner face of the near wall, the last one the outer face of the far wall, i.e. a grasp across the cup.

A pair is kept when both normals lie inside the friction cone (half-angle ``atan(mu)``) of the closing
axis ``y = normalise(n2 - n1)`` (equal to ``-n1`` for an exactly antipodal pair), the contact distance
``(p2 - p1) . y`` is within the stroke (minus a small margin) and the pads can touch both contacts
(lateral offset of ``p2`` from the closing line below ``lateral_tolerance``).

Grasp enumeration. Each pair gives ``n_angles`` approach directions ``x`` perpendicular to ``y``
(rotations about ``y`` starting from the most top-down one, ``-z_world`` projected); approaches tilted
more than ``max_tilt`` from straight down are dropped. ``z = x cross y`` (right-handed). The grasp centre
is the contacts' midpoint and each approach is repeated for several GraspNet depths (fingertip position
along ``x`` beyond the centre): shallow depths grasp with the fingertips, deep ones with the whole pad.
Sampling contacts over the whole surface gives candidates at every height of a tall object (a height
sweep); the depth variants add a sweep along the approach axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from torm.grasp.gripper import GripperGeometry
from torm.grasp.raycast import exit_hits
from torm.types import TriMesh

_EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class ContactPairs:
    """Antipodal contact pairs (P of them) of all objects; arrays in metres, world frame.

    ``obj`` (P,) is the position of the object in the input list; ``p1, p2`` (P, 3) contacts; ``n1, n2``
    (P, 3) outward unit normals; ``y`` (P, 3) unit closing axis from p1 to p2; ``dist`` (P,) contact
    distance along y; ``quality`` (P,) antipodal quality in [0, 1] (1 = normals exactly along y).
    """

    obj: np.ndarray
    p1: np.ndarray
    n1: np.ndarray
    p2: np.ndarray
    n2: np.ndarray
    y: np.ndarray
    dist: np.ndarray
    quality: np.ndarray

    def __len__(self) -> int:
        return len(self.obj)


@dataclass(frozen=True, eq=False)
class GraspCandidates:
    """Grasp candidates (C of them): ``obj`` (C,) object position, ``R`` (C, 3, 3) columns x (approach), y
    (closing), z; ``t`` (C, 3) grasp centre (m); ``width`` (C,) opening (m); ``depth`` (C,) fingertip
    position along x (m); ``contact_dist`` (C,) m; ``antipodal`` (C,) quality in [0, 1]; ``pair`` (C,) index of
    the contact pair a candidate came from (candidates of one pair share centre, closing axis and width), or
    None (every candidate its own pair)."""

    obj: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: np.ndarray
    depth: np.ndarray
    contact_dist: np.ndarray
    antipodal: np.ndarray
    pair: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.obj)

    def take(self, idx: np.ndarray) -> GraspCandidates:
        """The candidates at ``idx`` (indices or a boolean mask)."""
        return GraspCandidates(*(getattr(self, f)[idx] for f in
                                 ("obj", "R", "t", "width", "depth", "contact_dist", "antipodal")),
                               pair=None if self.pair is None else self.pair[idx])


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-12)


@numba.njit(cache=True, nogil=True)
def _exit_points(points, normals, p1, n1, r2, t_min, t_max):  # pragma: no cover - compiled
    K, S = p1.shape[0], p1.shape[1]
    N = points.shape[1]
    first = np.full((K, S), -1, dtype=np.int64)
    last = np.full((K, S), -1, dtype=np.int64)
    t_first = np.full((K, S), np.inf)
    t_last = np.full((K, S), -np.inf)
    for k in range(K):
        for s in range(S):
            ax, ay, az = p1[k, s, 0], p1[k, s, 1], p1[k, s, 2]
            bx, by, bz = n1[k, s, 0], n1[k, s, 1], n1[k, s, 2]
            for i in range(N):
                if normals[k, i, 0] * bx + normals[k, i, 1] * by + normals[k, i, 2] * bz >= 0.0:
                    continue  # not an exit surface for a line running along -n1
                dx = points[k, i, 0] - ax
                dy = points[k, i, 1] - ay
                dz = points[k, i, 2] - az
                along = -(dx * bx + dy * by + dz * bz)
                if along <= t_min or along > t_max:
                    continue
                if dx * dx + dy * dy + dz * dz - along * along < r2:
                    if along < t_first[k, s]:
                        t_first[k, s] = along
                        first[k, s] = i
                    if along > t_last[k, s]:
                        t_last[k, s] = along
                        last[k, s] = i
    return first, last, t_first, t_last


def _opposite_by_points(points: np.ndarray, normals: np.ndarray, p1: np.ndarray, n1: np.ndarray,
                        search_radius: float, t_min: float, t_max: float,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Opposite contacts from the points: points (K, N, 3), normals (K, N, 3), p1/n1 (K, S, 3).

    Among the exit-facing points within ``search_radius`` of the line and within ``(t_min, t_max]`` along
    it, the closest (first exit) and the farthest (last exit). Returns p2_first, n2_first, p2_last, n2_last
    (K, S, 3) (NaN where none) and the (K, S) distance between the two exits along the line (m). One
    compiled loop over all objects, samples and points.
    """
    first, last, t_first, t_last = _exit_points(
        np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
        np.ascontiguousarray(p1, dtype=np.float64), np.ascontiguousarray(n1, dtype=np.float64),
        float(search_radius) ** 2, float(t_min), float(t_max))
    kk = np.arange(points.shape[0])[:, None]
    out = []
    for best in (first, last):
        found = best >= 0
        j = np.where(found, best, 0)
        out.append(np.where(found[..., None], points[kk, j], np.nan))
        out.append(np.where(found[..., None], normals[kk, j], np.nan))
    gap = np.where(first >= 0, t_last - t_first, 0.0)
    return out[0], out[1], out[2], out[3], gap


def sample_contact_pairs(
    points_kxnx3: np.ndarray,
    normals_kxnx3: np.ndarray,
    meshes: Sequence[TriMesh | None] | None,
    *,
    n_samples: int,
    friction_coef: float,
    min_dist: float,
    max_dist: float,
    search_radius: float,
    lateral_tolerance: float,
    rng: np.random.Generator,
    far_contacts: bool = True,
) -> ContactPairs:
    """Antipodal contact pairs of every object (see the module docstring).

    Args:
        points_kxnx3, normals_kxnx3: stacked object clouds (K objects, N points each), m / unit outward.
        meshes: per-object meshes (None entries or None: search the points instead of ray casting).
        n_samples: contacts p1 drawn per object (without replacement when N allows).
        friction_coef: Coulomb friction coefficient mu; cone half-angle atan(mu).
        min_dist, max_dist: accepted contact distance range (m).
        search_radius: radius (m) around the line p1 - s n1 for the point search.
        lateral_tolerance: largest offset (m) of p2 from the closing line through p1.
        rng: random generator for the contact sampling.
        far_contacts: also pair p1 with the last exit within ``max_dist`` when it lies beyond the first
            (a grasp across a cavity, e.g. a cup's outer walls).
    """
    K, N, _ = points_kxnx3.shape
    S = int(n_samples)
    idx = np.stack([rng.choice(N, S, replace=False) for _ in range(K)]) if N >= S else rng.integers(0, N, (K, S))
    kk = np.arange(K)[:, None]
    p1 = points_kxnx3[kk, idx]
    n1 = _unit(normals_kxnx3[kk, idx])
    t_min = max(1e-4, 0.5 * min_dist)
    has_mesh = np.array([meshes is not None and meshes[k] is not None and not meshes[k].is_empty for k in range(K)])
    t_max = max_dist + search_radius

    def cast(back_kxsx3: np.ndarray):
        """Opposite contacts along p1 - t * back (first and last exits) for every object and sample."""
        p2, n2, p2f, n2f = (np.full((K, S, 3), np.nan) for _ in range(4))
        gap = np.zeros((K, S))
        if not np.all(has_mesh):  # batched point search for every object without a mesh
            sel = ~has_mesh
            p2[sel], n2[sel], p2f[sel], n2f[sel], gap[sel] = _opposite_by_points(
                points_kxnx3[sel], normals_kxnx3[sel], p1[sel], back_kxsx3[sel], search_radius, t_min, t_max)
        for k in np.flatnonzero(has_mesh):
            mesh = meshes[k]
            # start slightly outside so the entry face is behind the origin
            orig = p1[k] + 1e-4 * n1[k]
            (tf, p2[k], n2[k]), (tl, p2f[k], n2f[k]) = exit_hits(mesh.verts_vx3, mesh.faces_fx3, orig,
                                                                 -back_kxsx3[k], t_min=1e-4 + t_min, t_max=t_max)
            hit = np.isfinite(tf)
            gap[k, hit] = tl[hit] - tf[hit]
        return p2, n2, p2f, n2f, gap

    # Pass 1 casts along -n1. Pass 2 re-casts along the bisector closing axis unit(n2 - n1) of pass 1: on
    # two flat faces that lean towards each other (a frustum, a wedge) the ray along -n1 lands too low on
    # the opposite face, while the bisector line meets it level with p1.
    passes = [cast(n1)]
    y1 = _unit(passes[0][1] - n1)
    redo = np.all(np.isfinite(y1), axis=-1) & (np.linalg.norm(y1, axis=-1) > 0.5)
    passes.append(cast(np.where(redo[..., None], -y1, n1)))
    objs, p1s, n1s, p2s, n2s = [], [], [], [], []

    def flat(a: np.ndarray) -> np.ndarray:
        return a.reshape(-1, 3)

    obj0 = np.broadcast_to(np.arange(K)[:, None], (K, S)).reshape(-1)
    for i, (p2, n2, p2f, n2f, gap) in enumerate(passes):
        take = np.ones(K * S, bool) if i == 0 else redo.reshape(-1)
        o, a, na, b, nb = obj0[take], flat(p1)[take], flat(n1)[take], flat(p2)[take], flat(n2)[take]
        if far_contacts:  # the last exit too, where it is a different surface (across a cavity)
            far = gap.reshape(-1)[take] > 2.0 * search_radius
            o, a, na = np.concatenate([o, o[far]]), np.concatenate([a, a[far]]), np.concatenate([na, na[far]])
            b, nb = np.concatenate([b, flat(p2f)[take][far]]), np.concatenate([nb, flat(n2f)[take][far]])
        objs.append(o)
        p1s.append(a)
        n1s.append(na)
        p2s.append(b)
        n2s.append(nb)
    obj, p1, n1, p2, n2 = (np.concatenate(x) for x in (objs, p1s, n1s, p2s, n2s))
    found = np.all(np.isfinite(p2), axis=1) & np.all(np.isfinite(n2), axis=1)
    obj, p1, n1, p2, n2 = obj[found], p1[found], n1[found], p2[found], _unit(n2[found])
    y = _unit(n2 - n1)
    d = p2 - p1
    dist = np.einsum("ij,ij->i", d, y)
    lateral = np.linalg.norm(d - dist[:, None] * y, axis=1)
    cos_cone = 1.0 / np.sqrt(1.0 + friction_coef**2)  # cos(atan(mu))
    c1 = -np.einsum("ij,ij->i", n1, y)
    c2 = np.einsum("ij,ij->i", n2, y)
    keep = (dist >= min_dist) & (dist <= max_dist) & (lateral <= lateral_tolerance)
    keep &= (c1 >= cos_cone) & (c2 >= cos_cone)
    quality = np.clip((0.5 * (c1 + c2) - cos_cone) / max(1e-9, 1.0 - cos_cone), 0.0, 1.0)
    return ContactPairs(obj[keep], p1[keep], n1[keep], p2[keep], n2[keep], y[keep], dist[keep], quality[keep])


def enumerate_grasps(
    pairs: ContactPairs,
    gripper: GripperGeometry,
    *,
    n_angles: int,
    max_tilt_rad: float,
    depths: Sequence[float],
    width_margin: float,
) -> GraspCandidates:
    """Grasp poses for every pair x approach angle x depth (see the module docstring).

    ``width`` = contact distance + ``width_margin``, clipped to [min_opening, max_opening] (m).
    """
    P = len(pairs)
    A = int(n_angles)
    D = len(depths)
    if P == 0:
        e = np.zeros(0)
        return GraspCandidates(np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3)), e, e, e, e)
    y = pairs.y
    a = -_EZ[None, :] - (-y[:, 2:3]) * y  # projection of -z onto the plane perpendicular to y
    degenerate = np.linalg.norm(a, axis=1) < 1e-3
    if np.any(degenerate):  # closing axis (nearly) vertical: any horizontal start direction
        alt = np.cross(y[degenerate], np.array([1.0, 0.0, 0.0]))
        bad = np.linalg.norm(alt, axis=1) < 1e-3
        alt[bad] = np.cross(y[degenerate][bad], np.array([0.0, 1.0, 0.0]))
        a[degenerate] = alt
    a = _unit(a)
    b = np.cross(y, a)
    th = 2.0 * np.pi * np.arange(A) / A
    x = np.cos(th)[None, :, None] * a[:, None, :] + np.sin(th)[None, :, None] * b[:, None, :]  # (P, A, 3)
    tilt_ok = (-x[..., 2]) >= np.cos(max_tilt_rad) - 1e-9  # angle between x and -z_world
    pi, ai = np.nonzero(tilt_ok)
    x = x[pi, ai]
    yy = y[pi]
    z = np.cross(x, yy)
    R = np.stack([x, yy, z], axis=-1)  # columns x, y, z
    centre = 0.5 * (pairs.p1 + pairs.p2)[pi]
    width = np.clip(pairs.dist[pi] + width_margin, gripper.min_opening, gripper.max_opening)
    M = len(pi)
    dep = np.asarray(depths, dtype=np.float64)
    rep = lambda v: np.repeat(v, D, axis=0)  # noqa: E731
    return GraspCandidates(
        obj=rep(pairs.obj[pi]),
        R=rep(R),
        t=rep(centre),
        width=rep(width),
        depth=np.tile(dep, M),
        contact_dist=rep(pairs.dist[pi]),
        antipodal=rep(pairs.quality[pi]),
        pair=rep(pi),
    )
