"""Vectorised gripper-box collision checks (table plane, points) against brute-force references."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from torm.grasp.collision import min_box_z, points_collision_free, points_in_boxes, table_collision_free
from torm.grasp.gripper import GripperGeometry
from torm.grasp.score import rotation_distance

G = GripperGeometry()


def _top_down(t):
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # x = -z, y = y, z = x cross y
    return R, np.asarray(t, dtype=float)


def test_points_in_boxes_matches_brute_force():
    rng = np.random.default_rng(0)
    C = 40
    R = Rotation.random(C, random_state=1).as_matrix()
    t = rng.uniform(-0.05, 0.05, (C, 3))
    width = rng.uniform(0.02, 0.085, C)
    depth = rng.uniform(0.0, 0.04, C)
    pts = rng.uniform(-0.2, 0.2, (3000, 3))
    centres, halves = G.box_params(width, depth)
    got = points_in_boxes(R, t, centres, halves, pts, margin=0.001)
    local = np.einsum("cij,cpi->cpj", R, pts[None] - t[:, None])  # R^T (p - t)
    inside = np.zeros((C, len(pts)), dtype=bool)
    for b in range(centres.shape[1]):
        inside |= np.all(np.abs(local - centres[:, None, b]) <= halves[:, None, b] + 0.001, axis=2)
    assert np.array_equal(got, inside.sum(axis=1)) and got.sum() > 0
    assert np.array_equal(points_in_boxes(R, t, centres, halves, pts, 0.001, stop_at_first=True) > 0, got > 0)


def test_table_check_top_down_vs_side():
    R, t = _top_down([0.5, 0.0, 0.03])
    side = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # approach along +x world
    Rs = np.stack([R, R, side, side])
    ts = np.stack([t, [0.5, 0.0, 0.01], [0.5, 0.0, 0.02], [0.5, 0.0, 0.10]])
    w = np.full(4, 0.06)
    d = np.full(4, 0.02)
    ok = table_collision_free(Rs, ts, w, d, G, table_height=0.0, clearance=0.002)
    # top-down: fingertips 2 cm below the centre; side: the palm reaches palm_height / 2 below the centre
    assert ok.tolist() == [True, False, False, True]
    zmin = min_box_z(Rs, ts, *G.box_params(w, d))
    assert np.isclose(zmin[0, 0], 0.03 - 0.02) and np.isclose(zmin[2, 2], 0.02 - G.palm_height / 2)


def test_object_between_the_pads_is_not_a_collision_but_under_a_finger_is():
    R, t = _top_down([0.5, 0.0, 0.05])
    between = np.array([[0.5, 0.0, 0.045], [0.5, 0.025, 0.04]])  # inside the 6 cm opening
    under_finger = np.array([[0.5, 0.035, 0.04]])  # y = 3.5 cm: inside the right finger
    above = np.array([[0.5, 0.0, 0.05 + 0.17]])  # behind the palm, on the approach path (palm sweep)
    w, d = np.array([0.06]), np.array([0.02])
    assert points_collision_free(R[None], t[None], w, d, G, between)[0]
    assert not points_collision_free(R[None], t[None], w, d, G, under_finger)[0]
    assert not points_collision_free(R[None], t[None], w, d, G, above)[0]
    assert points_collision_free(R[None], t[None], w, d, G, above, check_approach_sweep=False)[0]


def test_rotation_distance_is_finger_swap_symmetric():
    R, _ = _top_down([0, 0, 0])
    swapped = R @ np.diag([1.0, -1.0, -1.0])
    quarter = R @ Rotation.from_euler("x", 90, degrees=True).as_matrix()
    d = rotation_distance(R, np.stack([R, swapped, quarter]))
    assert np.allclose(d, [0.0, 0.0, np.pi / 2], atol=1e-7)
    assert np.isclose(rotation_distance(R, swapped[None], symmetric=False)[0], np.pi)
