"""``torm reconstruct``: per-object meshes and point clouds from a capture folder's silhouettes.

Examples::

    torm capture --scenario rw3 --out runs/rw3_s0
    torm reconstruct runs/rw3_s0 --out runs/rw3_s0_rec
    torm reconstruct runs/rw3_s0 --segmenter noisy --preset paper --set mode=paper --out runs/rw3_paper
    torm reconstruct my_nerf_dataset --segmenter grounded_sam --set segmentation=models/gsam/grounded_sam.yaml \
        --out out/
    torm reconstruct my_capture --no-table --holdout-every 5 --out out/    # a recorded capture of any scene

Masks come from the capture (``mask_path`` per frame, or the alpha of RGBA images; soft greyscale masks
are thresholded at 0.5) unless ``--segmenter`` is given. The box comes from ``--bounds``, else the
capture's ``workspace_bounds``, else it is computed from the cameras and masks; the table plane from
``--table-z``, else the capture's ``table_height`` (none when absent or null; ``--no-table`` ignores it).
Writes ``scene.ply``, ``object_<k>.{ply,obj,glb}`` (meshes, metres, world frame), ``object_<k>_points.ply``
(equal-count surface samples with normals), ``reconstruction.json`` (timings, curves, config, the
settings chosen from the capture, objects rejected by the checks) and ``metrics.json``:
``fit_input_views`` (silhouette IoU on the views the reconstruction used: a fit, not a score),
``heldout`` (with ``--holdout-every K``: every K-th view is left out of the input and the IoU on those
views is reported) and, when the capture holds ideal depth, the paper's Table II depth metrics.
``--record FILE.rrd`` writes a rerun recording. ``--config``/``--set`` configure
:class:`torm.reconstruction.ReconstructionConfig` (``torm config show reconstruct`` lists its keys) and, under
``segmentation``, the ``--segmenter``'s own config: ``--set segmentation.KEY=VALUE``, or in the file a
``segmentation:`` mapping or the path of a segmenter YAML (``--set segmentation=FILE``, e.g. the one
``torm export-models`` writes; relative paths are relative to the file that names them).
Threads: ``TORM_THREADS`` (default: the free cores, fewer when the machine is busy; the count used is
logged and recorded).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from torm.commands._common import add_overrides, add_parser, add_record, check_output_dir, finite_float, print_json

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "reconstruct", __doc__, help="reconstruct per-object meshes from a capture folder")
    p.add_argument("capture_dir", metavar="CAPTURE_DIR", help="capture folder (transforms.json)")
    p.add_argument("--out", required=True, help="output folder")
    from torm.vocabulary import SEGMENTERS

    p.add_argument("--segmenter", choices=SEGMENTERS, default=None,
                   help=f"{' | '.join(SEGMENTERS)} (default: the capture's masks; difference needs the capture's "
                        "reference views)")
    p.add_argument("--preset", default=None, help="noisy: error preset (default paper)")
    add_record(p, "the capture and the result")
    p.add_argument("--bounds", type=finite_float, nargs=6, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="reconstruction box (m, world frame); default: the capture's workspace_bounds, else automatic")
    p.add_argument("--table-z", type=finite_float, default=None,
                   help="table-top height (m); default: the capture's table_height")
    p.add_argument("--no-table", action="store_true", help="no table plane (objects may extend below z = 0)")
    p.add_argument("--holdout-every", type=int, default=0, metavar="K",
                   help="leave every K-th view (0, K, 2K, ...) out of the input and report the IoU on them")
    add_overrides(p, example="grid_res=64", target="reconstruct")
    p.set_defaults(func=run)


def _silhouette_metrics(views: list[Any], mesh: Any, H: int, W: int,
                        unknown_vxhxw: np.ndarray | None = None) -> dict[str, Any]:
    """Silhouette IoU of ``mesh`` rendered in ``views`` vs their masks (> 0), at the capture resolution; pixels
    marked in ``unknown_vxhxw`` (no evidence: no source after undistortion) count neither way."""
    from torm.metrics import silhouette_iou
    from torm.reconstruction.raster import render_mask_fast

    pred = np.stack([render_mask_fast(mesh.verts_vx3, mesh.faces_fx3, v.K, v.T_cam_world, H, W) for v in views])
    target = np.stack([v.mask for v in views]) > 0
    if unknown_vxhxw is not None:
        pred, target = pred & ~unknown_vxhxw, target & ~unknown_vxhxw
    iou = silhouette_iou(pred, target)
    return {"n_views": len(views), "silhouette_iou_mean": iou["mean"], "silhouette_iou_min": iou["min"],
            "per_view": iou["per_view"]}


def _evaluate(capture: Any, used: list[int], held: list[int], mesh: Any, reference: str) -> dict[str, Any]:
    """Fit on the input views, IoU on the held-out views, and depth metrics vs the capture's ideal depth."""
    from torm.capture.lens import no_evidence_masks
    from torm.metrics import depth_metrics
    from torm.reconstruction.raster import render_depth

    H, W = capture.image_size
    unknown = no_evidence_masks(capture)
    out: dict[str, Any] = {"n_objects_present": len(capture.object_ids) or None, "mask_reference": reference}
    views = capture.views
    out["fit_input_views"] = {**_silhouette_metrics([views[i] for i in used], mesh, H, W,
                                                    None if unknown is None else unknown[used]),
                              "note": "IoU on the views the reconstruction was fitted to (not a held-out score)"}
    if held:
        out["heldout"] = {**_silhouette_metrics([views[i] for i in held], mesh, H, W,
                                                None if unknown is None else unknown[held]), "views": held,
                          "note": "held-out views: IoU on views left out of the reconstruction's input"}
    if all(v.depth is not None and v.mask is not None for v in views):
        depth = np.stack([render_depth(mesh.verts_vx3, mesh.faces_fx3, v.K, v.T_cam_world, H, W) for v in views])
        out["depth"] = depth_metrics(depth, np.stack([v.depth for v in views]), np.stack([v.mask for v in views]))
    # the earlier top-level names, kept: the fit on the input views
    out["silhouette_iou_mean"] = out["fit_input_views"]["silhouette_iou_mean"]
    out["silhouette_iou_min"] = out["fit_input_views"]["silhouette_iou_min"]
    return out


