"""Differentiable silhouette rasteriser: coverage, depth, conventions, gradients vs finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torm.geometry import invert_T, look_at_cv
from torm.reconstruction.raster import (
    _orientation_kernel,
    face_adjacency,
    face_adjacency_reference,
    render_depth,
    render_mask,
    render_silhouette,
    render_silhouettes,
)
from torm.types import CameraView

H = W = 64
K = np.array([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]])
T_ID = np.eye(4)  # camera at the origin looking along +z (OpenCV)


def _square(u0, u1, v0, v1, z=1.0, f=100.0):
    """Fronto-parallel square covering pixel coords [u0, u1] x [v0, v1] at depth z (two triangles)."""
    x = lambda u: (u - W / 2) / f * z  # noqa: E731
    y = lambda v: (v - H / 2) / f * z  # noqa: E731
    verts = np.array([[x(u0), y(v0), z], [x(u1), y(v0), z], [x(u1), y(v1), z], [x(u0), y(v1), z]])
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def test_square_coverage_matches_exact_area():
    u0, u1, v0, v1 = 10.3, 50.8, 12.65, 47.2
    verts, faces = _square(u0, u1, v0, v1)
    sil = render_silhouette(torch.tensor(verts), faces, K, T_ID, H, W).numpy()
    area = (u1 - u0) * (v1 - v0)
    assert abs(sil.sum() - area) < 1.0  # only the 4 corner pixels are approximate
    # interior rows: the edge columns carry the exact fractional coverage of the pixel
    r = 30
    assert sil[r, 10] == pytest.approx(1 - 0.3, abs=1e-6)
    assert sil[r, 50] == pytest.approx(0.8, abs=1e-6)
    assert sil[r, 11:50].min() == 1.0 and sil[r, :10].max() == 0.0 and sil[r, 51:].max() == 0.0
    assert sil[12, 30] == pytest.approx(1 - 0.65, abs=1e-6) and sil[47, 30] == pytest.approx(0.2, abs=1e-6)


def test_pixel_centre_convention_matches_camera_project():
    # hard coverage is decided at pixel centres (c + 0.5, r + 0.5): a square over [10.4, 10.6] x [20.4, 20.6]
    # covers exactly pixel (20, 10); CameraView.project of its centre lands in that pixel too
    verts, faces = _square(10.4, 10.6, 20.4, 20.6)
    m = render_mask(verts, faces, K, T_ID, H, W)
    assert np.argwhere(m).tolist() == [[20, 10]]
    cam = CameraView(K=K, T_world_cam=invert_T(T_ID), mask=np.zeros((H, W), np.int32))
    uv, z = cam.project(verts.mean(0, keepdims=True))
    assert np.floor(uv[0]).astype(int).tolist() == [10, 20] and z[0] == pytest.approx(1.0)


def test_depth_is_perspective_correct():
    # a plane tilted in depth: z = 1 + 0.5 x; the z-buffer must hold the exact ray-plane intersection
    verts = np.array([[-0.1, -0.1, 0.95], [0.1, -0.1, 1.05], [0.1, 0.1, 1.05], [-0.1, 0.1, 0.95]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    d = render_depth(verts, faces, K, T_ID, H, W)
    r, c = 32, 40
    xr = (c + 0.5 - W / 2) / 100.0  # ray direction x/z
    assert d[r, c] == pytest.approx(1.0 / (1.0 - 0.5 * xr), rel=1e-5)
    assert d[0, 0] == 0.0
    # nearest surface wins
    v2, f2 = _square(20, 30, 20, 30, z=0.5)
    allv = np.concatenate([verts, v2])
    d2 = render_depth(allv, np.concatenate([faces, f2 + 4]), K, T_ID, H, W)
    assert d2[25, 25] == pytest.approx(0.5, rel=1e-6) and d2[35, 35] == pytest.approx(d[35, 35]) and d[35, 35] > 0.9


def test_empty_and_behind_camera():
    v = torch.zeros((0, 3), requires_grad=True)
    s = render_silhouette(v, np.zeros((0, 3), np.int64), K, T_ID, H, W)
    assert s.shape == (H, W) and float(s.detach().abs().sum()) == 0.0
    s.sum().backward()  # no crash
    verts, faces = _square(10, 50, 10, 50, z=-1.0)
    assert render_depth(verts, faces, K, T_ID, H, W).max() == 0.0


def _sphere_scene():
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    T = invert_T(look_at_cv(np.array([0.25, 0.1, 0.15]), np.zeros(3)))
    return m, T


def test_batched_views_equal_single_views():
    m, T = _sphere_scene()
    T2 = invert_T(look_at_cv(np.array([-0.2, 0.2, 0.1]), np.zeros(3)))
    v = torch.tensor(m.vertices)
    both = render_silhouettes(v, m.faces, np.stack([K, K]), np.stack([T, T2]), H, W)
    one = render_silhouette(v, m.faces, K, T2, H, W)
    assert torch.allclose(both[1], one)
    # antialiased area is close to the projected disc area and coverage stays in [0, 1]
    assert both.min() >= 0 and both.max() <= 1


def test_face_adjacency_closed_mesh():
    m, _ = _sphere_scene()
    adj = face_adjacency(m.faces, len(m.vertices))
    assert adj.min() >= 0  # closed manifold: every edge has a partner
    f = 7
    for k in range(3):
        g = adj[f, k]
        assert {m.faces[f, k], m.faces[f, (k + 1) % 3]} <= set(m.faces[g])


def test_face_adjacency_matches_sort_reference():
    """The compiled adjacency equals the sort-based reference on a closed mesh, an open one (boundary edges -1)
    and the empty mesh."""
    m, _ = _sphere_scene()
    closed = np.asarray(m.faces)
    open_ = closed[: len(closed) // 2]
    for faces in (closed, open_, closed[:0]):
        got = face_adjacency(faces, len(m.vertices))
        want = face_adjacency_reference(faces, len(m.vertices))
        assert got.shape == want.shape == (len(faces), 3)
        assert np.array_equal(got, want)
    assert (face_adjacency(open_, len(m.vertices)) == -1).any()


def test_orientation_kernel_signs():
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]], dtype=np.int64)
    assert _orientation_kernel(uv, faces).tolist() == [1, -1, 0]


@pytest.mark.parametrize("mesh_kind", ["cube", "sphere"])
def test_gradient_matches_finite_differences(mesh_kind):
    if mesh_kind == "cube":
        mesh = trimesh.creation.box(extents=[0.08, 0.08, 0.08])
    else:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    T = invert_T(look_at_cv(np.array([0.22, 0.12, 0.18]), np.zeros(3)))
    R = T[:3, :3]
    yy, xx = np.mgrid[0:H, 0:W]
    target = torch.tensor(((xx - 30.0) ** 2 + (yy - 34.0) ** 2 < 15.0**2).astype(np.float64))

    def loss(v):
        return ((render_silhouette(v, mesh.faces, K, T, H, W) - target) ** 2).mean()

    v0 = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
    loss(v0).backward()
    g = v0.grad.numpy()
    eps = 2e-6
    checked = 0
    rng = np.random.default_rng(0)
    for i in rng.permutation(len(mesh.vertices)):
        for axis in (0, 1):  # camera x (image right) and camera y (image down), in world coordinates
            d = R[axis]
            ga = float(g[i] @ d)
            if abs(ga) < 1e-4:
                continue
            vp = v0.detach().clone()
            vm = v0.detach().clone()
            vp[i] += torch.tensor(eps * d)
            vm[i] -= torch.tensor(eps * d)
            fd = (float(loss(vp)) - float(loss(vm))) / (2 * eps)
            assert np.sign(fd) == np.sign(ga), (i, axis, fd, ga)
            assert abs(fd - ga) <= 0.15 * abs(fd) + 1e-6, (i, axis, fd, ga)
            checked += 1
        if checked >= 8:
            break
    assert checked >= 6


def test_gradient_moves_edge_towards_target():
    # one gradient step on the square's right edge vertices moves them towards a wider target
    verts, faces = _square(20.0, 40.3, 20.0, 40.0)
    target = torch.zeros((H, W), dtype=torch.float64)
    target[20:40, 20:45] = 1.0
    v = torch.tensor(verts, requires_grad=True)
    ((render_silhouette(v, faces, K, T_ID, H, W) - target) ** 2).sum().backward()
    assert v.grad[1, 0] < 0 and v.grad[2, 0] < 0  # -grad points to +x (image right)
    assert abs(float(v.grad[0, 0])) < 1e-9 and abs(float(v.grad[3, 0])) < 1e-9
