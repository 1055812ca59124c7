"""Grounded-SAM on onnxruntime, driven end to end by tiny ONNX models built here with onnx.helper.

The fake Grounding DINO outputs constant boxes/logits (with duplicates NMS must remove, a low score,
a whole-image box and a padding-column logit that must all be dropped) plus a term that is zero only
when the text inputs and the image tensor are exactly what the official preprocessing produces. The
fake SAM decoder returns the box prompt rectangle (with a hole and a far 3x3 speck) at the original
image size, so the expected instance masks are known exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from torm.errors import CaptureError, ModelFileError, UnknownNameError
from torm.segmentation import make_segmenter
from torm.segmentation.grounded_sam import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    GroundedSAMConfig,
    gdino_resize_hw,
    sam_resize_hw,
    select_sam_mask,
)
from torm.types import CameraView, Capture

VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "?", "clear", "glass", "trans", "##par", "##ent", "object", "##s"]
PROMPT = "clear glass. transparent object."
H, W = 192, 256  # SAM scale 4 exactly; Grounding DINO input 800 x 1066
Q, L = 900, 256


def _sig(x: float) -> float:
    return 1.0 / (1.0 + np.exp(-x))


def _save(graph, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _const(name: str, arr: np.ndarray):
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(arr), name + "_v"))


def _gdino_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    logits = np.full((1, Q, L), -10.0, np.float32)
    boxes = np.tile(np.array([0.5, 0.5, 0.1, 0.1], np.float32), (1, Q, 1))
    # q0: "clear glass", box x 48..80, y 72..120 (pixels of the 256 x 192 image)
    logits[0, 0, 1], logits[0, 0, 2] = 3.0, 2.0
    boxes[0, 0] = [0.25, 0.5, 0.125, 0.25]
    # q1: near-duplicate of q0 with a lower score -> removed by NMS
    logits[0, 1, 1] = 2.0
    boxes[0, 1] = [0.26, 0.5, 0.125, 0.25]
    # q2: "transparent object", box x 160..208, y 48..96; '.' and [SEP] above text_threshold are not phrase words
    logits[0, 2, 4:7] = 2.5
    logits[0, 2, 7] = 1.0
    logits[0, 2, 8] = 0.5
    logits[0, 2, 9] = 0.8
    boxes[0, 2] = [0.71875, 0.375, 0.1875, 0.25]
    # q3: below box_threshold
    logits[0, 3, 1] = -1.0
    boxes[0, 3] = [0.5, 0.8, 0.1, 0.1]
    # q4: the whole image (a table-like box) -> dropped by max_box_fraction
    logits[0, 4, 1] = 2.2
    boxes[0, 4] = [0.5, 0.5, 1.0, 1.0]
    # q5: high logit only in a column beyond the text -> ignored
    logits[0, 5, 40] = 5.0
    boxes[0, 5] = [0.1, 0.1, 0.1, 0.1]
    onehot = np.zeros((1, Q, L), np.float32)
    onehot[0, 0, 1] = 1.0
    return logits, boxes, onehot


def build_gdino(path: Path, static_T: int | None, expected_mask_sum: float, img_hw: tuple[int, int],
                img_mean: float, names: tuple[str, str] = ("img", "text_token_mask"), check: bool = True) -> Path:
    logits, boxes, onehot = _gdino_tables()
    T = static_T if static_T else "T"
    inputs = [
        helper.make_tensor_value_info(names[0], TensorProto.FLOAT, [1, 3, "h", "w"]),
        helper.make_tensor_value_info("input_ids", TensorProto.INT64, [1, T]),
        helper.make_tensor_value_info("attention_mask", TensorProto.BOOL, [1, T]),
        helper.make_tensor_value_info("position_ids", TensorProto.INT64, [1, T]),
        helper.make_tensor_value_info("token_type_ids", TensorProto.INT64, [1, T]),
        helper.make_tensor_value_info(names[1], TensorProto.BOOL, [1, T, T]),
    ]
    outputs = [helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, Q, L]),
               helper.make_tensor_value_info("boxes", TensorProto.FLOAT, [1, Q, 4])]
    # check = (sum(position_ids) - 13) + (sum(text mask) - expected) + (sum(shape(img)) - expected)
    #         + 10 * (mean(img) - expected) + sum(attention_mask) - 10 ; it is added to q0's winning logit
    nodes = [
        _const("C", logits), _const("B", boxes), _const("E", onehot),
        helper.make_node("Cast", ["position_ids"], ["pf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceSum", ["pf"], ["ps"], keepdims=0),
        _const("p_exp", np.array(13.0, np.float32)),
        helper.make_node("Sub", ["ps", "p_exp"], ["d1"]),
        helper.make_node("Cast", [names[1]], ["mf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceSum", ["mf"], ["ms"], keepdims=0),
        _const("m_exp", np.array(expected_mask_sum, np.float32)),
        helper.make_node("Sub", ["ms", "m_exp"], ["d2"]),
        helper.make_node("Shape", [names[0]], ["shp"]),
        helper.make_node("Cast", ["shp"], ["shpf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceSum", ["shpf"], ["ss"], keepdims=0),
        _const("s_exp", np.array(1 + 3 + img_hw[0] + img_hw[1], np.float32)),
        helper.make_node("Sub", ["ss", "s_exp"], ["d3"]),
        helper.make_node("ReduceMean", [names[0]], ["im"], keepdims=0),
        _const("i_exp", np.array(img_mean, np.float32)),
        helper.make_node("Sub", ["im", "i_exp"], ["d4a"]),
        _const("hundred", np.array(10.0, np.float32)),
        helper.make_node("Mul", ["d4a", "hundred"], ["d4"]),
        helper.make_node("Cast", ["attention_mask"], ["af"], to=TensorProto.FLOAT),
        helper.make_node("ReduceSum", ["af"], ["as"], keepdims=0),
        _const("a_exp", np.array(10.0, np.float32)),
        helper.make_node("Sub", ["as", "a_exp"], ["d5"]),
        helper.make_node("Sum", ["d1", "d2", "d3", "d4", "d5"], ["d"]),
        _const("zero_d", np.array(0.0, np.float32)),
        helper.make_node("Mul", ["E", "d" if check else "zero_d"], ["Ed"]),
        helper.make_node("Add", ["C", "Ed"], ["logits"]),
        helper.make_node("Identity", ["B"], ["boxes"]),
    ]
    return _save(helper.make_graph(nodes, "fake_gdino", inputs, outputs), path)


def build_sam_encoder(path: Path) -> Path:
    inputs = [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 1024, 1024])]
    outputs = [helper.make_tensor_value_info("image_embeddings", TensorProto.FLOAT, [1, 256, 64, 64])]
    nodes = [
        helper.make_node("AveragePool", ["image"], ["pooled"], kernel_shape=[16, 16], strides=[16, 16]),
        _const("Wc", np.full((256, 3, 1, 1), 1.0 / 3.0, np.float32)),
        helper.make_node("Conv", ["pooled", "Wc"], ["image_embeddings"]),
    ]
    return _save(helper.make_graph(nodes, "fake_sam_encoder", inputs, outputs), path)


def build_sam_decoder(path: Path, coords_name: str = "point_coords") -> Path:
    f = TensorProto.FLOAT
    inputs = [
        helper.make_tensor_value_info("image_embeddings", f, [1, 256, 64, 64]),
        helper.make_tensor_value_info(coords_name, f, [1, "N", 2]),
        helper.make_tensor_value_info("point_labels", f, [1, "N"]),
        helper.make_tensor_value_info("mask_input", f, [1, 1, 256, 256]),
        helper.make_tensor_value_info("has_mask_input", f, [1]),
        helper.make_tensor_value_info("orig_im_size", f, [2]),
    ]
    outputs = [
        helper.make_tensor_value_info("masks", f, [1, 1, "H", "W"]),
        helper.make_tensor_value_info("iou_predictions", f, [1, 1]),
        helper.make_tensor_value_info("low_res_masks", f, [1, 1, 256, 256]),
    ]

    def scalar(name, v):
        return _const(name, np.array(v, np.float32))

    def idx(name, v):
        return _const(name, np.array(v, np.int64))

    nodes = [
        idx("i0", 0), idx("i1", 1), idx("i2", 2), idx("i3", 3),
        helper.make_node("Gather", ["orig_im_size", "i0"], ["Hs"]),
        helper.make_node("Gather", ["orig_im_size", "i1"], ["Ws"]),
        helper.make_node("ReduceMax", ["orig_im_size"], ["mx"], keepdims=0),
        scalar("long", 1024.0),
        helper.make_node("Div", ["long", "mx"], ["scale"]),
        _const("shape4", np.array([-1], np.int64)),
        helper.make_node("Reshape", [coords_name, "shape4"], ["flat"]),  # x1 y1 x2 y2 (first two points)
        helper.make_node("Div", ["flat", "scale"], ["flat_px"]),
        helper.make_node("Gather", ["flat_px", "i0"], ["x1"]),
        helper.make_node("Gather", ["flat_px", "i1"], ["y1"]),
        helper.make_node("Gather", ["flat_px", "i2"], ["x2"]),
        helper.make_node("Gather", ["flat_px", "i3"], ["y2"]),
        scalar("zero", 0.0), scalar("one", 1.0), scalar("half", 0.5), scalar("pt4", 0.4), scalar("three", 3.0),
        helper.make_node("Range", ["zero", "Ws", "one"], ["xr"]),
        helper.make_node("Range", ["zero", "Hs", "one"], ["yr"]),
        helper.make_node("Add", ["xr", "half"], ["xs"]),
        helper.make_node("Add", ["yr", "half"], ["ys"]),
    ]

    def inside(out, v, lo, hi):
        return [helper.make_node("GreaterOrEqual", [v, lo], [out + "_a"]),
                helper.make_node("LessOrEqual", [v, hi], [out + "_b"]),
                helper.make_node("And", [out + "_a", out + "_b"], [out])]

    nodes += inside("inx", "xs", "x1", "x2") + inside("iny", "ys", "y1", "y2")
    # hole = central 20 % of the box
    nodes += [
        helper.make_node("Sub", ["x2", "x1"], ["bw"]), helper.make_node("Sub", ["y2", "y1"], ["bh"]),
        helper.make_node("Mul", ["bw", "pt4"], ["bw4"]), helper.make_node("Mul", ["bh", "pt4"], ["bh4"]),
        helper.make_node("Add", ["x1", "bw4"], ["hx1"]), helper.make_node("Sub", ["x2", "bw4"], ["hx2"]),
        helper.make_node("Add", ["y1", "bh4"], ["hy1"]), helper.make_node("Sub", ["y2", "bh4"], ["hy2"]),
    ]
    nodes += inside("hinx", "xs", "hx1", "hx2") + inside("hiny", "ys", "hy1", "hy2")
    nodes += [
        helper.make_node("Less", ["xs", "three"], ["sx"]), helper.make_node("Less", ["ys", "three"], ["sy"]),
        _const("ax0", np.array([0], np.int64)), _const("ax1", np.array([1], np.int64)),
    ]
    for name in ("inx", "hinx", "sx"):
        nodes.append(helper.make_node("Unsqueeze", [name, "ax0"], [name + "_r"]))
    for name in ("iny", "hiny", "sy"):
        nodes.append(helper.make_node("Unsqueeze", [name, "ax1"], [name + "_c"]))
    nodes += [
        helper.make_node("And", ["iny_c", "inx_r"], ["rect"]),
        helper.make_node("And", ["hiny_c", "hinx_r"], ["hole"]),
        helper.make_node("And", ["sy_c", "sx_r"], ["speck"]),
        helper.make_node("Not", ["hole"], ["nothole"]),
        helper.make_node("And", ["rect", "nothole"], ["ring"]),
        helper.make_node("Or", ["ring", "speck"], ["fg"]),
        scalar("pos", 10.0), scalar("neg", -10.0),
        helper.make_node("Where", ["fg", "pos", "neg"], ["m2"]),
        _const("ax01", np.array([0, 1], np.int64)),
        helper.make_node("Unsqueeze", ["m2", "ax01"], ["masks"]),
        _const("iou_c", np.array([[0.9]], np.float32)),
        helper.make_node("Identity", ["iou_c"], ["iou_predictions"]),
        helper.make_node("Identity", ["mask_input"], ["low_res_masks"]),
    ]
    return _save(helper.make_graph(nodes, "fake_sam_decoder", inputs, outputs), path)


def _grey_mean() -> float:
    return float(np.mean((128 / 255.0 - IMAGENET_MEAN) / IMAGENET_STD))


def _models(tmp: Path, static_T: int | None = None) -> dict[str, str]:
    (tmp / "vocab.txt").write_text("\n".join(VOCAB) + "\n")
    pads = (static_T - 10) if static_T else 0
    img_hw = gdino_resize_hw(H, W)
    return {
        "gdino_model": str(build_gdino(tmp / "gdino.onnx", static_T, 36.0 + pads, img_hw, _grey_mean())),
        "bert_vocab": str(tmp / "vocab.txt"),
        "sam_encoder": str(build_sam_encoder(tmp / "sam_enc.onnx")),
        "sam_decoder": str(build_sam_decoder(tmp / "sam_dec.onnx")),
        "prompt": PROMPT,
        "providers": ["CPUExecutionProvider"],
        "threads": 1,
    }


def _capture(n_views: int = 2) -> Capture:
    K = np.array([[200.0, 0, W / 2], [0, 200.0, H / 2], [0, 0, 1]])
    rgb = np.full((H, W, 3), 128, np.uint8)
    return Capture(views=tuple(CameraView(K=K, T_world_cam=np.eye(4), rgb=rgb, name=f"v{i}") for i in range(n_views)))


def _rect(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_resize_rules_match_the_official_transforms():
    assert gdino_resize_hw(192, 256) == (800, 1066)
    assert gdino_resize_hw(720, 1280) == (750, 1333)  # capped by max_size 1333
    assert gdino_resize_hw(800, 600) == (1066, 800)
    assert sam_resize_hw(192, 256) == (768, 1024)
    assert sam_resize_hw(720, 1280) == (576, 1024)


@pytest.mark.parametrize("static_T", [None, 16])
def test_pipeline_gives_known_boxes_phrases_and_masks(tmp_path, static_T):
    seg = make_segmenter("grounded_sam", _models(tmp_path, static_T))
    result = seg.segment(_capture(2))
    assert result.masks_vxhxw.shape == (2, H, W)
    for v in range(2):
        dets = result.detections[v]
        assert [d.label for d in dets] == ["clear glass", "transparent object"]
        np.testing.assert_allclose([d.score for d in dets], [_sig(3.0), _sig(2.5)], atol=2e-5)
        np.testing.assert_allclose(dets[0].box_xyxy, [48, 72, 80, 120], atol=1e-3)
        np.testing.assert_allclose(dets[1].box_xyxy, [160, 48, 208, 96], atol=1e-3)
        assert [d.instance_id for d in dets] == [1, 2]
        m = result.masks_vxhxw[v]
        # rectangles with their holes filled and the 3x3 speck at the corner removed
        np.testing.assert_array_equal(m == 1, _rect(72, 120, 48, 80))
        np.testing.assert_array_equal(m == 2, _rect(48, 96, 160, 208))
        assert set(np.unique(m)) == {0, 1, 2}
    assert {"gdino", "sam_encoder", "sam_decoder", "postprocess", "total"} <= set(result.timings)
    assert result.apply(_capture(2)).masks().shape == (2, H, W)


def test_post_processing_switches_change_the_mask(tmp_path):
    cfg = dict(_models(tmp_path), fill_holes=False, min_blob_area_px=0)
    m = make_segmenter("grounded_sam", cfg).segment(_capture(1)).masks_vxhxw[0]
    assert m[95, 64] == 0  # hole at the centre of box 1 kept
    assert m[1, 1] == 1  # the speck joins the highest-scoring instance's mask
    ring = _rect(72, 120, 48, 80) & ~_rect(91, 101, 61, 67)
    speck = _rect(0, 3, 0, 3)
    np.testing.assert_array_equal(m == 1, ring | speck)
    cfg = dict(_models(tmp_path), fill_holes=False, min_blob_area_px=0, keep_largest_component=True)
    m = make_segmenter("grounded_sam", cfg).segment(_capture(1)).masks_vxhxw[0]
    np.testing.assert_array_equal(m == 1, ring)


def test_thresholds_change_the_detections(tmp_path):
    cfg = dict(_models(tmp_path), box_threshold=0.94)
    dets = make_segmenter("grounded_sam", cfg).segment(_capture(1)).detections[0]
    assert [d.label for d in dets] == ["clear glass"]
    cfg = dict(_models(tmp_path), nms_iou=0.95)  # the duplicate survives a lax NMS
    dets = make_segmenter("grounded_sam", cfg).segment(_capture(1)).detections[0]
    assert [d.label for d in dets] == ["clear glass", "transparent object", "clear"]
    assert dets[2].instance_id == 3  # the shifted duplicate keeps the 2.56 px strip right of the first box
    cfg = dict(_models(tmp_path), nms_iou=0.95, min_blob_area_px=200)  # ... which blob removal then deletes
    dets = make_segmenter("grounded_sam", cfg).segment(_capture(1)).detections[0]
    assert [d.instance_id for d in dets] == [1, 2, 0]
    cfg = dict(_models(tmp_path), text_threshold=0.9)
    dets = make_segmenter("grounded_sam", cfg).segment(_capture(1)).detections[0]
    assert [d.label for d in dets] == ["clear", "transparent"]


def test_wrong_text_inputs_change_the_score(tmp_path):
    """The fake model's check term is zero only for the official text inputs; a different prompt breaks it."""
    cfg = dict(_models(tmp_path), prompt="clear glass. transparent object. glass")
    dets = make_segmenter("grounded_sam", cfg).segment(_capture(1)).detections[0]
    assert abs(dets[0].score - _sig(3.0)) > 1e-3


