"""Grounding DINO and SAM built with ``transformers`` (tiny configs of the published classes, random weights)
export to torm's ONNX signatures and run through torm's grounded_sam segmenter on a committed render; the
exported graphs reproduce PyTorch; a file of the wrong kind gets the named signature error."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("transformers")  # the dev extra (and torm[models]) install it

from torm.cli import main  # noqa: E402
from torm.errors import ModelFileError  # noqa: E402
from torm.segmentation.export import load_models  # noqa: E402
from torm.segmentation.grounded_sam import GroundedSAMConfig, GroundedSAMSegmenter  # noqa: E402

RENDER = Path(__file__).resolve().parent / "data" / "learned_seg_view.png"  # a committed PBR render, 320x192


def _cfg(folder: Path) -> dict:
    """The exported grounded_sam.yaml with its paths (relative to the file's folder) resolved, as torm loads it."""
    from torm.segmentation import resolve_config_paths

    path = folder / "grounded_sam.yaml"
    return resolve_config_paths("grounded_sam", yaml.safe_load(path.read_text()), path)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("gsam")
    assert main(["-q", "export-models", "--out", str(out), "--random-weights", "--tiny", "--image-hw", "128",
                 "160"]) == 0
    return out


def test_export_writes_models_cards_and_a_config(exported):
    cfg = _cfg(exported)
    for key in ("gdino_model", "sam_encoder", "sam_decoder", "bert_vocab"):
        assert Path(cfg[key]).is_file(), key
    card = json.loads((exported / "grounding_dino.onnx.json").read_text())
    assert card["opset"] == 17 and len(card["sha256"]) == 64 and card["licence"] == "Apache-2.0"
    assert card["inputs"]["img"] == [1, 3, 128, 160] and card["inputs"]["text_token_mask"][1:] == [32, 32]
    assert card["max_tokens"] == 32 and card["random_weights"] is True and card["source_files_sha256"] is None
    raw = yaml.safe_load((exported / "grounded_sam.yaml").read_text())
    assert raw["gdino_model"] == "grounding_dino.onnx" and raw["bert_vocab"] == "vocab.txt"  # relative to the YAML
    assert card["vocab_size"] == 30522 and card["vocab_file"] == "vocab.txt"
    import hashlib

    assert card["vocab_sha256"] == hashlib.sha256((exported / "vocab.txt").read_bytes()).hexdigest()
    assert card["special_token_ids"] == {"[PAD]": 0, "[CLS]": 101, "[SEP]": 102, ".": 1012}
    for name in ("sam_encoder.onnx.json", "sam_decoder.onnx.json"):
        assert json.loads((exported / name).read_text())["random_weights"] is True


def test_exported_models_segment_a_render_through_torm(exported):
    cfg = _cfg(exported)
    seg = GroundedSAMSegmenter(GroundedSAMConfig(**cfg, box_threshold=0.0, text_threshold=0.0, max_detections=3))
    rgb = cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB)
    timings: dict[str, float] = {}
    mask, dets = seg.segment_image(rgb, timings)  # random weights: the masks mean nothing, the plumbing is real
    assert mask.shape == rgb.shape[:2] and mask.dtype == np.int32 and 1 <= len(dets) <= 3
    assert set(timings) >= {"gdino", "sam_encoder", "sam_decoder"}


def test_exported_graphs_reproduce_pytorch(exported):
    import onnxruntime as ort
    import torch

    from torm.segmentation.tokenizer import WordPieceTokenizer, grounding_text_inputs

    g, s = load_models(random_weights=True, tiny=True)  # the same seeded weights the export used
    cfg = _cfg(exported)
    t = grounding_text_inputs(WordPieceTokenizer.from_file(cfg["bert_vocab"]), cfg["prompt"], pad_to=32)
    img = np.random.default_rng(1).normal(size=(1, 3, 128, 160)).astype(np.float32)
    feeds = {"img": img, "input_ids": t.input_ids, "attention_mask": t.attention_mask,
             "position_ids": t.position_ids, "token_type_ids": t.token_type_ids,
             "text_token_mask": t.self_attention_mask}
    logits, boxes = ort.InferenceSession(cfg["gdino_model"]).run(None, feeds)
    from torm.segmentation.export import _gdino_wrapper

    with torch.no_grad():
        ref = _gdino_wrapper(g)(*(torch.from_numpy(np.asarray(feeds[k])) for k in feeds))
    np.testing.assert_allclose(logits, ref[0].numpy(), atol=1e-4)
    np.testing.assert_allclose(boxes, ref[1].numpy(), atol=1e-4)
    # the decoder with a box prompt (labels 2, 3) is transformers' SamModel(input_boxes=...)
    emb = np.random.default_rng(2).normal(size=(1, 256, 64, 64)).astype(np.float32)
    box = np.array([100.0, 150.0, 400.0, 380.0], np.float32)
    masks, iou, low = ort.InferenceSession(cfg["sam_decoder"]).run(None, {
        "image_embeddings": emb, "point_coords": box.reshape(1, 2, 2),
        "point_labels": np.array([[2.0, 3.0]], np.float32),
        "mask_input": np.zeros((1, 1, 256, 256), np.float32), "has_mask_input": np.zeros(1, np.float32),
        "orig_im_size": np.array([768.0, 1024.0], np.float32)})
    with torch.no_grad():
        r = s(image_embeddings=torch.from_numpy(emb), input_boxes=torch.from_numpy(box)[None, None],
              multimask_output=False)
    assert masks.shape == (1, 1, 768, 1024)
    np.testing.assert_allclose(low, r.pred_masks[:, 0].numpy(), atol=1e-5)
    np.testing.assert_allclose(iou, r.iou_scores[:, 0].numpy(), atol=1e-5)


