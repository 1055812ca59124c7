"""Differentiable silhouette rasteriser: coverage, depth, conventions, gradients vs finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torm.geometry import invert_T, look_at_cv
from torm.reconstruction import losses
from torm.reconstruction.raster import (
    SilhouetteBatch,
    _compact_pixels,
    _face_orientation,
    _orientation_kernel,
    _project_kernel,
    _rasterize_reference_kernel,
    edge_coverage_reference,
    face_adjacency,
    face_adjacency_reference,
    project_torch,
    rasterize,
    render_depth,
    render_mask,
    render_silhouette,
    render_silhouettes,
    render_silhouettes_sparse,
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


def test_rasteriser_equals_the_reference_kernel():
    """The span-culling rasteriser gives the reference kernel's triangle ids and depths: a sphere, a random soup of
    small and large triangles, vertices behind the camera and far outside the image."""
    m, T = _sphere_scene()
    p = m.vertices @ T[:3, :3].T + T[:3, 3]
    sphere = np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2], p[:, 2]], axis=1)
    rng = np.random.default_rng(0)
    soup = np.column_stack([rng.uniform(-20, W + 20, 600), rng.uniform(-20, H + 20, 600), rng.uniform(0.5, 2, 600)])
    soup[:200, :2] = soup[:200:4, :2].repeat(4, axis=0)[:200] + rng.normal(0, 0.7, (200, 2))  # sub-pixel faces
    soup[5, 2] = -1.0  # behind the camera
    soup[7, :2] = [1e12, -1e12]  # far outside
    soup_faces = rng.integers(0, 600, (900, 3))
    for uvz, faces in ((sphere, np.asarray(m.faces, dtype=np.int64)), (soup, soup_faces)):
        tri = -np.ones((H, W), dtype=np.int32)
        depth = np.zeros((H, W), dtype=np.float32)
        _rasterize_reference_kernel(np.ascontiguousarray(uvz), faces, H, W, tri, depth)
        got_tri, got_depth = rasterize(uvz, faces, H, W)
        assert (tri >= 0).sum() > 100
        assert np.array_equal(got_tri, tri) and np.array_equal(got_depth, depth)


def test_face_orientation_equals_the_orientation_kernel():
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]], dtype=np.int64)
    assert [_face_orientation(uv, faces, f) for f in range(3)] == _orientation_kernel(uv, faces).tolist()


def test_compact_pixels_is_unique_with_inverse():
    rng = np.random.default_rng(0)
    idx = rng.integers(0, 50, size=200)
    pix, inv = _compact_pixels(idx, 50)
    want_pix, want_inv = np.unique(idx, return_inverse=True)
    assert np.array_equal(pix, want_pix) and np.array_equal(inv, want_inv)
    pix0, inv0 = _compact_pixels(np.zeros(0, dtype=np.int64), 10)
    assert len(pix0) == len(inv0) == 0


def test_sparse_silhouettes_and_loss_equal_the_dense_ones():
    """The sparse silhouettes hold the dense image; eq. (2) on them has the dense loss's value and vertex gradient."""
    m, T = _sphere_scene()
    T2 = invert_T(look_at_cv(np.array([-0.2, 0.2, 0.1]), np.zeros(3)))
    Ks, Ts = np.stack([K, K]), np.stack([T, T2])
    target = torch.from_numpy(np.roll(render_silhouettes(torch.tensor(m.vertices), m.faces, Ks, Ts, H, W).numpy()
                                      > 0.5, 2, axis=2).astype(np.float64))
    v1 = torch.tensor(m.vertices, requires_grad=True)
    sil = render_silhouettes_sparse(v1, m.faces, Ks, Ts, H, W)
    assert len(sil.pix_n) > 0 and bool((sil.pix_n[1:] > sil.pix_n[:-1]).all())  # distinct, ascending
    dense = sil.dense()
    assert np.allclose(sil.values(), dense.detach().numpy(), atol=1e-6)
    assert set(np.unique(sil.hard_vxhxw)) == {0.0, 1.0}
    loss_s = losses.envelope_mask_loss_sparse(torch.from_numpy(sil.hard_vxhxw).double(), sil.pix_n, sil.delta_n,
                                              target, 2.5)
    loss_s.sum().backward()
    v2 = torch.tensor(m.vertices, requires_grad=True)
    loss_d = losses.envelope_mask_loss(render_silhouettes(v2, m.faces, Ks, Ts, H, W), target, 2.5)
    loss_d.sum().backward()
    assert torch.allclose(loss_s.detach(), loss_d.detach(), atol=1e-12)
    assert float(v1.grad.abs().max()) > 0 and torch.allclose(v1.grad, v2.grad, atol=1e-12)


