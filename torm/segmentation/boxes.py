"""Box utilities: format conversion, IoU, greedy NMS and Grounding DINO output decoding (numpy)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torm.segmentation.tokenizer import TextInputs, WordPieceTokenizer


def cxcywh_to_xyxy(boxes_nx4: np.ndarray, width: int, height: int) -> np.ndarray:
    """Normalised (cx, cy, w, h) in [0, 1] -> pixel (x0, y0, x1, y1), clipped to the image."""
    b = np.asarray(boxes_nx4, dtype=np.float64).reshape(-1, 4)
    scale = np.array([width, height, width, height], dtype=np.float64)
    cx, cy, w, h = (b * scale).T
    out = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0.0, width)
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0.0, height)
    return out


def box_iou(a_nx4: np.ndarray, b_mx4: np.ndarray) -> np.ndarray:
    """(N, M) IoU of xyxy boxes (pixels)."""
    a = np.asarray(a_nx4, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_mx4, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0.0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0.0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0.0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def nms(boxes_nx4: np.ndarray, scores_n: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression; indices of kept boxes in descending score order.

    A box is suppressed when its IoU with an already kept, higher-scoring box exceeds ``iou_threshold``.
    """
    boxes = np.asarray(boxes_nx4, dtype=np.float64).reshape(-1, 4)
    order = list(np.argsort(-np.asarray(scores_n, dtype=np.float64), kind="stable"))
    keep: list[int] = []
    while order:
        i = order.pop(0)
        keep.append(int(i))
        if order:
            ious = box_iou(boxes[i:i + 1], boxes[order])[0]
            order = [j for j, iou in zip(order, ious, strict=True) if iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class DecodedBoxes:
    """Decoded detections of one image: ``boxes_nx4`` xyxy pixels, ``scores_n`` in [0, 1], ``phrases``."""

    boxes_nx4: np.ndarray
    scores_n: np.ndarray
    phrases: tuple[str, ...]


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -60.0, 60.0)))


def phrase_from_tokens(
    probs_t: np.ndarray, text: TextInputs, tokenizer: WordPieceTokenizer, text_threshold: float
) -> str:
    """Grounding DINO's ``get_phrases_from_posmap``: decode the real tokens whose probability > threshold.

    ``[CLS]``, ``[SEP]``, ``[PAD]`` and the phrase separators ``.``/``?`` are never part of a phrase.
    """
    ids = text.input_ids[0]
    skip = {tokenizer.vocab[t] for t in ("[CLS]", "[SEP]", "[PAD]")} | {
        tokenizer.vocab[t] for t in (".", "?") if t in tokenizer.vocab}
    n = min(len(probs_t), text.length)
    sel = [int(ids[i]) for i in range(n) if probs_t[i] > text_threshold and text.attention_mask[0, i]
           and int(ids[i]) not in skip]
    return tokenizer.decode(sel).strip()


def decode_grounding(
    logits_qxl: np.ndarray,
    boxes_qx4: np.ndarray,
    text: TextInputs,
    tokenizer: WordPieceTokenizer,
    image_wh: tuple[int, int],
    box_threshold: float,
    text_threshold: float,
    nms_iou: float,
    logits_are_probabilities: bool = False,
    max_box_fraction: float = 1.0,
    min_box_px: float = 2.0,
    max_detections: int = 100,
    canvas_wh: tuple[float, float] | None = None,
) -> DecodedBoxes:
    """Turn Grounding DINO's per-query outputs into scored, phrase-labelled pixel boxes.

    Args:
        logits_qxl: (Q, L) token logits per query (L >= the text length; extra columns are ignored).
        boxes_qx4: (Q, 4) normalised cxcywh boxes.
        image_wh: (W, H) of the original image in pixels.
        canvas_wh: (W, H) in original-image pixels of the canvas the boxes are normalised to, when the image was
            letterboxed (resized keeping its aspect, padded at the right and bottom: :func:`letterbox_hw`); None =
            the image itself.
        box_threshold: keep a query when its max token probability over real tokens is >= this.
        text_threshold: tokens above this form the query's phrase.
        nms_iou: IoU above which a lower-scoring box is suppressed.
        max_box_fraction: drop boxes covering more than this fraction of the image (whole-table boxes).
        min_box_px: drop boxes thinner than this many pixels.
    """
    logits = np.asarray(logits_qxl, dtype=np.float64)
    probs = logits if logits_are_probabilities else _sigmoid(logits)
    T = min(text.length, probs.shape[1])
    valid = text.attention_mask[0, :T].astype(bool)
    scores = np.where(valid[None, :], probs[:, :T], 0.0).max(axis=1) if T else np.zeros(len(probs))
    keep = np.nonzero(scores >= box_threshold)[0]
    W, H = image_wh
    cw, ch = canvas_wh if canvas_wh is not None else (W, H)
    boxes = cxcywh_to_xyxy(np.asarray(boxes_qx4)[keep], cw, ch)
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, W)  # the padding holds no image
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, H)
    sc = scores[keep]
    wh = boxes[:, 2:] - boxes[:, :2]
    ok = (wh.min(axis=1) >= min_box_px) & (wh.prod(axis=1) <= max_box_fraction * W * H + 1e-9)
    boxes, sc, keep = boxes[ok], sc[ok], keep[ok]
    order = nms(boxes, sc, nms_iou)[:max_detections]
    phrases = tuple(phrase_from_tokens(probs[keep[i], :T], text, tokenizer, text_threshold) for i in order)
    return DecodedBoxes(boxes[order], sc[order], phrases)