def _segmenter_settings(args: argparse.Namespace, data: dict[str, Any]
                        ) -> tuple[str | None, dict[str, Any] | None, list[str], list[str]]:
    """Split the segmenter's settings off the reconstruction's: (its YAML path, its data or None to read that path,
    its overrides, the reconstruction's overrides). ``data`` (the ``--config`` file) loses its ``segmentation``."""
    from torm.errors import ConfigError

    seg_over = [o.removeprefix("segmentation.") for o in args.overrides if o.startswith("segmentation.")]
    file_over = [o.partition("=")[2] for o in args.overrides if o.startswith("segmentation=")]
    rest = [o for o in args.overrides if not o.startswith(("segmentation.", "segmentation="))]
    entry = file_over[-1] if file_over else data.pop("segmentation", None)
    if entry is not None and not isinstance(entry, (str, dict)):
        raise ConfigError(f"segmentation: a mapping of the segmenter's keys or the path of its YAML, got {entry!r}")
    if (entry is not None or seg_over) and not args.segmenter:
        raise ConfigError("segmentation settings were given but no --segmenter: name the segmenter they configure "
                          "(torm reconstruct --segmenter NAME), or drop them")
    if isinstance(entry, dict):
        return args.config, entry, seg_over, rest
    if isinstance(entry, str):  # a segmenter YAML, relative to the config file that names it
        base = Path(args.config).parent if args.config and not file_over else Path(".")
        return str(base / entry), None, seg_over, rest
    return None, None, seg_over, rest


