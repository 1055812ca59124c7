"""Why the learned segmenter misses objects, and whether splitting instance cores at necks helps.

For each held-out split of the model card's data recipe (its validation split ``val`` or ``val_rig``,
``test_layouts``, ``test_shapes``; the folder
``benchmarks/seg_postprocess.py`` renders or reuses) and the card's calibrated post-processing:

1. every (view, GT object with >= 100 visible px) is classified by
   :func:`torm.segmentation.training.evaluate.miss_causes`: ``ok`` (best IoU >= 0.5), ``background`` (under
   half of it predicted foreground), ``merged`` (its dominant predicted instance also covers other objects),
   ``split`` (no predicted instance holds half of it), ``other``; with the median visible area per category;
2. the neck split (:func:`torm.segmentation.instances.split_cores_at_necks`) is swept over its erosion depth
   (0 = off, the shipped setting); the depth is chosen on the validation split only and the test splits are reported for
   every depth, so the choice can be checked. It acts on boundary cores: with the ``centre`` grouping (a
   centre-head model) only depth 0 is run.

Writes ``<out>/seg_miss_causes.{json,md}``. Run: ``python benchmarks/seg_miss_causes.py`` (~5 min on 2 cores
when the splits are rendered).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
from seg_postprocess import add_split_args, card_splits, val_split  # noqa: E402

log = logging.getLogger("bench.seg_miss_causes")

DEPTHS = (0.0, 2.0, 4.0, 6.0)
TEST_SPLITS = ("test_layouts", "test_shapes")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_split_args(p)
    p.add_argument("--quick", action="store_true", help="1 shard per split, 2 depths (for tests)")
    return p.parse_args(argv)


def causes_of_split(preds: list[np.ndarray], data: dict[str, Any]) -> dict[str, Any]:
    """Counts and median visible area (px) per miss cause over all views of a split."""
    from torm.segmentation.training.evaluate import MISS_CAUSES, miss_causes

    areas: dict[str, list[int]] = {k: [] for k in MISS_CAUSES}
    for pred, gt in zip(preds, data["mask"], strict=True):
        for g, cause in miss_causes(pred, gt).items():
            areas[cause].append(int(np.count_nonzero(gt == g)))
    n_miss = sum(len(v) for k, v in areas.items() if k != "ok")
    return {k: {"n": len(v), "median_area_px": int(np.median(v)) if v else None,
                "share_of_misses": len(v) / n_miss if n_miss and k != "ok" else None}
            for k, v in areas.items()}


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    bc.setup(a.threads)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from tqdm import tqdm

    from torm.segmentation.instances import instances_from_maps
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter
    from torm.segmentation.training.evaluate import evaluate

    seg = LearnedSegmenter(LearnedConfig(model=a.model, threads=a.threads, input_width=0))
    val_name = val_split(seg)
    splits = (val_name, *TEST_SPLITS)
    recipe, data = card_splits(a, seg, splits)
    depths = DEPTHS[:2] if a.quick else DEPTHS
    if seg.postprocess["grouping"] == "centre":
        depths = (0.0,)
    held = tuple(seg.card["held_out_shapes"])
    pp = dict(seg.postprocess)
    t0 = time.perf_counter()
    maps = {s: [seg.maps(im) for im in tqdm(data[s]["rgb"], desc=f"network {s}", unit="view")] for s in splits}
    net_s = time.perf_counter() - t0

    def instances(m: np.ndarray, depth: float) -> np.ndarray:
        return instances_from_maps(m, pp["grouping"], pp["fg_threshold"], pp["boundary_threshold"],
                                   pp["min_core_px"], 30, pp["centre_threshold"], pp["nms_px"], pp["max_vote_px"],
                                   depth)[0]

    causes, sweep = {}, []
    for depth in depths:
        for s in splits:
            preds = [instances(m, depth) for m in maps[s]]
            if depth == 0.0:
                causes[s] = causes_of_split(preds, data[s])
            it = iter(preds)
            m = evaluate(lambda _im, _it=it: next(_it), data[s], held)
            sweep.append({"split": s, "core_split_px": depth, "object_iou": m["object"]["iou_mean"],
                          "held_out_iou": m["held_out_objects"]["iou_mean"], "miss_rate": m["object"]["miss_rate"],
                          "false_pos_per_view": m["false_positives_per_view"]})
    val = [r for r in sweep if r["split"] == val_name]
    chosen = max(val, key=lambda r: (r["object_iou"], -r["core_split_px"]))["core_split_px"]
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    doc = {"context": bc.context(args), "model": seg.config.model_path.name, "renderer": recipe.renderer,
           "postprocess": pp, "views": {s: int(len(data[s]["rgb"])) for s in splits}, "network_seconds": net_s,
           "causes": causes, "neck_split_sweep": sweep, "neck_split_chosen_on_val": chosen, "val_split": val_name}
    a.out.mkdir(parents=True, exist_ok=True)
    bc.write_json(a.out / "seg_miss_causes.json", json.loads(json.dumps(doc, default=str)))
    (a.out / "seg_miss_causes.md").write_text(report(doc))
    log.info("miss causes %s; neck split chosen on val: %s px", {s: {k: v["n"] for k, v in c.items()}
                                                                   for s, c in causes.items()}, chosen)
    return 0


def report(doc: dict[str, Any]) -> str:
    from torm.segmentation.training.evaluate import MISS_CAUSES

    crow = [[s, *[f"{c[k]['n']} ({c[k]['median_area_px']} px)" for k in MISS_CAUSES],
             *[c[k]["share_of_misses"] for k in MISS_CAUSES[1:]]] for s, c in doc["causes"].items()]
    srow = [[r["split"], f"{r['core_split_px']:g}", r["object_iou"], r["held_out_iou"], r["miss_rate"],
             r["false_pos_per_view"]] for r in doc["neck_split_sweep"]]
    return (
        "# Learned segmenter: why objects are missed, and the neck split\n\n"
        "Generated by `benchmarks/seg_miss_causes.py`. Model `" + doc["model"] + "`, renderer `" + doc["renderer"]
        + f"`, post-processing from the model card: `{doc['postprocess']}`; views: {doc['views']}. One row per "
        "(view, GT object with >= 100 visible px); rules in `torm.segmentation.training.evaluate.miss_causes`.\n\n"
        "**Run context**\n\n" + bc.context_md(doc["context"])
        + "\n## Miss causes (count, median visible area)\n\n"
        + bc.md_table(["split", *MISS_CAUSES, *[f"share {k}" for k in MISS_CAUSES[1:]]], crow, 3)
        + "\n## Neck split of instance cores (0 = off, the shipped setting)\n\n"
        + ("The card's grouping is `centre` (instances from centre votes, no boundary cores to split): only depth 0 "
           "ran.\n\n" if doc["postprocess"].get("grouping") == "centre" else
           f"Depth chosen on `{doc.get('val_split', 'val')}`: **{doc['neck_split_chosen_on_val']:g} px** "
           "(ties go to the smaller depth).\n\n")
        + bc.md_table(["split", "core split px", "object IoU", "held-out shapes IoU", "miss rate",
                       "false pos / view"], srow, 4))


if __name__ == "__main__":
    raise SystemExit(main())
