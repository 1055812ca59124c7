"""Mesh split, surface sampling and export."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torm.errors import ReconstructionError
from torm.mesh import sample_objects, sample_surface, split_components, write_mesh, write_point_cloud
from torm.mesh.split import face_components
from torm.types import TriMesh


def _spheres(centres, radii, subdiv=2):
    vs, fs, off = [], [], 0
    for c, r in zip(centres, radii, strict=True):
        s = trimesh.creation.icosphere(subdiv, radius=r)
        vs.append(s.vertices + c)
        fs.append(s.faces + off)
        off += len(s.vertices)
    return np.concatenate(vs), np.concatenate(fs)


def test_split_finds_every_component_and_keeps_every_face():
    centres = [[0.65, 0.0, 0.05], [0.45, 0.1, 0.05], [0.45, -0.1, 0.05], [0.55, 0.0, 0.05]]
    v, f = _spheres(centres, [0.03, 0.02, 0.025, 0.03])
    rng = np.random.default_rng(0)
    f_shuffled = f[rng.permutation(len(f))]
    parts = split_components(v, f_shuffled)
    assert len(parts) == 4
    cen = np.array([p.verts_vx3.mean(0) for p in parts])
    np.testing.assert_allclose(cen[:, 0], [0.45, 0.45, 0.55, 0.65], atol=1e-9)  # sorted by x then y
    assert cen[0, 1] < cen[1, 1]
    # every face kept exactly (same triangles with the same winding, as vertex positions)
    orig = {tuple(np.round(v[t], 12).ravel()) for t in f_shuffled}
    got = [tuple(np.round(p.verts_vx3[t], 12).ravel()) for p in parts for t in p.faces_fx3]
    assert len(got) == len(f) and set(got) == orig
    for p in parts:
        m = p.to_trimesh()
        assert m.is_watertight and m.volume > 0


def test_split_thresholds_drop_small_components():
    v, f = _spheres([[0, 0, 0], [1, 0, 0]], [0.05, 0.005])
    assert len(split_components(v, f)) == 2
    big_only = split_components(v, f, min_volume=1e-6)  # 1 cm^3: the 5 mm sphere (0.5 cm^3) goes
    assert len(big_only) == 1 and big_only[0].verts_vx3[:, 0].mean() == pytest.approx(0, abs=1e-9)
    assert len(split_components(v, f, min_fraction=0.6)) == 0  # each sphere holds half the faces
    assert len(split_components(v, f, min_faces=len(f) // 2)) == 2
    with pytest.raises(ReconstructionError):
        split_components(v, f, min_fraction=2.0)
    assert split_components(v, np.zeros((0, 3), dtype=np.int64)) == []


def test_vertex_touching_faces_are_separate_components():
    f = np.array([[0, 1, 2], [0, 3, 4], [1, 5, 2]])  # faces 0 and 2 share edge (1, 2); face 1 only vertex 0
    n, labels = face_components(f)
    assert n == 2 and labels[0] == labels[2] != labels[1]


def test_sampler_equal_counts_unit_outward_normals():
    v, f = _spheres([[0, 0, 0], [0.3, 0, 0]], [0.05, 0.02], subdiv=3)
    parts = split_components(v, f)
    clouds = sample_objects(parts, 2000, rng=7)
    assert [c.points_nx3.shape for c in clouds] == [(2000, 3), (2000, 3)]
    for c, centre, r in zip(clouds, [[0, 0, 0], [0.3, 0, 0]], [0.05, 0.02], strict=True):
        np.testing.assert_allclose(np.linalg.norm(c.normals_nx3, axis=1), 1.0, atol=1e-12)
        radial = c.points_nx3 - centre
        d = np.linalg.norm(radial, axis=1)
        assert np.all(d <= r + 1e-9) and np.all(d > 0.98 * r)  # on the (inscribed) surface
        assert np.all(np.einsum("ij,ij->i", radial / d[:, None], c.normals_nx3) > 0.95)  # outward
        # area-uniform: the mean of the points is the centre, the z spread of a sphere is uniform
        np.testing.assert_allclose(radial.mean(0), 0, atol=0.1 * r)
        hist = np.histogram(radial[:, 2] / r, bins=4, range=(-1, 1))[0]
        assert hist.min() > 0.8 * hist.max()
    # deterministic for a seed
    first, again = sample_surface(parts[0], 10, 3), sample_surface(parts[0], 10, 3)
    np.testing.assert_array_equal(first.points_nx3, again.points_nx3)
    with pytest.raises(ReconstructionError):
        sample_surface(TriMesh(np.zeros((0, 3)), np.zeros((0, 3))), 10, 0)


def test_export_roundtrip(tmp_path):
    v, f = _spheres([[0.5, 0, 0.05]], [0.03])
    mesh = TriMesh(v, f)
    for ext in ("ply", "obj", "glb", "stl"):
        p = write_mesh(mesh, tmp_path / "out" / f"scene.{ext}")
        loaded = trimesh.load(p, force="mesh")
        assert loaded.volume == pytest.approx(mesh.to_trimesh().volume, rel=1e-5)
    with pytest.raises(ReconstructionError, match="use one of"):
        write_mesh(mesh, tmp_path / "scene.xyz")
    cloud = sample_surface(mesh, 500, 1)
    p = write_point_cloud(cloud, tmp_path / "cloud.ply")
    raw = p.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    assert b"element vertex 500" in header and b"property float nz" in header
    data = np.frombuffer(body, dtype="<f4").reshape(500, 6)
    np.testing.assert_allclose(data[:, :3], cloud.points_nx3, atol=1e-6)
    np.testing.assert_allclose(data[:, 3:], cloud.normals_nx3, atol=1e-6)
    pc = trimesh.load(p)
    assert len(pc.vertices) == 500