def test_a_file_of_the_wrong_kind_names_the_expected_signature(exported):
    cfg = _cfg(exported)
    cfg["gdino_model"] = cfg["sam_encoder"]
    with pytest.raises(ModelFileError, match=r"grounded_sam.gdino_model .*input_ids"):
        GroundedSAMSegmenter(GroundedSAMConfig(**cfg))


def test_hybrid_prompting_learned_boxes_prompt_sam(exported):
    """box_source: learned: the learned segmenter's instances prompt SAM (no Grounding DINO, no vocabulary)."""
    cfg = _cfg(exported)
    seg = GroundedSAMSegmenter(GroundedSAMConfig(sam_encoder=cfg["sam_encoder"], sam_decoder=cfg["sam_decoder"],
                                                 box_source="learned"))
    rgb = cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB)
    boxes = seg.detect(rgb)
    from torm.segmentation.learned import LearnedSegmenter

    _, learned = LearnedSegmenter().segment_image(rgb)
    top = sorted(learned, key=lambda d: -d.score)[: seg.config.max_detections]  # the most confident instances
    assert len(top) >= 1 and len(boxes.scores_n) == len(top)
    np.testing.assert_allclose(boxes.boxes_nx4, [d.box_xyxy for d in top])
    mask, dets = seg.segment_image(rgb, {})
    assert mask.shape == rgb.shape[:2] and len(dets) == len(top)
    with pytest.raises(Exception, match="box_source"):
        GroundedSAMConfig(sam_encoder="x", sam_decoder="y", box_source="yolo")


@pytest.fixture(scope="module")
def exported_sam2(tmp_path_factory):
    """SAM 2 (tiny config of transformers' Sam2Model, random weights) without Grounding DINO."""
    out = tmp_path_factory.mktemp("sam2")
    assert main(["-q", "export-models", "--out", str(out), "--random-weights", "--tiny", "--sam-kind", "sam2",
                 "--boxes", "learned"]) == 0
    return out


def test_sam2_exports_run_through_torm_with_learned_boxes(exported_sam2):
    cfg = _cfg(exported_sam2)
    assert cfg["box_source"] == "learned" and "gdino_model" not in cfg
    card = json.loads((exported_sam2 / "sam2_encoder.onnx.json").read_text())
    assert card["sam_kind"] == "sam2" and card["source"] == "facebook/sam2.1-hiera-tiny"
    seg = GroundedSAMSegmenter(GroundedSAMConfig(**cfg))
    assert seg.sam_kind == "sam2"
    rgb = cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB)
    timings: dict[str, float] = {}
    mask, dets = seg.segment_image(rgb, timings)
    assert mask.shape == rgb.shape[:2] and len(dets) >= 1 and set(timings) >= {"sam_encoder", "sam_decoder"}


def test_sam2_graphs_reproduce_pytorch(exported_sam2):
    import onnxruntime as ort
    import torch

    from torm.segmentation.export import load_sam2
    from torm.segmentation.grounded_sam import sam2_box_prompt, sam2_preprocess

    m = load_sam2(random_weights=True, tiny=True)  # the same seeded weights the export used
    rgb = cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB)
    x = sam2_preprocess(rgb)
    emb, s0, s1 = ort.InferenceSession(str(exported_sam2 / "sam2_encoder.onnx")).run(None, {"image": x})
    with torch.no_grad():
        r0, r1, re = m.get_image_embeddings(torch.from_numpy(x))
    for a, b in ((emb, re), (s0, r0), (s1, r1)):
        np.testing.assert_allclose(a, b.numpy(), atol=1e-4)
    coords, labels = sam2_box_prompt(np.array([60.0, 40.0, 200.0, 150.0]), rgb.shape[:2])
    masks, iou, low = ort.InferenceSession(str(exported_sam2 / "sam2_decoder.onnx")).run(None, {
        "image_embeddings": emb, "high_res_feats_0": s0, "high_res_feats_1": s1, "point_coords": coords,
        "point_labels": labels, "mask_input": np.zeros((1, 1, 256, 256), np.float32),
        "has_mask_input": np.zeros(1, np.float32), "orig_im_size": np.array(rgb.shape[:2], np.float32)})
    with torch.no_grad():  # SAM 2's predictor: box corners as points labelled 2 and 3
        r = m(image_embeddings=[torch.from_numpy(a) for a in (s0, s1, emb)],
              input_points=torch.from_numpy(coords)[:, None], input_labels=torch.tensor([[[2, 3]]]),
              multimask_output=False)
    assert masks.shape == (1, 1, *rgb.shape[:2])
    np.testing.assert_allclose(low, r.pred_masks[:, 0].numpy(), atol=1e-5)
    np.testing.assert_allclose(iou, r.iou_scores[:, 0].numpy(), atol=1e-5)


def test_a_sam_encoder_with_a_sam2_decoder_is_a_named_error(exported, exported_sam2):
    sam1 = _cfg(exported)
    sam2 = _cfg(exported_sam2)
    with pytest.raises(ModelFileError, match="SAM encoder but the decoder .* is a SAM 2 decoder.*--sam-kind"):
        GroundedSAMSegmenter(GroundedSAMConfig(sam_encoder=sam1["sam_encoder"], sam_decoder=sam2["sam_decoder"],
                                               box_source="learned"))
