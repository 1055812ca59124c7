"""The learned segmenters on a committed real photo (ClearGrasp frame 000000080, Apache-2.0) and a v4 render.

A regression guard on real images, not a claim of transfer: the shipped model (v3, trained on renders only)
scored union IoU 0.47 on this frame on 2026-12-05 (`benchmarks/results/segmentation_real.md`: mean 0.32 over the
three ClearGrasp frames, precision 0.41). The stated floor is 0.40; the transfer target of issue 43 is 0.75.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FRAME = Path(__file__).parent / "data" / "cleargrasp_000000080"


def test_shipped_segmenter_on_a_real_cleargrasp_frame_scores_above_its_stated_floor():
    import cv2

    from benchmarks.segmentation_real import K_D435, union_scores
    from torm.segmentation import make_segmenter
    from torm.types import CameraView, Capture

    rgb = cv2.imread(str(FRAME / "000000080-transparent-rgb-img.jpg"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    true = cv2.imread(str(FRAME / "000000080-mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    seg = make_segmenter("learned", {"threads": 1})
    masks = seg.segment(Capture(views=(CameraView(K_D435, np.eye(4), rgb=rgb),))).masks_vxhxw[0]
    s = union_scores(masks > 0, true)
    assert s["iou"] >= 0.40, s
    assert s["recall"] >= 0.6, s  # it finds most of the bottles; its weakness is precision (issue 43)


V4 = "torm/segmentation/models/learned_seg_v4.onnx"


def test_v4_on_the_real_cleargrasp_frame_beats_v3_above_its_stated_floor():
    """v4 (trained with opaque look-alikes, rooms and sensor effects, still on renders only) on frame 080: measured
    union IoU 0.63, precision 0.85 on 2026-12-05 (v3: 0.47 / 0.67). Floors 0.55 and 0.75; the target is 0.75 IoU."""
    import cv2

    from benchmarks.segmentation_real import K_D435, union_scores
    from torm.segmentation import make_segmenter
    from torm.types import CameraView, Capture

    rgb = cv2.imread(str(FRAME / "000000080-transparent-rgb-img.jpg"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    true = cv2.imread(str(FRAME / "000000080-mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    cap = Capture(views=(CameraView(K_D435, np.eye(4), rgb=rgb),))
    s4 = union_scores(make_segmenter("learned", {"threads": 1, "model": V4}).segment(cap).masks_vxhxw[0] > 0, true)
    s3 = union_scores(make_segmenter("learned", {"threads": 1}).segment(cap).masks_vxhxw[0] > 0, true)
    assert s4["iou"] >= 0.55 and s4["precision"] >= 0.75, s4
    assert s4["iou"] > s3["iou"] + 0.05 and s4["precision"] > s3["precision"] + 0.05, (s3, s4)


def test_v4_rejects_opaque_look_alikes_beside_glass_on_a_committed_render():
    """A v4 validation render (320x192, Mitsuba): glass beside an opaque painted twin of a measuring cylinder, plastic
    blobs and a box, only the glass labelled. Measured: v4 union IoU 0.83, precision 0.84; v3 0.55 / 0.59 (it marks
    the twin and the box: benchmarks/results/learned_v3_v4_distractors.png)."""
    import cv2

    from benchmarks.segmentation_real import union_scores
    from torm.segmentation import make_segmenter

    data = Path(__file__).parent / "data"
    rgb = cv2.imread(str(data / "v4_distractors_view.png"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    true = cv2.imread(str(data / "v4_distractors_view_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    s4 = union_scores(make_segmenter("learned", {"threads": 1, "model": V4}).segment_image(rgb)[0] > 0, true)
    s3 = union_scores(make_segmenter("learned", {"threads": 1}).segment_image(rgb)[0] > 0, true)
    assert s4["iou"] >= 0.75 and s4["precision"] >= 0.75, s4
    assert s4["precision"] > s3["precision"] + 0.15, (s3, s4)


def _frame_080_scores(*models: str) -> list[dict[str, float]]:
    """Union scores of each shipped ``model`` on ClearGrasp frame 080 through ``segment`` (a one-view capture with
    the D435's intrinsics; the transparent prompt, the card's input width)."""
    import cv2

    from benchmarks.segmentation_real import K_D435, union_scores
    from torm.segmentation import make_segmenter
    from torm.types import CameraView, Capture

    rgb = cv2.imread(str(FRAME / "000000080-transparent-rgb-img.jpg"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    true = cv2.imread(str(FRAME / "000000080-mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    cap = Capture(views=(CameraView(K_D435, np.eye(4), rgb=rgb),))
    return [union_scores(make_segmenter("learned", {"threads": 1, "model": m}).segment(cap).masks_vxhxw[0] > 0, true)
            for m in models]


def _rw5_view() -> tuple[np.ndarray, np.ndarray]:
    """The committed rw5 PBR render (RGB uint8) and its instance mask (1 = the glass ball, 2 = the opaque cup)."""
    import cv2

    data = Path(__file__).parent / "data"
    rgb = cv2.imread(str(data / "rw5_pbr_view.png"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    return rgb, cv2.imread(str(data / "rw5_pbr_view_mask.png"), cv2.IMREAD_UNCHANGED)


V6 = "v6"


def test_v6_photo_trained_features_on_the_real_cleargrasp_frame_beat_v4():
    """v6 (ImageNet EfficientNet-Lite0 encoder, issue 61) on frame 080, transparent-class prompt, 640 px: measured union
    IoU 0.814, precision 0.993 on 2026-12-07 (v4 0.62 / 0.85). Floors 0.75 and 0.90; the issue's target is 0.85."""
    s6, s4 = _frame_080_scores(V6, V4)
    assert s6["iou"] >= 0.75 and s6["precision"] >= 0.90, s6
    assert s6["iou"] > s4["iou"] + 0.10, (s4, s6)


