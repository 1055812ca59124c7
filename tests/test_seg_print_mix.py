"""Segmenter v5 data (issue 43): the ``print`` distractor mix (mugs, books, printed and clear-coated materials on
UV-mapped meshes) and the guarantee that the ``v4`` mix still draws v4's data."""

from __future__ import annotations

import numpy as np
import pytest

from torm.errors import ConfigError


def test_v4_mix_draws_what_v4_drew_before_kinds_and_materials_were_added():
    """v4's data are reproduced: the appended zero weights leave every weighted draw of kind and material as it was
    with v4's four-entry tuples."""
    from torm.segmentation.training.clutter import KINDS, MATERIALS, MIXES

    kind_p, mat_p = MIXES["v4"]
    assert KINDS[:4] == ("can", "box", "blob", "twin") and MATERIALS[:4] == (
        "roughplastic", "plastic", "roughconductor", "textured")
    for seed in range(300):
        old = np.random.default_rng(seed).choice(KINDS[:4], p=[0.35, 0.25, 0.15, 0.25])
        assert np.random.default_rng(seed).choice(KINDS, p=list(kind_p)) == old
        old = np.random.default_rng(seed).choice(MATERIALS[:4], p=[0.4, 0.2, 0.25, 0.15])
        assert np.random.default_rng(seed).choice(MATERIALS, p=list(mat_p)) == old
    for k, m in MIXES.values():
        assert len(k) == len(KINDS) and len(m) == len(MATERIALS) and sum(k) == pytest.approx(1) == sum(m)


def test_unknown_mix_is_a_named_error():
    from torm.segmentation.training.dataset import DataRecipe

    assert DataRecipe(distractor_mix="print").distractor_mix == "print"
    with pytest.raises(ConfigError, match="distractor_mix 'glossy'; valid choices: v4, print"):
        DataRecipe(distractor_mix="glossy")


def test_print_images_are_patterns_not_flat_colours():
    from torm.segmentation.training.clutter import print_image

    contrast = []
    for seed in range(24):
        img = print_image(np.random.default_rng(seed), 64)
        assert img.shape == (64, 64, 3) and img.dtype == np.float32
        assert img.min() >= 0.0 and img.max() <= 1.0
        assert len(np.unique(img.reshape(-1, 3), axis=0)) >= 2, seed  # a print, not a flat colour
        contrast.append(np.ptp(img.reshape(-1, 3), axis=0).max())
    assert np.median(contrast) > 0.2  # most prints contrast clearly with their background (linear RGB)


def test_uv_soup_unwraps_the_cylinder_seam_and_maps_caps_flat():
    import trimesh

    from torm.segmentation.training.clutter import uv_soup

    r, h = 0.04, 0.1
    m = trimesh.creation.cylinder(radius=r, height=h, sections=24)
    v, n, uv = uv_soup(m.vertices, m.faces, cylindrical=True)
    assert v.shape == n.shape == (3 * len(m.faces), 3) and uv.shape == (3 * len(m.faces), 2)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    side = np.abs(n[:, 2]) < 0.5
    faces_uv = uv.reshape(-1, 3, 2)
    # no side face spans the whole print: across the seam its corners are unwrapped past u = 1 (24 sections:
    # a side face covers 1/24 of a turn)
    side_faces = side.reshape(-1, 3).all(axis=1)
    assert side_faces.sum() == 2 * 24 and np.ptp(faces_uv[side_faces, :, 0], axis=1).max() == pytest.approx(1 / 24)
    # side corners: u is the azimuth turn fraction, v the height over the circumference (print not stretched)
    az = (np.arctan2(v[side, 1], v[side, 0]) / (2 * np.pi)) % 1.0
    assert np.allclose(uv[side, 0] % 1.0, az, atol=1e-6)
    assert np.allclose(uv[side, 1], (v[side, 2] - v[:, 2].min()) / (2 * np.pi * r), atol=1e-6)
    # caps: planar in x, y over the largest extent (the height, 0.1 m)
    cap = ~side
    assert np.allclose(uv[cap], (v[cap][:, :2] - v[:, :2].min(axis=0)) / h, atol=1e-6)


