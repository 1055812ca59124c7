"""``torm reconstruct``: per-object meshes and point clouds from a capture folder's silhouettes.

Examples::

    torm capture --scenario rw3 --out runs/rw3_s0
    torm reconstruct runs/rw3_s0 --out runs/rw3_s0_rec
    torm reconstruct runs/rw3_s0 --segmenter noisy --preset paper --set mode=paper --out runs/rw3_paper
    torm reconstruct my_nerf_dataset --segmenter grounded_sam --seg-config models/gsam.yaml --out out/

Masks come from the capture (``mask_path`` per frame) unless ``--segmenter`` is given. Writes
``scene.ply``, ``object_<k>.{ply,obj,glb}`` (meshes, metres, world frame), ``object_<k>_points.ply``
(equal-count surface samples with normals), ``reconstruction.json`` (timings, curves, config) and,
when the capture holds ground truth (masks and/or ideal depth), ``metrics.json`` with the silhouette
IoU and the paper's Table II depth metrics. ``--record FILE.rrd`` writes a rerun recording.
``--config``/``--set`` configure :class:`torm.reconstruction.ReconstructionConfig` (``torm config show
reconstruct`` lists its keys).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from torm.commands._common import add_overrides, add_parser, add_record, print_json

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "reconstruct", __doc__, help="reconstruct per-object meshes from a capture folder")
    p.add_argument("capture_dir", metavar="CAPTURE_DIR", help="capture folder (transforms.json)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--segmenter", default=None, help="gt | noisy | grounded_sam (default: the capture's masks)")
    p.add_argument("--preset", default=None, help="noisy: error preset (default paper)")
    p.add_argument("--seg-config", default=None, help="segmenter config YAML (e.g. ONNX model paths)")
    add_record(p, "the capture and the result")
    add_overrides(p, example="grid_res=64", target="reconstruct")
    p.set_defaults(func=run)


def _evaluate(capture: Any, gt_masks: np.ndarray | None, mesh: Any) -> dict[str, Any]:
    """Silhouette IoU vs GT masks and depth metrics vs the capture's ideal depth (when present)."""
    from torm.metrics import depth_metrics, silhouette_iou
    from torm.reconstruction.raster import render_depth

    H, W = capture.image_size
    depth = np.stack([render_depth(mesh.verts_vx3, mesh.faces_fx3, v.K, v.T_cam_world, H, W)
                      for v in capture.views])
    out: dict[str, Any] = {"n_objects_present": len(capture.object_ids) or None}
    if gt_masks is not None:
        iou = silhouette_iou(depth > 0, gt_masks > 0)
        out["silhouette_iou_mean"], out["silhouette_iou_min"] = iou["mean"], iou["min"]
        if all(v.depth is not None for v in capture.views):
            out["depth"] = depth_metrics(depth, np.stack([v.depth for v in capture.views]), gt_masks > 0)
    return out


def run(args: argparse.Namespace) -> int:
    from torm import config as cfgmod
    from torm.capture.io import load_capture
    from torm.errors import CaptureError
    from torm.mesh.export import write_mesh, write_point_cloud
    from torm.reconstruction import ReconstructionConfig, reconstruct

    capture = load_capture(args.capture_dir)
    gt_masks = capture.masks() if capture.has_masks else None
    seg_summary = None
    if args.segmenter:
        from torm.commands.segment import load_segmenter_config
        from torm.segmentation import make_segmenter

        over = [f"preset={args.preset}"] if args.preset and args.segmenter == "noisy" else []
        seg = make_segmenter(args.segmenter, load_segmenter_config(args.segmenter, args.seg_config, over))
        res = seg.segment(capture)
        capture = res.apply(capture)
        seg_summary = res.summary()
    elif not capture.has_masks:
        raise CaptureError(f"{args.capture_dir} has no masks; pass --segmenter grounded_sam (or gt/noisy) or run "
                           "torm segment first")
    data = cfgmod.load_yaml(args.config) if args.config else {}
    cfg = cfgmod.from_dict(ReconstructionConfig, data, args.overrides, where=args.config or "ReconstructionConfig")
    rec = reconstruct(capture, cfg)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_mesh(rec.scene_mesh, out / "scene.ply")
    files = []
    for k, (mesh, cloud) in enumerate(zip(rec.object_meshes, rec.point_clouds, strict=True)):
        for ext in ("ply", "obj", "glb"):
            files.append(str(write_mesh(mesh, out / f"object_{k}.{ext}")))
        files.append(str(write_point_cloud(cloud, out / f"object_{k}_points.ply")))
    summary = {"n_objects": rec.n_objects, "timings_s": rec.timings,
               "info": {k: v for k, v in rec.info.items() if isinstance(v, (int, float, str, bool))},
               "config": cfgmod.to_dict(cfg), "segmentation": seg_summary, "files": files}
    (out / "reconstruction.json").write_text(json.dumps({**summary, "history": rec.history}, default=float))
    if gt_masks is not None or any(v.depth is not None for v in capture.views):
        metrics = _evaluate(capture, gt_masks, rec.scene_mesh)
        metrics["n_objects_found"] = rec.n_objects
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
        summary["metrics"] = metrics
    if args.record:
        from torm.viz import TrialRecorder

        recorder = TrialRecorder(args.record)
        recorder.perception(capture, list(rec.object_meshes), list(rec.point_clouds), [[] for _ in rec.point_clouds])
        recorder.close()
    print_json(summary)
    return 0