def test_v6_finds_the_glass_ball_of_a_committed_rw5_render():
    """A PBR render of rw5 (a glass ball beside the opaque cup; tests/data/rw5_pbr_view.md). Measured 2026-12-07 with
    the transparent prompt: glass IoU 0.676, recall 0.993 (v4 0.394, v3 0.389); its false positives are on the cup,
    which v6 classes as transparent where it sees it (the opaque class does not work yet: docs, issue 61)."""
    from benchmarks.segmentation_real import union_scores
    from torm.segmentation import make_segmenter

    rgb, gt = _rw5_view()
    seg = make_segmenter("learned", {"threads": 1, "model": V6})
    s = union_scores(seg.segment_image(rgb)[0] > 0, gt == 1)
    assert s["iou"] >= 0.60 and s["recall"] >= 0.95, s
    both = make_segmenter("learned", {"threads": 1, "model": V6, "classes": ["transparent", "opaque"]})
    assert (both.segment_image(rgb)[0] > 0).sum() >= (seg.segment_image(rgb)[0] > 0).sum()  # a wider prompt keeps more


V7 = "v7"


def test_v7_on_the_real_cleargrasp_frame_beats_v6():
    """v7 (v6's photo-trained encoder; opaque look-alikes are opaque objects, class head picked by transparent IoU on
    renders) on frame 080, transparent prompt, 640 px: measured union IoU 0.919, precision 0.965 on 2026-12-07 (v6
    0.814 / 0.993). Floors 0.85 and 0.90; thresholded masks move by a few pixels across CPU kernels, not by 0.05."""
    s7, s6 = _frame_080_scores(V7, V6)
    assert s7["iou"] >= 0.85 and s7["precision"] >= 0.90, s7
    assert s7["iou"] > s6["iou"] + 0.05, (s6, s7)


def test_v7_prompt_includes_the_opaque_cup_of_a_committed_rw5_render_only_when_asked():
    """The committed rw5 render (glass ball + opaque cup): the transparent prompt segments the ball and not the cup,
    the opaque prompt the cup and not the ball. Measured 2026-12-07: ball IoU 0.923 (cup recall 0.0); cup IoU 0.942
    (ball recall 0.0). v6 classed the cup transparent (cup foreground 0.36, p(transparent) 0.73)."""
    from benchmarks.segmentation_real import union_scores
    from torm.segmentation import make_segmenter

    rgb, gt = _rw5_view()
    glass = make_segmenter("learned", {"threads": 1, "model": V7, "classes": ["transparent"]}).segment_image(rgb)[0]
    opaque = make_segmenter("learned", {"threads": 1, "model": V7, "classes": ["opaque"]}).segment_image(rgb)[0]
    ball = union_scores(glass > 0, gt == 1)
    cup = union_scores(opaque > 0, gt == 2)
    assert ball["iou"] >= 0.80 and cup["iou"] >= 0.80, (ball, cup)
    assert union_scores(glass > 0, gt == 2)["recall"] <= 0.05  # the glass prompt leaves the cup out
    assert union_scores(opaque > 0, gt == 1)["recall"] <= 0.05  # the opaque prompt leaves the ball out


def test_v7s_int8_copy_reads_the_real_frame_and_the_prompt_like_v7():
    """v7q, v7's int8 copy (torm.segmentation.quantize; 2.2x faster on a CPU): frame 080 at 640 px measured union IoU
    0.903, precision 0.932 on 2026-12-07 (v7 0.919 / 0.948); on the rw5 render ball IoU 0.893 with the transparent
    prompt, cup IoU 0.948 with the opaque prompt, each leaving the other object out. Floors as v7's: int8 rounding
    moves border pixels, not objects."""
    from benchmarks.segmentation_real import union_scores
    from torm.segmentation import make_segmenter

    (sq,) = _frame_080_scores("v7q")
    assert sq["iou"] >= 0.85 and sq["precision"] >= 0.90, sq
    rgb, gt = _rw5_view()
    glass = make_segmenter("learned", {"threads": 1, "model": "v7q", "classes": ["transparent"]}).segment_image(rgb)[0]
    opaque = make_segmenter("learned", {"threads": 1, "model": "v7q", "classes": ["opaque"]}).segment_image(rgb)[0]
    assert union_scores(glass > 0, gt == 1)["iou"] >= 0.80 and union_scores(opaque > 0, gt == 2)["iou"] >= 0.80
    assert union_scores(glass > 0, gt == 2)["recall"] <= 0.05 and union_scores(opaque > 0, gt == 1)["recall"] <= 0.05