def run(args: argparse.Namespace) -> int:
    from torm import config as cfgmod
    from torm.capture.io import load_capture
    from torm.errors import CaptureError, ConfigError
    from torm.mesh.export import write_mesh, write_point_cloud
    from torm.reconstruction import ReconstructionConfig, reconstruct
    from torm.segmentation.base import mask_reference, masks_are_ground_truth

    out = check_output_dir(args.out)  # before any work: a bad --out is refused now, not after the reconstruction
    capture = load_capture(args.capture_dir)
    input_ref = mask_reference(capture)
    gt_masks = capture.masks() if masks_are_ground_truth(capture) else None
    seg_summary = None
    data = cfgmod.load_yaml(args.config) if args.config else {}
    seg_path, seg_data, seg_over, overrides = _segmenter_settings(args, data)
    if args.segmenter:
        from torm.commands.segment import load_segmenter_config
        from torm.segmentation import make_segmenter

        over = [f"preset={args.preset}"] if args.preset and args.segmenter == "noisy" else []
        seg = make_segmenter(args.segmenter, load_segmenter_config(args.segmenter, seg_path, over + seg_over,
                                                                   data=seg_data))
        res = seg.segment(capture)
        capture = res.apply(capture)
        seg_summary = res.summary()
    elif not capture.has_masks:
        raise CaptureError(f"{args.capture_dir} has no masks; pass --segmenter grounded_sam (or gt/noisy) or run "
                           "torm segment first")
    cfg = cfgmod.from_dict(ReconstructionConfig, data, overrides, where=args.config or "ReconstructionConfig")
    flags: dict[str, Any] = {}
    if args.bounds is not None:
        flags["bounds"] = (tuple(args.bounds[:3]), tuple(args.bounds[3:]))
    if args.table_z is not None:
        flags["table_z"] = args.table_z
    if args.no_table:
        flags["no_table"], flags["table_z"] = True, None
    if flags:
        cfg = dataclasses.replace(cfg, **flags)
    if args.holdout_every < 0 or args.holdout_every == 1:
        raise ConfigError("--holdout-every K needs K >= 2 (every K-th view is held out) or 0 (none)")
    held = [i for i in range(len(capture)) if args.holdout_every and i % args.holdout_every == 0]
    used = [i for i in range(len(capture)) if i not in set(held)]
    rec = reconstruct(capture.subset(used) if held else capture, cfg)
    write_mesh(rec.scene_mesh, out / "scene.ply")
    files = []
    for k, (mesh, cloud) in enumerate(zip(rec.object_meshes, rec.point_clouds, strict=True)):
        for ext in ("ply", "obj", "glb"):
            files.append(str(write_mesh(mesh, out / f"object_{k}.{ext}")))
        files.append(str(write_point_cloud(cloud, out / f"object_{k}_points.ply")))
    keep = ("rejected_objects", "unexplained_views", "bounds", "table_z", "repaired_views", "grid_cells")
    summary = {"n_objects": rec.n_objects, "timings_s": rec.timings,
               "info": {k: v for k, v in rec.info.items() if isinstance(v, (int, float, str, bool)) or k in keep},
               "config": cfgmod.to_dict(cfg), "segmentation": seg_summary, "files": files,
               "input_views": used, "heldout_views": held}
    (out / "reconstruction.json").write_text(json.dumps({**summary, "history": rec.history}, default=float))
    ref = input_ref if gt_masks is not None else (mask_reference(capture) if seg_summary is None else
                                                  "the segmenter's masks")
    scored = capture if gt_masks is None else capture.with_masks(gt_masks)
    metrics = _evaluate(scored, used, held, rec.scene_mesh, ref)
    metrics["n_objects_found"] = rec.n_objects
    metrics["mode"] = rec.info.get("mode_label")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    summary["metrics"] = {k: v for k, v in metrics.items() if k not in ("fit_input_views", "heldout")}
    summary["metrics"].update({f"{k}_iou_mean": metrics[k]["silhouette_iou_mean"]
                               for k in ("fit_input_views", "heldout") if k in metrics})
    if args.record:
        from torm.viz import TrialRecorder

        recorder = TrialRecorder(args.record)
        recorder.perception(capture, list(rec.object_meshes), list(rec.point_clouds), [[] for _ in rec.point_clouds])
        recorder.close()
    print_json(summary)
    return 0