def test_missing_and_mismatched_model_files_raise_model_file_error(tmp_path):
    cfg = _models(tmp_path)
    with pytest.raises(ModelFileError, match="does_not_exist.onnx"):
        make_segmenter("grounded_sam", dict(cfg, sam_encoder=str(tmp_path / "does_not_exist.onnx")))
    bad = build_sam_decoder(tmp_path / "bad_dec.onnx", coords_name="points")
    with pytest.raises(ModelFileError, match=r"bad_dec\.onnx.*point_coords"):
        make_segmenter("grounded_sam", dict(cfg, sam_decoder=str(bad)))
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not an onnx model")
    with pytest.raises(ModelFileError, match="junk.onnx"):
        make_segmenter("grounded_sam", dict(cfg, gdino_model=str(junk)))
    with pytest.raises(ModelFileError, match=r"sam_decoder.*sam_enc\.onnx.*image_embeddings"):  # wrong signature
        make_segmenter("grounded_sam", dict(cfg, sam_decoder=cfg["sam_encoder"]))
    with pytest.raises(ModelFileError, match="vocab"):
        make_segmenter("grounded_sam", dict(cfg, bert_vocab=str(tmp_path / "nope.txt")))
    with pytest.raises(ModelFileError, match="gdino_model is not set"):
        make_segmenter("grounded_sam", dict(cfg, gdino_model=""))


