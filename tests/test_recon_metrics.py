"""Reconstruction metrics on hand-computable cases."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torm.errors import ReconstructionError
from torm.metrics import (
    chamfer_distance_mm,
    depth_metrics,
    match_clouds_to_meshes,
    match_meshes,
    match_objects,
    mesh_centroid,
    mesh_volume,
    occupancy_grid,
    silhouette_iou,
    volume_iou,
)
from torm.types import TriMesh


def _tm(m: trimesh.Trimesh, offset=(0.0, 0.0, 0.0)) -> TriMesh:
    return TriMesh(m.vertices + np.asarray(offset), m.faces)


def test_silhouette_iou_known_masks():
    gt = np.zeros((2, 4, 4), bool)
    gt[0, :2, :2] = True  # 4 px
    pred = np.zeros((2, 4, 4), np.int32)
    pred[0, :2, :3] = 3  # 6 px, 4 shared -> 4/6
    r = silhouette_iou(pred, gt)  # view 1: both empty -> 1
    np.testing.assert_allclose(r["per_view"], [4 / 6, 1.0])
    assert r["mean"] == pytest.approx((4 / 6 + 1) / 2) and r["min"] == pytest.approx(4 / 6)
    assert silhouette_iou(gt[0], gt[0])["mean"] == 1.0
    with pytest.raises(ReconstructionError):
        silhouette_iou(gt, gt[:, :3])


def test_depth_metrics_tiny_arrays():
    gt = np.array([[1.0, 2.0, 4.0], [1.0, 1.0, np.nan]])
    mask = np.array([[1, 1, 1], [1, 0, 1]])
    pred = np.array([[1.04, 2.4, 4.0], [0.0, 5.0, 1.0]])  # (1,0) no prediction, (1,1) outside mask
    r = depth_metrics(pred, gt, mask)
    # evaluated: 1.04 vs 1, 2.4 vs 2, 4 vs 4; GT-valid mask pixels: 4 (nan GT excluded)
    err = np.array([0.04, 0.4, 0.0])
    assert r["n_pixels"] == 3 and r["coverage"] == pytest.approx(3 / 4)
    assert r["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert r["mae"] == pytest.approx(err.mean())
    assert r["absrel"] == pytest.approx(np.mean([0.04, 0.2, 0.0]))
    assert r["delta_1.05"] == pytest.approx(2 / 3)  # ratios 1.04, 1.2, 1.0
    assert r["delta_1.10"] == pytest.approx(2 / 3)
    assert r["delta_1.25"] == pytest.approx(1.0)
    # symmetric ratio: under-estimates count the same as over-estimates
    r2 = depth_metrics(np.array([[1 / 1.2]]), np.array([[1.0]]), np.array([[1]]))
    assert r2["delta_1.25"] == 1.0 and r2["delta_1.10"] == 0.0
    empty = depth_metrics(np.zeros((2, 2)), np.ones((2, 2)), np.ones((2, 2)))
    assert empty["coverage"] == 0.0 and np.isnan(empty["rmse"])


def test_chamfer_of_shifted_point_sets():
    a = np.stack(np.meshgrid(*[np.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.1  # lattice, 0.1 m
    shift = np.array([0.002, 0.0, 0.0])
    assert chamfer_distance_mm(a, a + shift) == pytest.approx(2.0)
    assert chamfer_distance_mm(a, a) == 0.0
    # asymmetric case: b = a plus one far point 1 m away from everything -> mean of both directions
    far = np.array([[5.0, 5.0, 5.0]])
    b = np.concatenate([a, far])
    d_far = np.linalg.norm(a - far, axis=1).min()
    assert chamfer_distance_mm(a, b) == pytest.approx(500 * (0 + d_far / len(b)))
    with pytest.raises(ReconstructionError):
        chamfer_distance_mm(a, np.zeros((0, 3)))


def test_volume_iou_boxes_and_spheres():
    box = trimesh.creation.box([0.1, 0.04, 0.02])
    r = volume_iou(_tm(box), _tm(box, [0.05, 0, 0]))  # overlap half the box: 1 / 3
    assert r["iou"] == pytest.approx(1 / 3, abs=0.01) and r["volume_ratio"] == pytest.approx(1.0)
    assert volume_iou(_tm(box), _tm(box))["iou"] == pytest.approx(1.0)
    s = trimesh.creation.icosphere(4, radius=0.05)
    r = volume_iou(_tm(s), _tm(s, [0.05, 0, 0]))
    R, d = 0.05, 0.05
    lens = np.pi / 12 * (4 * R + d) * (2 * R - d) ** 2
    assert r["iou"] == pytest.approx(lens / (2 * 4 / 3 * np.pi * R**3 - lens), abs=0.01)
    big = trimesh.creation.icosphere(3, radius=0.1)
    assert volume_iou(_tm(s), _tm(big))["volume_ratio"] == pytest.approx(0.125, rel=0.01)
    # lists are unions; disjoint parts add up
    two = volume_iou([_tm(s), _tm(s, [0.3, 0, 0])], _tm(s))
    assert two["iou"] == pytest.approx(0.5, abs=0.01) and two["volume_ratio"] == pytest.approx(2.0)


def test_occupancy_counts_voxels_inside():
    box = trimesh.creation.box([0.01, 0.02, 0.03])  # 10 x 20 x 30 mm centred at 0
    occ = occupancy_grid(_tm(box), np.array([-0.02, -0.02, -0.02]), 0.001, (40, 40, 40))
    assert occ.sum() == 10 * 20 * 30
    assert not occ[:, :, :4].any() and occ[20, 20, 20]


def test_match_objects_and_centroids():
    s = trimesh.creation.icosphere(2, radius=0.03)
    gt = [_tm(s, [0.4, 0, 0.03]), _tm(s, [0.5, 0, 0.03]), _tm(s, [0.6, 0, 0.03])]
    pred = [_tm(s, [0.502, 0, 0.03]), _tm(s, [0.4, 0.005, 0.03]), _tm(s, [0.6, 0.2, 0.03])]
    np.testing.assert_allclose(mesh_centroid(gt[1]), [0.5, 0, 0.03], atol=1e-9)
    assert mesh_volume(gt) == pytest.approx(3 * s.volume)
    r = match_meshes(pred, gt, max_dist=0.03)
    assert r["n_present"] == 3 and r["n_found"] == 2 and r["n_spurious"] == 1
    assert sorted(r["pairs"]) == [(0, 1), (1, 0)]
    # one-to-one: two predictions on one object count once
    r = match_objects(np.array([[0, 0, 0], [0.001, 0, 0]]), np.array([[0, 0, 0]]), max_dist=0.01)
    assert r["n_found"] == 1 and r["n_spurious"] == 1
    assert match_objects(np.zeros((0, 3)), np.zeros((2, 3)))["n_found"] == 0


def test_match_clouds_to_meshes_holds_a_partly_seen_tube():
    """A rack hides the lower 60 mm of three 16 mm tubes 35 mm apart (as in the lab suite): each visible top lies
    on its own tube's surface and matches it although its centroid sits 30 mm above the tube's (the centroid rule
    at 20 mm misses them all); a cloud off every surface and an empty cloud match nothing; a second cloud on one
    tube, with fewer points on it, is the spurious one."""
    tube = trimesh.creation.cylinder(radius=0.008, height=0.16, sections=32)
    gt = [_tm(tube, [0.6, y, 0.08]) for y in (-0.035, 0.0, 0.035)]
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 500)

    def top(y, off=0.0):  # visible part of the wall, z 0.06..0.16, ``off`` m outside it
        r = 0.008 + off
        return np.stack([0.6 + r * np.cos(ang), y + r * np.sin(ang), rng.uniform(0.06, 0.16, 500)], 1)

    half_off = np.concatenate([top(0.0)[:250], top(0.0, off=0.02)[:250]])
    clouds = [top(0.035), top(-0.035, off=0.004), top(0.0), np.array([[0.9, 0.3, 0.05]]), np.zeros((0, 3)), half_off]
    r = match_clouds_to_meshes(clouds, gt)
    assert sorted(r["pairs"]) == [(0, 2), (1, 0), (2, 1)]
    assert r["n_found"] == 3 and r["n_spurious"] == 3
    assert all(f == pytest.approx(1.0) for f in r["fractions"])
    assert match_objects(np.array([c.mean(0) for c in clouds[:3]]), np.array([mesh_centroid(g) for g in gt]),
                         max_dist=0.02)["n_found"] == 0
    # 4 mm outside its tube: inside a 10 mm tolerance, outside a 2 mm one
    assert (1, 0) not in match_clouds_to_meshes(clouds, gt, tol=0.002)["pairs"]
    with pytest.raises(ReconstructionError, match="tol > 0"):
        match_clouds_to_meshes(clouds, gt, tol=0.0)
    assert match_clouds_to_meshes([], gt)["n_found"] == 0 and match_clouds_to_meshes(clouds, [])["n_spurious"] == 6