def test_sparse_loss_equals_dense_loss_on_random_values():
    """The identity behind the sparse loss, on a hand-made prediction (fractional values, two views)."""
    g = torch.Generator().manual_seed(0)
    hard = (torch.rand((2, 5, 7), generator=g) > 0.5).float()
    target = torch.rand((2, 5, 7), generator=g)
    pix = torch.tensor([0, 3, 34, 35, 40, 69])
    delta = (torch.rand(6, generator=g) - 0.5).requires_grad_(True)
    got = losses.envelope_mask_loss_sparse(hard, pix, delta, target, 1.7)
    got.sum().backward()
    d2 = delta.detach().clone().requires_grad_(True)
    want = losses.envelope_mask_loss(hard.reshape(-1).index_add(0, pix, d2).reshape(2, 5, 7), target, 1.7)
    want.sum().backward()
    assert torch.allclose(got.detach(), want.detach(), atol=1e-6) and torch.allclose(delta.grad, d2.grad, atol=1e-6)


def test_weighted_sparse_loss_equals_the_weighted_dense_loss_and_ignores_zero_weight_pixels():
    """Per-pixel weights (0 = no evidence): the sparse path equals the dense reference, and a zero-weight pixel's
    target changes neither the loss nor its gradient."""
    g = torch.Generator().manual_seed(1)
    hard = (torch.rand((2, 5, 7), generator=g) > 0.5).float()
    target = torch.rand((2, 5, 7), generator=g)
    weight = (torch.rand((2, 5, 7), generator=g) > 0.3).float()
    pix = torch.tensor([0, 3, 34, 35, 40, 69])
    weight.reshape(-1)[torch.tensor([3, 40])] = 0.0  # two edge pixels without evidence

    def sparse(tgt):
        delta = (torch.rand(6, generator=torch.Generator().manual_seed(2)) - 0.5).requires_grad_(True)
        loss = losses.envelope_mask_loss_sparse(hard, pix, delta, tgt, 1.7, weight)
        loss.sum().backward()
        return loss.detach(), delta.grad, delta

    got, grad, delta = sparse(target)
    d2 = delta.detach().clone().requires_grad_(True)
    want = losses.envelope_mask_loss(hard.reshape(-1).index_add(0, pix, d2).reshape(2, 5, 7), target, 1.7, weight)
    want.sum().backward()
    assert torch.allclose(got, want.detach(), atol=1e-6) and torch.allclose(grad, d2.grad, atol=1e-6)
    flipped = torch.where(weight > 0, target, 1.0 - target)  # other targets where the weight is 0
    got2, grad2, _ = sparse(flipped)
    assert torch.allclose(got, got2, atol=1e-7) and torch.allclose(grad, grad2, atol=1e-7)
    assert grad[1] == 0 and grad[4] == 0  # the two no-evidence pixels pull nothing
    ones = torch.ones_like(hard)
    assert torch.allclose(losses.mask_loss_init(hard, target, ones), losses.mask_loss_init(hard, target))


def test_sparse_silhouettes_of_an_empty_mesh_and_an_unfinished_batch():
    v = torch.zeros((0, 3), requires_grad=True)
    sil = render_silhouettes_sparse(v, np.zeros((0, 3), np.int64), K, T_ID, H, W)
    assert sil.hard_vxhxw.shape == (1, H, W) and len(sil.pix_n) == 0 and sil.values().sum() == 0
    m, T = _sphere_scene()
    batch = SilhouetteBatch(torch.tensor(m.vertices), m.faces, np.stack([K, K]), np.stack([T, T]), H, W)
    batch.view(0, face_adjacency(m.faces, len(m.vertices)))
    with pytest.raises(RuntimeError, match="every view"):
        batch.finish()


def test_compiled_projection_and_edge_coverage_equal_the_torch_reference():
    """The compiled float64 projection and edge corrections (forward and backward) equal the torch ops they
    replace, on a sphere seen in two views."""
    m, T = _sphere_scene()
    T2 = invert_T(look_at_cv(np.array([-0.2, 0.2, 0.1]), np.zeros(3)))
    Ks, Ts = np.stack([K, K]), np.stack([T, T2])
    X = torch.tensor(m.vertices, requires_grad=True)
    uvz = _project_kernel(np.ascontiguousarray(m.vertices), Ks, Ts)
    assert np.allclose(uvz, project_torch(X, torch.tensor(Ks), torch.tensor(Ts)).detach().numpy(), atol=1e-9)
    fast = SilhouetteBatch(X, m.faces, Ks, Ts, H, W)
    slow = SilhouetteBatch(X, m.faces, Ks, Ts, H, W, compiled=False)
    adj = face_adjacency(m.faces, len(m.vertices))
    for i in range(2):
        fast.view(i, adj)
        slow.view(i, adj)
    assert np.array_equal(fast.hard, slow.hard)
    a, b = fast.finish(), slow.finish()
    assert torch.equal(a.pix_n, b.pix_n) and len(a.pix_n) > 50
    assert torch.allclose(a.delta_n, b.delta_n, atol=1e-9)
    w = torch.randn(len(a.pix_n), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ga = torch.autograd.grad((a.delta_n * w).sum(), X)[0]
    gb = torch.autograd.grad((b.delta_n * w).sum(), X)[0]
    assert float(ga.abs().max()) > 0 and torch.allclose(ga, gb, atol=1e-9)
    assert callable(edge_coverage_reference)