def test_alternative_export_names_are_accepted(tmp_path):
    cfg = _models(tmp_path)
    alt = build_gdino(tmp_path / "alt.onnx", None, 36.0, gdino_resize_hw(H, W), _grey_mean(),
                      names=("samples", "text_self_attention_masks"))
    dets = make_segmenter("grounded_sam", dict(cfg, gdino_model=str(alt))).segment(_capture(1)).detections[0]
    assert [d.label for d in dets] == ["clear glass", "transparent object"]


def test_views_without_rgb_and_unknown_names(tmp_path):
    seg = make_segmenter("grounded_sam", _models(tmp_path))
    K = np.array([[200.0, 0, W / 2], [0, 200.0, H / 2], [0, 0, 1]])
    cap = Capture(views=(CameraView(K=K, T_world_cam=np.eye(4), mask=np.zeros((H, W), np.int32), name="m"),))
    with pytest.raises(CaptureError, match="'m'"):
        seg.segment(cap)
    with pytest.raises(UnknownNameError, match="grounded_sam"):
        make_segmenter("sam2", {})


def test_select_sam_mask_uses_multimask_outputs_for_boxes():
    masks = np.stack([np.full((4, 4), float(i)) for i in range(4)])[None]
    iou = np.array([[0.99, 0.2, 0.8, 0.5]])
    assert select_sam_mask(masks, iou, n_points=2)[0, 0] == 2.0  # box (2 points): best of the 3 multimask outputs
    assert select_sam_mask(masks, iou, n_points=3)[0, 0] == 0.0  # 3+ points: the single-mask output
    assert GroundedSAMConfig().box_threshold == 0.35
