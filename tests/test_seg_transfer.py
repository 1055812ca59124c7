"""Segmenter v4 machinery (issue 43): sensor effects and magnification, opaque look-alikes in PBR scenes, glass-only
labels, per-shard renderer draws, few-shot fine-tuning on labelled real frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from torm.errors import ConfigError

FRAME = Path(__file__).parent / "data" / "cleargrasp_000000080"


def test_zoom_magnifies_image_and_targets_together_and_scales_offsets():
    from torm.segmentation.training.augment import zoom

    h, w = 64, 96
    yy, xx = np.mgrid[0:h, 0:w]
    mask = ((yy // 8 + xx // 8) % 2).astype(np.float32)  # 8 px checker: registration is visible everywhere
    img = np.repeat((20.0 + 180.0 * mask)[..., None], 3, axis=2).astype(np.float32)
    tgt = np.stack([mask, np.zeros_like(mask), np.zeros_like(mask), np.full_like(mask, 3.0), np.full_like(mask, -2.0)])
    img2, tgt2 = zoom(img, tgt, 2.0, np.random.default_rng(0), offset_channels=(3, 4))
    assert img2.shape == img.shape and tgt2.shape == tgt.shape
    fg = tgt2[0] > 0.5
    assert np.mean(img2[..., 0][fg] > 100) > 0.9 and np.mean(img2[..., 0][~fg] < 120) > 0.9  # registered
    # cells are 16 px wide now: runs of equal labels along a row are twice as long
    runs = np.diff(np.flatnonzero(np.diff(tgt2[0, h // 2]) != 0))
    assert np.median(runs) == 16
    assert np.allclose(tgt2[3], 6.0) and np.allclose(tgt2[4], -4.0)  # offsets (px) magnified with the image
    same_img, same_t = zoom(img, tgt, 1.0, np.random.default_rng(0))
    assert same_img is img and same_t is tgt


def test_sensor_effects_at_strength_zero_leave_the_image_and_at_one_change_it():
    from torm.segmentation.training.augment import SENSOR_RANGES, sensor_effects

    rng = np.random.default_rng(1)
    img = rng.uniform(0, 255, (48, 64, 3)).astype(np.float32)
    out, applied = sensor_effects(img, rng, strength=0.0)
    assert applied == {} and np.abs(out - img).max() < 0.05  # sRGB -> linear -> sRGB round trip only
    seen: set[str] = set()
    for _ in range(30):
        out, applied = sensor_effects(img, rng, strength=1.0)
        assert out.shape == img.shape and out.dtype == np.float32 and out.min() >= 0 and out.max() <= 255
        seen |= set(applied)
        for k, v in applied.items():
            lo, hi, _p = SENSOR_RANGES[k]
            assert lo <= v <= hi
    assert seen == set(SENSOR_RANGES)  # every effect fires somewhere in 30 draws


def test_train_config_rejects_bad_v4_augmentation():
    from torm.segmentation.training.train import TrainConfig

    with pytest.raises(ConfigError, match="zoom_range"):
        TrainConfig(zoom_range=(0.5, 2.0))
    with pytest.raises(ConfigError, match="sensor_effects"):
        TrainConfig(sensor_effects=1.5)


def test_footprints_and_placement_keep_distractors_clear_of_objects():
    from torm.segmentation.training.clutter import GAP_M, Footprint, place

    a, b = Footprint((0.0, 0.0), 0.05), Footprint((0.1 + GAP_M, 0.0), 0.05)
    assert a.clear_of(b) and not a.clear_of(Footprint((0.09, 0.0), 0.05))
    rng = np.random.default_rng(0)
    taken = [Footprint((0.55, 0.0), 0.05)]
    for _ in range(20):
        fp = place(0.03, taken, (0.55, 0.0), rng)
        assert fp is not None and all(fp.clear_of(t) for t in taken)
        taken.append(fp)
    assert place(1.0, taken, (0.55, 0.0), rng) is None  # nothing that large fits


def test_distractor_meshes_rest_on_the_table_and_twins_copy_glass_shapes():
    from torm.segmentation.training.clutter import KINDS, distractor_mesh

    rng = np.random.default_rng(3)
    cube = (np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (0, 2)], float) * 0.02,
            np.array([[0, 1, 2]]))
    for kind in KINDS:
        v, f = distractor_mesh(kind, rng, [cube])
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # resting on z = 0
        assert np.allclose(0.5 * (v[:, :2].min(0) + v[:, :2].max(0)), 0.0, atol=1e-9)  # centred in x, y
        assert f.shape[1] == 3 and 0.005 < np.ptp(v, axis=0).max() < 0.4
    v, _ = distractor_mesh("twin", rng, [cube])
    assert len(v) == 8  # the twin is the glass mesh, rescaled


def test_recipe_validates_v4_fields_and_draws_one_renderer_per_shard():
    from torm.segmentation.training.dataset import DataRecipe, shard_renderer

    with pytest.raises(ConfigError, match="renderer_weights"):
        DataRecipe(renderer_weights={"blender": 1.0})
    with pytest.raises(ConfigError, match="distractor_fraction"):
        DataRecipe(distractor_fraction=1.5)
    with pytest.raises(ConfigError, match="distractors_per_scene"):
        DataRecipe(distractors_per_scene=(3, 1))
    assert shard_renderer(DataRecipe(), "train", 5) == "mujoco"
    r = DataRecipe(renderer_weights={"pbr": 0.7, "mujoco": 0.2, "pbr_scalar": 0.1})
    draws = [shard_renderer(r, "train", i) for i in range(400)]
    assert draws == [shard_renderer(r, "train", i) for i in range(400)]  # a pure function of the shard
    share = {k: draws.count(k) / 400 for k in ("pbr", "mujoco", "pbr_scalar")}
    assert abs(share["pbr"] - 0.7) < 0.08 and abs(share["mujoco"] - 0.2) < 0.07 and share["pbr_scalar"] > 0.04


def test_glass_only_labels_make_opaque_objects_background(tmp_path):
    import json

    from torm.segmentation.training.dataset import DataRecipe, generate_shard

    small = dict(renderer="mujoco", width=64, height=48, full_width=128, full_height=72, n_procedural=6,
                 scenes_per_shard=1, views_per_scene=2, library_fraction=1.0, objects_per_scene=(4, 6), seed=11)
    found = False
    for shard in range(8):  # draw until a scene holds the opaque cup beside glass
        z = np.load(generate_shard(DataRecipe(**small, label_opaque=False, shards={"train": 8}), "train", shard,
                                   tmp_path / "glass_only"))
        meta = json.loads(str(z["meta"]))["scenes"][0]
        if "opaque" not in meta["materials"]:
            continue
        found = True
        z_all = np.load(generate_shard(DataRecipe(**small, shards={"train": 8}), "train", shard, tmp_path / "all"))
        opaque_ids = [i + 1 for i, m in enumerate(meta["materials"]) if m == "opaque"]
        glass_ids = [i + 1 for i, m in enumerate(meta["materials"]) if m == "glass"]
        assert not np.isin(z["mask"], opaque_ids).any()
        assert np.array_equal(np.isin(z["mask"], glass_ids), np.isin(z_all["mask"], glass_ids))
        break
    assert found, "no scene of these 8 shards holds an opaque object beside glass"


def test_a_pbr_scene_with_look_alikes_labels_only_glass_and_occludes_exactly(tmp_path):
    """One tiny PBR render: distractors and room surfaces are in the image, id 0 in the masks; where a distractor
    stands in front of glass, the glass pixels behind it are background."""
    pytest.importorskip("mitsuba")
    from tests.render_helpers import one_glass_cylinder_view
    from torm.segmentation.training.render import SceneLook, render_pbr

    world, T, K = one_glass_cylinder_view(0.12)
    rgb_p, mask_p, _ = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4)
    rgb_c, mask_c, info = render_pbr(world, T[None], K[None], 80, 60, np.random.default_rng(0), spp=4,
                                     look=SceneLook(n_distractors=6, room=True, clutter_seed=5))
    assert info["distractors"] and info["room"]["walls"]
    assert set(np.unique(mask_c)) <= {0, 1} and (mask_c > 0).sum() <= (mask_p > 0).sum()
    assert np.abs(rgb_c.astype(int) - rgb_p.astype(int)).mean() > 1.0  # the clutter is visible


def _frames_folder(tmp_path: Path) -> Path:
    d = tmp_path / "frames"
    d.mkdir()
    for suffix in ("-transparent-rgb-img.jpg", "-mask.png"):
        shutil.copy(FRAME / f"000000080{suffix}", d / f"000000080{suffix}")
    return d


def test_finetune_folder_errors_name_the_problem_and_the_fix(tmp_path):
    import cv2

    from torm.segmentation.training.finetune import find_frames, instance_mask, load_labelled_frames

    with pytest.raises(ConfigError, match="does not exist"):
        find_frames(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    cv2.imwrite(str(tmp_path / "empty" / "a.jpg"), np.zeros((32, 48, 3), np.uint8))
    with pytest.raises(ConfigError, match="no frame with a mask.*masks/<name>.png"):
        find_frames(tmp_path / "empty")
    d = _frames_folder(tmp_path)
    assert [p.name for p, _ in find_frames(d)] == ["000000080-transparent-rgb-img.jpg"]
    cv2.imwrite(str(d / "000000080-mask.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ConfigError, match="must have their frame's size"):
        load_labelled_frames(d)
    # binary masks become connected components; id masks stay
    m = np.zeros((20, 20), np.uint8)
    m[2:6, 2:6] = 255
    m[10:15, 10:15] = 255
    assert instance_mask(m).max() == 2
    m[10:15, 10:15] = 7
    assert set(np.unique(instance_mask(m))) == {0, 7, 255}


def test_finetune_runs_exports_a_loadable_model_and_records_the_frames_it_saw(tmp_path):
    from torm.segmentation import make_segmenter
    from torm.segmentation.training.finetune import finetune

    d = _frames_folder(tmp_path)
    with pytest.raises(ConfigError, match="rehearsal_shards = -1 must be >= 0"):
        finetune(d, tmp_path / "bad.onnx", steps=2, rehearsal_shards=-1, progress=False)
    card = finetune(d, tmp_path / "ft.onnx", steps=2, threads=1, progress=False, rehearsal_shards=0)
    assert card["finetune"]["frames"][0]["image"] == "000000080-transparent-rgb-img.jpg"
    assert card["training"]["steps"] == 2 and card["validated_on"]["recorded"]["validated"] is False
    assert card["postprocess"]  # carried over from the base model's card
    seg = make_segmenter("learned", {"model": str(tmp_path / "ft.onnx"), "threads": 1})
    out = seg.segment_image(np.zeros((72, 128, 3), np.uint8))[0]
    assert out.shape == (72, 128)


def test_freeze_encoder_trains_only_the_decoder_and_fg_crop_bias_centres_windows_on_objects(tmp_path):
    import torch

    from torm.segmentation.training.targets import targets
    from torm.segmentation.training.train import Batcher, TrainConfig, train

    with pytest.raises(ConfigError, match="valid choices"):
        TrainConfig(freeze="decoder")
    with pytest.raises(ConfigError, match="fg_crop_bias"):
        TrainConfig(fg_crop_bias=1.5)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (2, 64, 128, 3), dtype=np.uint8)
    mask = np.zeros((2, 64, 128), np.uint8)
    mask[:, 40:48, 110:118] = 1  # one small object in a corner
    cfg = TrainConfig(channels=(4, 8), steps=3, batch_size=2, crop=(16, 16), lr=1e-2, val_every=3, freeze="encoder")
    torch.manual_seed(0)
    from torm.segmentation.training.model import SegUNet

    before = SegUNet(cfg.channels).state_dict()
    train(cfg, rgb, mask, rgb, mask, tmp_path / "w", progress=False)
    after = torch.load(tmp_path / "w" / "checkpoint.pt", weights_only=False)["model"]
    changed = {k for k in before if not torch.equal(before[k], after[k]) and "running" not in k}
    assert changed and all(k.startswith(("up.", "head.")) for k in changed)  # the encoder ("down.") kept its weights
    # windows centred on the object: with bias 1 every 16x16 window holds object pixels, without it few do
    tgt = targets(mask, 1)
    biased = Batcher(rgb, tgt, TrainConfig(crop=(16, 16), batch_size=64, fg_crop_bias=1.0), np.random.default_rng(1))
    plain = Batcher(rgb, tgt, TrainConfig(crop=(16, 16), batch_size=64), np.random.default_rng(1))
    hit_b = (biased.sample()[1][:, 0].sum((1, 2)) > 0).float().mean()
    hit_p = (plain.sample()[1][:, 0].sum((1, 2)) > 0).float().mean()
    assert hit_b == 1.0 and hit_p < 0.3


def test_onnx_sessions_take_the_benchmark_workers_thread_share(monkeypatch):
    from torm.segmentation.onnx_models import session_threads

    monkeypatch.delenv("TORM_THREADS", raising=False)
    assert session_threads(0) == 0 and session_threads(3) == 3
    monkeypatch.setenv("TORM_THREADS", "1")
    assert session_threads(0) == 1 and session_threads(2) == 2  # an explicit count wins


def test_rehearsal_draws_part_of_every_batch_from_the_renders(tmp_path):
    import torch

    from torm.segmentation.training import train as tr

    rng = np.random.default_rng(0)
    real = rng.integers(0, 255, (2, 48, 96, 3), dtype=np.uint8)
    real_mask = np.zeros((2, 48, 96), np.uint8)
    real_mask[:, 10:20, 10:20] = 1
    old = np.full((3, 32, 64, 3), 7, np.uint8)  # renders: another size, one flat grey
    old_mask = np.zeros((3, 32, 64), np.uint8)
    with pytest.raises(ConfigError, match="rehearsal_fraction"):
        tr.TrainConfig(rehearsal_fraction=1.0)
    cfg = tr.TrainConfig(channels=(4, 8), steps=1, batch_size=4, crop=(48, 64), val_every=1, rehearsal_fraction=0.5)
    with pytest.raises(ConfigError, match="no rehearsal views"):
        tr.train(cfg, real, real_mask, real, real_mask, tmp_path / "a", progress=False)
    seen = []
    real_fn = tr.loss_fn

    def spy(logits, tgt, c):
        seen.append(logits.shape)
        return real_fn(logits, tgt, c)

    orig_norm = tr.normalise
    inputs = []
    tr.loss_fn = spy
    tr.normalise = lambda x: inputs.append(x.clone()) or orig_norm(x)
    try:
        tr.train(cfg, real, real_mask, real, real_mask, tmp_path / "b", progress=False, rehearsal=(old, old_mask))
    finally:
        tr.loss_fn, tr.normalise = real_fn, orig_norm
    assert seen[0][0] == 4 and tuple(seen[0][2:]) == (32, 64)  # windows shrink to fit the smaller renders
    flat = torch.stack([(x.amax((0, 1, 2)) - x.amin((0, 1, 2))) for x in inputs[0]])
    assert int((flat < 60).sum()) == 2  # two of four samples are the flat renders (sensor noise aside)
