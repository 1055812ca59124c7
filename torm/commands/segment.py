"""``torm segment``: extract per-view instance masks of a capture folder and save them as a new capture.

Examples::

    torm segment runs/rw3_s0 --segmenter noisy --preset paper --seed 0 --out runs/rw3_s0_noisy
    torm segment runs/rw3_s0 --segmenter noisy --set overrides.p_missing_view=0.2 --out runs/rw3_s0_miss
    torm segment runs/rw3_s0 --segmenter grounded_sam --config models/grounded_sam.yaml \\
        --prompt "clear glass. transparent object." --out runs/rw3_s0_gsam
    torm segment runs/rw3_s0 --segmenter gt --check-views drop
    torm segment runs/rw3_s0 --segmenter learned --set fg_threshold=0.5 --out runs/rw3_s0_learned
    torm segment runs/scene --reference runs/empty --segmenter difference      # scene minus the reference pass

The output folder (default ``CAPTURE_DIR_<segmenter>``) is a full capture (``transforms.json``, images,
depth) whose ``masks/`` hold the predicted 16-bit instance masks. The input folder is never modified.
When the input had ground-truth masks (the simulator's: ``metadata.mask_source``) they are kept in ``gt_masks/``
and the mask quality (IoU vs GT) is stored in ``metadata.segmentation``; GT object ids/names move to
``metadata.gt_object_ids/names`` and ``object_ids`` lists the predicted instance ids. Masks of any other origin (a
segmenter's, a recorded capture's) are never called ground truth: the output names their source in
``metadata.input_mask_source`` and its own in ``metadata.mask_source``. Without ``--segmenter`` the shipped learned
model runs (no downloaded weights needed). ``--config`` is YAML with the segmenter's config
fields at the top level (or under a key named after the segmenter); ``--set key=value`` overrides them
(``torm config show segment:NAME`` lists a segmenter's keys, e.g. ``segment:noisy``).
With ``--check-views`` the cross-view consistency checks run and ``drop`` writes only the kept views.
``--reference DIR``: a capture of the empty workspace recorded along the same camera path (the reference pass);
each view is paired with the reference view at the same pose (refused beyond 2 mm / 0.5 deg, or from another
camera or renderer), the ``difference`` segmenter and reference-mode ``learned`` models read it, and after the
segmentation the static background is compared with it (refused when the table or the light changed).
Prints a JSON summary (timings, detections per view, quality, flagged views) on stdout.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm.commands._common import add_overrides, add_parser, check_output_dir, print_json, seed_arg

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "segment", __doc__, help="extract per-view instance masks of a capture folder")
    p.add_argument("capture_dir", metavar="CAPTURE_DIR", help="capture folder (transforms.json)")
    from torm.vocabulary import SEGMENTERS

    p.add_argument("--segmenter", default="learned", choices=SEGMENTERS,
                   help="learned | grounded_sam | gt | noisy | difference (default learned: the shipped model, no "
                        "downloads; grounded_sam needs your ONNX exports; difference needs --reference)")
    p.add_argument("--prompt", default=None, help="grounded_sam text prompt, phrases separated by '.'")
    p.add_argument("--preset", default=None, help="noisy: error preset (none, mild, moderate, severe, paper, ...)")
    p.add_argument("--seed", type=seed_arg, default=None, help="noisy: corruption seed")
    p.add_argument("--check-views", choices=("none", "flag", "drop"), default="none",
                   help="cross-view consistency checks: report (flag) or remove (drop) inconsistent views")
    p.add_argument("--out", default=None, help="output capture folder (default CAPTURE_DIR_<segmenter>)")
    p.add_argument("--reference", default=None, metavar="DIR",
                   help="capture folder of the empty workspace along the same camera path (reference pass)")
    add_overrides(p, example="overrides.p_missing_view=0.2", target="segment:SEGMENTER")
    p.set_defaults(func=run)


def load_segmenter_config(name: str, path: str | None, overrides: list[str],
                          data: dict[str, Any] | None = None) -> Any:
    """The segmenter's frozen config from an optional YAML file (flat or under ``name:``), or ``data`` read from
    ``path`` already, and overrides; relative file paths are relative to the file's folder."""
    from torm import config as cfgmod
    from torm.segmentation import resolve_config_paths, segmenter_config_class

    cls = segmenter_config_class(name)
    if data is None:
        data = cfgmod.load_yaml(path) if path else {}
    if isinstance(data.get(name), dict):
        data = data[name]
    if path:  # file paths in the YAML are relative to its own folder (as torm export-models writes them)
        data = resolve_config_paths(name, data, path)
    return cfgmod.from_dict(cls, data, overrides, where=str(path) if path else name)


