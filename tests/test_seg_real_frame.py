"""The shipped learned segmenter on a committed real photo (ClearGrasp frame 000000080, Apache-2.0).

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
