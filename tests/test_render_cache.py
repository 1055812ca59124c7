"""Render cache: keys change with every pixel-shaping setting, mismatched entries are refused, hits skip rendering."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest

from sim.render import MitsubaRenderer, PbrSettings, RenderCache, cache_key, cache_root
from sim.render.cache import NON_KEY_SETTINGS, canonical
from tests.render_helpers import camera, tiny_world

FAST = PbrSettings(spp=4, max_depth=4, denoise="none")
# a different valid value for every settings field
CHANGED = {"spp": 64, "max_depth": 5, "rr_depth": 2, "integrator": "path", "sampler": "independent",
           "denoise": "bilateral",
           "denoise_strength": 7.0, "render_scale": 0.5, "variant": "scalar_rgb", "threads": 1, "exposure": 2.0,
           "cache": False}


def test_every_pixel_shaping_setting_changes_the_key():
    assert set(CHANGED) == {f.name for f in dataclasses.fields(PbrSettings)}
    w, cam = tiny_world(), camera()
    base = MitsubaRenderer(w, FAST)
    digest = "d" * 64
    k0 = cache_key(base.cache_inputs(cam, digest))
    for name, value in CHANGED.items():
        r = MitsubaRenderer.__new__(MitsubaRenderer)
        r.__dict__.update(base.__dict__)
        r.settings = dataclasses.replace(FAST, **{name: value})
        k = cache_key(r.cache_inputs(cam, digest))
        assert (k == k0) == (name in NON_KEY_SETTINGS), name
    # camera, scene, light scales and extra emitters are in the key too
    assert cache_key(base.cache_inputs(camera(width=65), digest)) != k0
    assert cache_key(base.cache_inputs(cam, "e" * 64)) != k0
    assert cache_key(base.cache_inputs(cam, digest, env_scale=0.5)) != k0
    assert cache_key(base.cache_inputs(cam, digest, extra_emitters={"p": {"type": "point",
                                                                            "position": [0, 0, 1]}})) != k0


def test_object_poses_change_the_scene_digest():
    from sim.render.scene import describe_world

    w = tiny_world()
    d0 = describe_world(w).digest()
    assert describe_world(w).digest() == d0
    w.model.body_pos[1] += [0.001, 0, 0]  # the glass box moves 1 mm
    assert describe_world(w).digest() != d0
    assert describe_world(w, layout_seed=99).digest() != describe_world(w).digest()
    # the appearance seed (table texture, lights) reaches the scene and so the key
    from sim.render import MitsubaRenderer

    a, b = MitsubaRenderer(w, FAST), MitsubaRenderer(w, FAST, appearance_seed=99)
    assert a.scene()[1].lighting.params != b.scene()[1].lighting.params


def test_mismatched_entry_is_refused_with_a_warning(tmp_path, caplog):
    cache = RenderCache(tmp_path)
    a = {"settings": {"spp": 16}, "camera": np.eye(3)}
    b = {"settings": {"spp": 32}, "camera": np.eye(3)}
    key = cache_key(a)
    cache.put(key, a, {"rgb": np.full((2, 2, 3), 7, np.uint8)})
    assert cache.get(key, a)["rgb"][0, 0, 0] == 7
    with caplog.at_level(logging.WARNING):
        assert cache.get(key, b) is None  # same key file, other settings: never reused
    assert "other inputs" in caplog.text
    assert cache.get("0" * 64, a) is None


def test_renderer_hits_the_cache_and_refuses_a_tampered_entry(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path))
    assert cache_root() == tmp_path
    w, cams = tiny_world(), [camera(width=32, height=24), camera(eye=(-0.2, -0.2, 0.3), width=32, height=24)]
    r = MitsubaRenderer(w, FAST)
    first = r.render(cams)
    assert r.stats == {"rendered": 2, "cache_hits": 0, "render_s": pytest.approx(r.stats["render_s"])}
    again = MitsubaRenderer(w, FAST).render(cams)
    assert all(v.info["cache_hit"] for v in again)
    for a, b in zip(first, again, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.instance, b.instance)
    # an entry whose stored settings differ from the request (e.g. written by another version) is not used
    metas = sorted((tmp_path / "renders").rglob("*.json"))
    assert len(metas) == 2
    doc = json.loads(metas[0].read_text())
    doc["inputs"]["settings"]["spp"] = 999
    metas[0].write_text(json.dumps(doc))
    r2 = MitsubaRenderer(w, FAST)
    with caplog.at_level(logging.WARNING):
        r2.render(cams)
    assert r2.stats["rendered"] == 1 and r2.stats["cache_hits"] == 1
    # other settings render anew
    r3 = MitsubaRenderer(w, dataclasses.replace(FAST, spp=16))
    r3.render(cams[:1])
    assert r3.stats["rendered"] == 1


def test_canonical_form_hashes_arrays_and_refuses_unknown_objects():
    big = np.arange(100.0)
    assert canonical({"a": big}) == canonical({"a": big.copy()})
    assert canonical({"a": big}) != canonical({"a": big + 1})
    with pytest.raises(TypeError):
        canonical({"a": object()})


def test_ldsampler_sample_counts_are_validated():
    from torm.errors import ConfigError

    with pytest.raises(ConfigError, match="square power of two"):
        PbrSettings(spp=8)
    assert PbrSettings(spp=8, sampler="independent").spp == 8
