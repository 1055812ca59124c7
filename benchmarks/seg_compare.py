"""Learned segmenters side by side on the same rendered test views (one shard folder, every model).

``benchmarks/segmentation.py --learned`` scores a model on the test splits of its own data recipe, so two models
trained on different recipes are scored on different views. This script scores several models on the test splits
of one folder (``--data``, rendered by ``torm train-segmenter`` or :func:`torm.segmentation.training.dataset.generate`):
``test_layouts`` (unseen layouts), ``test_shapes`` (scenes holding the held-out shapes) and, when rendered,
``test_fixtures`` (glassware in a tube rack or on a tray). Each model reads with its own card's post-processing
(:class:`torm.segmentation.learned.LearnedSegmenter`), as a trial would.

Metrics (:func:`torm.segmentation.training.evaluate.evaluate`): silhouette IoU (union of the instances against the
union of the glass per view: false positives count), object IoU (best-match IoU per (view, GT object with >= 100
visible px)), miss rate (object IoU < 0.5), false positives per view.

Run: ``python benchmarks/seg_compare.py --data runs/seg_data/v4f --models v3,v4,runs/seg_v4f/learned_seg_v4f.onnx
--tag v4f`` (writes ``benchmarks/results/seg_compare_<tag>.{json,md}``; ~1 s per view and model on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._common import RESULTS, check_tag, context, context_md, md_table, setup, write_json  # noqa: E402

SPLITS = ("test_layouts", "test_shapes", "test_fixtures")


def score(model: str, data: Path, threads: int, classes: str = "transparent", by_renderer: bool = False
          ) -> dict[str, Any]:
    """Metrics of ``model`` (shipped short name or .onnx path) on every test split rendered in ``data``.

    ``classes`` ``transparent``: the ground truth keeps the glass objects only (opaque ones become background) and a
    class-head model is prompted for ``transparent``; ``all``: every labelled object, a class-head model prompted
    for every class (a model without the head reads as it is). ``by_renderer``: each split's views are also scored
    per renderer that drew them (rows ``test_layouts (pbr)`` ...) where a split mixes renderers."""
    import numpy as np

    from torm.segmentation.learned import CLASSES, LearnedConfig, LearnedSegmenter, model_fingerprint
    from torm.segmentation.training.dataset import load_split, transparent_maps
    from torm.segmentation.training.evaluate import evaluate

    seg = LearnedSegmenter(LearnedConfig(model=model, threads=threads))
    if classes == "all" and seg.classes_available == CLASSES:
        seg = LearnedSegmenter(LearnedConfig(model=model, threads=threads, classes=CLASSES))
    out: dict[str, Any] = {"model": model_fingerprint(seg.config.model_path), "postprocess": dict(seg.postprocess),
                           "classes": list(seg.config.classes), "splits": {}}
    held = tuple(seg.card.get("held_out_shapes", ()))
    for split in SPLITS:
        if not (data / split).is_dir():
            continue
        views = load_split(data, split)
        if classes == "transparent":  # glass-only ground truth (a no-op on data rendered with label_opaque false)
            views["mask"] = np.where(transparent_maps(views["mask"], views["scene"], views["meta"]) > 0,
                                     views["mask"], 0).astype(views["mask"].dtype)
        renderer_n = np.array([views["meta"][int(sc)].get("renderer", "?") for sc in views["scene"]])
        parts = [(split, np.arange(len(renderer_n)))]
        if by_renderer and len(set(renderer_n)) > 1:
            parts += [(f"{split} ({r})", np.flatnonzero(renderer_n == r)) for r in sorted(set(renderer_n))]
        for name, idx in parts:
            t = time.perf_counter()
            r = evaluate(lambda im: seg.segment_image(im)[0], view_subset(views, idx), held)
            out["splits"][name] = {"views": r["views"], "silhouette_iou": r["silhouette_iou_mean"],
                                   "object_iou": r["object"]["iou_mean"], "miss_rate": r["object"]["miss_rate"],
                                   "false_positives_per_view": r["false_positives_per_view"],
                                   "seconds_per_view": (time.perf_counter() - t) / max(r["views"], 1)}
    return out


def view_subset(views: dict[str, Any], idx: Any) -> dict[str, Any]:
    """The views ``idx`` of a loaded split: every per-view array indexed, ``meta`` (per scene) kept whole."""
    n = len(views["rgb"])
    return {k: (v[idx] if hasattr(v, "shape") and len(v) == n else v) for k, v in views.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="shard folder holding test_* splits")
    ap.add_argument("--models", default="v3,v4", help="comma-separated shipped short names or .onnx paths")
    ap.add_argument("--tag", required=True, help="writes seg_compare_<tag>.{json,md}")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--classes", default="transparent", choices=("transparent", "all"),
                    help="ground truth: glass objects only (default) or every labelled object")
    ap.add_argument("--out", default=str(RESULTS), help="result folder")
    ap.add_argument("--note", default="", help="a paragraph for the Markdown file: what is compared and why")
    ap.add_argument("--by-renderer", action="store_true",
                    help="also score each split's views per renderer (pbr, mujoco, pbr_scalar) where it mixes them")
    args = ap.parse_args(argv)
    check_tag(args.tag)
    data = Path(args.data)
    found = [s for s in SPLITS if (data / s).is_dir()]
    if not found:
        raise SystemExit(f"{data}: no test split ({', '.join(SPLITS)}); render them with torm train-segmenter "
                         "(data.shards.test_layouts=N ...) or benchmarks/seg_postprocess.py --test-shards N")
    setup(args.threads)
    recipe = json.loads((data / "recipe.json").read_text()) if (data / "recipe.json").is_file() else {}
    doc: dict[str, Any] = {"context": context(vars(args)), "data": str(data), "recipe": recipe,
                           "classes": args.classes,
                           "models": [score(m, data, args.threads, args.classes, args.by_renderer)
                                      for m in args.models.split(",") if m]}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"seg_compare_{args.tag}.json", doc)
    rows = []
    for m in doc["models"]:
        for split, r in m["splits"].items():
            rows.append([f"`{m['model']}`", split, r["views"], r["silhouette_iou"], r["object_iou"], r["miss_rate"],
                         r["false_positives_per_view"], r["seconds_per_view"]])
    mix = recipe.get("distractor_mix", "v4") if recipe else "?"
    L = [f"# Learned segmenters on the same rendered test views (`{data.name}`)", "", context_md(doc["context"]), "",
         f"Test splits of `{data}` (data recipe seed {recipe.get('seed', '?')}, renderer weights "
         f"{recipe.get('renderer_weights') or recipe.get('renderer', '?')}, distractor mix {mix}): every model reads "
         "the same views with its own card's post-processing. Ground truth: "
         + ("the glass objects (opaque ones are background; a class-head model is prompted for transparent)"
            if args.classes == "transparent" else "every labelled object (a class-head model prompted for every class)")
         + ". Silhouette IoU: union of the instances against the union of the ground truth per view (false "
         "positives count); object IoU: best match per (view, GT object with >= 100 visible px); a miss is object "
         "IoU < 0.5.", "",
         md_table(["model", "split", "views", "silhouette IoU", "object IoU", "miss rate", "false pos / view",
                   "s / view"], rows)] + ([args.note, ""] if args.note else [])
    (out / f"seg_compare_{args.tag}.md").write_text("\n".join(L) + "\n")
    print("\n".join(str(r[:5]) for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