def _write_gt_masks(folder: Path, masks_vxhxw: np.ndarray) -> list[str]:
    """Write ground-truth masks as ``gt_masks/00000.png`` (16-bit); returns the relative paths."""
    (folder / "gt_masks").mkdir(parents=True, exist_ok=True)
    rel = []
    for i, m in enumerate(masks_vxhxw):
        r = f"gt_masks/{i:05d}.png"
        cv2.imwrite(str(folder / r), m.astype(np.uint16))
        rel.append(r)
    return rel


def _json_safe(obj: Any) -> Any:
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from torm.capture.io import load_capture, save_capture
    from torm.segmentation import make_segmenter
    from torm.segmentation.multiview import ConsistencyConfig, check_views

    name = args.segmenter
    overrides = list(args.overrides)
    if args.prompt is not None:
        overrides.append(f"prompt={json.dumps(args.prompt)}")
    if args.preset is not None:
        overrides.append(f"preset={args.preset}")
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    config = load_segmenter_config(name, args.config, overrides)
    out = Path(args.out) if args.out else Path(str(Path(args.capture_dir).resolve()) + f"_{name}")
    if out.resolve() == Path(args.capture_dir).resolve():
        from torm.errors import SegmentationError

        raise SegmentationError(f"--out {out} is the input capture; write the segmented capture to another folder")
    check_output_dir(out)  # before the segmentation, not after it
    capture = load_capture(args.capture_dir)
    if args.reference:
        from torm.segmentation.reference import attach_reference

        capture = attach_reference(capture, load_capture(args.reference))
    segmenter = make_segmenter(name, config)
    result = segmenter.segment(capture)
    if any(v.reference_rgb is not None for v in capture.views):
        from torm.segmentation.reference import check_background

        result.info["reference_background_grey"] = check_background(capture, result.masks_vxhxw)
    from torm.segmentation.base import MASK_SOURCE_KEY, masks_are_ground_truth

    gt = capture.masks() if masks_are_ground_truth(capture) else None
    out_cap = result.apply(capture)
    summary = result.summary()
    summary.pop("events", None)
    kept = list(range(len(capture)))
    if args.check_views != "none":
        rep = check_views(out_cap, ConsistencyConfig(action=args.check_views))
        kept = rep.kept
        summary["consistency"] = {"kept": rep.kept, "flagged": {str(k): v for k, v in rep.reasons.items()}}
        out_cap = out_cap.subset(kept)
    pred_ids = sorted({int(k) for v in out_cap.views for k in np.unique(v.mask) if k > 0})
    gt_names = dict(zip(capture.object_ids, capture.object_names, strict=False))
    keeps_ids = name in ("gt", "noisy")
    names = [gt_names.get(k, f"spurious{k}") if keeps_ids else f"instance{k}" for k in pred_ids]
    meta = dict(capture.metadata)
    if gt is not None:
        meta["gt_object_ids"] = list(capture.object_ids)
        meta["gt_object_names"] = list(capture.object_names)
    elif capture.has_masks:  # the input's masks were not the simulator's: say where they came from, call them nothing
        meta["input_mask_source"] = capture.metadata.get(MASK_SOURCE_KEY, "unknown (not ground truth)")
    meta[MASK_SOURCE_KEY] = out_cap.metadata.get(MASK_SOURCE_KEY, f"segmenter {name}")
    meta["segmentation"] = _json_safe({k: v for k, v in summary.items() if k != "instances_per_view"})
    out_cap = replace(out_cap, object_ids=tuple(pred_ids), object_names=tuple(names), metadata=meta)
    path = save_capture(out_cap, out)
    if gt is not None:
        rel = _write_gt_masks(out, gt[kept])
        doc = json.loads(path.read_text())
        for frame, r in zip(doc["frames"], rel, strict=True):
            frame["gt_mask_path"] = r
        path.write_text(json.dumps(doc, indent=2))
    quality = summary.get("quality", {})
    print_json({
        "out": str(out),
        "segmenter": name,
        "views": len(out_cap),
        "instances_per_view": summary["instances_per_view"],
        "detections_per_view": summary["detections_per_view"],
        "timings": summary["timings"],
        "quality": {k: v for k, v in quality.items() if k != "silhouette_iou_per_view"},
        "consistency": summary.get("consistency"),
    })
    return 0