def test_uv_mesh_file_is_a_ply_mitsuba_reads_with_texture_coordinates(tmp_path):
    pytest.importorskip("mitsuba")
    from sim.render.mitsuba_env import load_mitsuba
    from torm.segmentation.training.clutter import _uv_mesh_file, distractor_mesh

    mi, _ = load_mitsuba()  # the process's variant (it is process-global): any reads a PLY

    v, f = distractor_mesh("mug", np.random.default_rng(0), [])
    path = _uv_mesh_file(v, f, True, tmp_path)
    assert path == _uv_mesh_file(v, f, True, tmp_path)  # content-addressed: written once
    mesh = mi.load_dict({"type": "ply", "filename": str(path), "face_normals": False})
    assert mesh.has_vertex_texcoords() and mesh.has_vertex_normals()
    assert mesh.face_count() == len(f)
    bb = mesh.bbox()
    assert np.allclose([bb.min.z, bb.max.z - bb.min.z], [0.0, np.ptp(v[:, 2])], atol=1e-5)


def test_a_print_mix_scene_shows_prints_and_labels_only_glass():
    pytest.importorskip("mitsuba")
    from tests.render_helpers import one_glass_cylinder_view
    from torm.segmentation.training.render import SceneLook, render_pbr

    world, T, K = one_glass_cylinder_view(0.25)
    _, mask_p, _ = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4)
    rgb, mask, info = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4,
                                 look=SceneLook(n_distractors=8, clutter_seed=7, mix="print"))
    kinds = {d["kind"] for d in info["distractors"]}
    mats = {d["material"] for d in info["distractors"]}
    assert kinds & {"mug", "book"} and mats & {"textured", "glossy_print"}
    assert set(np.unique(mask)) <= {0, 1} and 0 < (mask > 0).sum() <= (mask_p > 0).sum()
    assert rgb.std() > 5


def test_object_distractors_are_opaque_instances_after_the_worlds_objects_and_books_stay_background():
    """Segmenter v7's data: the recipe's ``object_distractors`` kinds get instance ids after the world's objects (the
    class head's opaque class); other kinds (books) and the room stay 0. The same draw without the labels renders
    the same pixels."""
    pytest.importorskip("mitsuba")
    from tests.render_helpers import one_glass_cylinder_view
    from torm.segmentation.training.render import SceneLook, render_pbr

    world, T, K = one_glass_cylinder_view(0.25)
    kinds = ("can", "box", "blob", "twin", "mug")
    look = SceneLook(n_distractors=8, clutter_seed=7, mix="print")
    rgb0, mask0, _ = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4, look=look)
    rgb, mask, info = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4,
                                 look=SceneLook(n_distractors=8, clutter_seed=7, mix="print", object_kinds=kinds))
    drawn = info["distractors"]
    labelled = info["object_distractors"]
    assert len(labelled) == sum(d["kind"] in kinds for d in drawn) > 0
    assert any(d["kind"] == "book" for d in drawn)  # this draw holds a book: it must stay background
    n = len(world.objects)
    ids = set(np.unique(mask).tolist())
    assert ids <= set(range(n + len(labelled) + 1)) and ids - set(range(n + 1))  # some labelled distractor is seen
    assert np.array_equal(mask[mask <= n] > 0, mask0[mask <= n] > 0)  # the glass keeps its pixels and ids
    assert np.array_equal(rgb, rgb0)


def test_recipe_refuses_unknown_object_distractor_kinds_and_glass_only_labels():
    from torm.errors import ConfigError
    from torm.segmentation.training.dataset import DataRecipe

    with pytest.raises(ConfigError, match="unknown kind.*valid choices: can, box"):
        DataRecipe(object_distractors=("cup",))
    with pytest.raises(ConfigError, match="label_opaque"):
        DataRecipe(object_distractors=("mug",), label_opaque=False)
    assert DataRecipe(object_distractors=("mug", "can")).object_distractors == ("mug", "can")


def test_evaluate_counts_labelled_distractors_as_their_own_object_type():
    """Instance ids past the world's objects (data.object_distractors) are scored under the type 'distractor'."""
    from torm.segmentation.training.evaluate import evaluate

    mask = np.zeros((1, 20, 20), np.int32)
    mask[0, :10, :10] = 1  # the scene's one object
    mask[0, 10:, 10:] = 2  # a labelled distractor
    data = {"rgb": np.zeros((1, 20, 20, 3), np.uint8), "mask": mask, "T_world_cam": np.eye(4)[None],
            "scene": np.array([0]), "meta": [{"objects": ["cylinder"]}]}
    r = evaluate(lambda im: mask[0], data, min_visible_px=10)
    assert r["object"]["iou_mean"] == pytest.approx(1.0)
    assert set(r["per_type"]) == {"cylinder", "distractor"}
