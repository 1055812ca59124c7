"""Calibrate the learned segmenter's post-processing on its validation split; measure it once on the test splits.

The network predicts two maps per view (object foreground, instance-boundary band), or five with the centre
head (plus an instance-centre probability and each pixel's offset to its centre);
:func:`torm.segmentation.instances.instances_from_maps` turns them into instances: ``grouping`` ``boundary``
(``fg_threshold``, ``boundary_threshold``, ``min_core_px``), ``centre`` (``fg_threshold``, ``centre_threshold``,
``nms_px``, ``max_vote_px``) or ``hybrid`` (the boundary instances split by centre votes: all of them). The first
shipped model used the untuned 0.5 / 0.5 / 8 boundary grouping. This script:

1. renders (or reuses) the validation split (:func:`val_split`: the one the model's training run selected on,
   ``val`` or ``val_rig``), ``test_layouts`` and ``test_shapes`` splits of the model card's own data
   recipe (``runs/seg_data/<renderer>``, the folder ``benchmarks/segmentation.py --learned`` uses);
2. runs the network once per view (optionally also on the horizontally flipped view, averaging the two
   maps: test-time augmentation ``flip_tta``);
3. grid-searches the settings (:func:`grid`; for a centre-head model all three groupings) on that split only
   (``val``: random layouts of the training distribution, 320x192 windows; ``val_rig``: library shapes in the
   rig's full frames;
   the training run used it only to pick its checkpoint) by mean object IoU (best-match IoU per (view, GT
   object), :func:`torm.segmentation.training.evaluate.evaluate`);
4. reports the default and the chosen setting on both test splits, which take no part in any choice.

Writes ``<out>/seg_postprocess.{json,md}``. With ``--write-card`` the chosen setting is stored in the model
card's ``postprocess`` entry, which :class:`torm.segmentation.learned.LearnedSegmenter` uses when the config
leaves a setting unset. Run: ``python benchmarks/seg_postprocess.py [--write-card]`` (~10 min on 2 cores when
the splits are rendered; rendering them: ~8 min).
"""

from __future__ import annotations

import argparse
import itertools
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

log = logging.getLogger("bench.seg_postprocess")

FG = (0.3, 0.4, 0.5, 0.6, 0.7)
BD = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
CORE = (4, 8, 16, 32)
CENTRE_FG = (0.3, 0.4, 0.5, 0.6)
CENTRE_THR = (0.1, 0.2, 0.3, 0.5)
NMS = (3, 6, 10, 15)
VOTE = (10.0, 20.0, 40.0)
#: val scores a setting can be chosen on (``--select-on``)
SELECT_ON = ("object_iou", "silhouette_iou")
#: every setting key, with the untuned defaults (LearnedSegmenter's POSTPROCESS_DEFAULTS for a 2-map model)
DEFAULT = {"grouping": "boundary", "fg_threshold": 0.5, "boundary_threshold": 0.5, "min_core_px": 8,
           "flip_tta": False, "centre_threshold": 0.3, "nms_px": 5, "max_vote_px": 20.0}
#: the untuned default of a centre-head model
DEFAULT_CENTRE = {**DEFAULT, "grouping": "centre"}


def grid(channels: int, quick: bool = False, flip_tta: bool = True) -> list[dict[str, Any]]:
    """The settings searched on val: the boundary grid (FG x BD x CORE x flip; for a centre-head model a
    16-setting subset), and for a centre-head model the centre grid (CENTRE_FG x CENTRE_THR x NMS x VOTE x flip)
    and a 16-setting hybrid grid. ``flip_tta=False``: only settings with one network run per view (the hybrid
    grid unflipped)."""
    def mk(**kw: Any) -> dict[str, Any]:
        return {**DEFAULT, **kw}

    flips = (False, True) if flip_tta else (False,)
    if channels == 2:
        fg, bd, core = (FG[1:3], BD[2:4], CORE[:2]) if quick else (FG, BD, CORE)
        return [mk(fg_threshold=f, boundary_threshold=b, min_core_px=c, flip_tta=t)
                for f, b, c, t in itertools.product(fg, bd, core, flips)]
    out = [mk(fg_threshold=f, boundary_threshold=b, min_core_px=c, flip_tta=t)
           for f, b, c, t in itertools.product((0.4, 0.5), (0.3, 0.5), (8, 32), flips)]
    cfg, cthr, nms, vote = ((0.5,), (0.3,), (5,), (20.0,)) if quick else (CENTRE_FG, CENTRE_THR, NMS, VOTE)
    out += [mk(grouping="centre", fg_threshold=f, centre_threshold=c, nms_px=n, max_vote_px=v, flip_tta=t)
            for f, c, n, v, t in itertools.product(cfg, cthr, nms, vote, flips)]
    out += [mk(grouping="hybrid", fg_threshold=f, boundary_threshold=b, min_core_px=c, centre_threshold=ct,
               flip_tta=flip_tta) for f, b, c, ct in itertools.product((0.4, 0.5), (0.3, 0.5), (8, 32), (0.2, 0.3))]
    return out[:4] + out[16:18] + out[-2:] if quick else out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_split_args(p)
    p.add_argument("--write-card", action="store_true", help="store the chosen setting in the model card")
    p.add_argument("--quick", action="store_true", help="tiny grid and 1 shard per split (for tests)")
    p.add_argument("--no-flip-tta", action="store_true",
                   help="search only settings with one network run per view (flip TTA doubles the segmentation "
                        "time; use it when the model already misses the speed target)")
    p.add_argument("--select-on", choices=SELECT_ON, default="object_iou",
                   help="the val score that picks the setting: object_iou (best-match IoU per GT object; blind to "
                        "false positives) or silhouette_iou (union IoU per view: false positives on opaque "
                        "look-alikes count)")
    return p.parse_args(argv)


def add_split_args(p: argparse.ArgumentParser) -> None:
    """The options of a script that measures the shipped segmenter on its card's held-out splits."""
    p.add_argument("--out", type=Path, default=bc.RESULTS, help="result folder")
    p.add_argument("--data", type=Path, default=None, help="shard folder (default runs/seg_data/<card renderer>)")
    p.add_argument("--model", default="", help="ONNX file (default: the shipped model)")
    p.add_argument("--cache", type=Path, default=None, help="--quick: folder for its tiny MuJoCo-rendered splits")
    p.add_argument("--threads", type=int, default=bc.THREADS)
    p.add_argument("--test-shards", type=int, default=1,
                   help="shards per test split when the card's recipe rendered none (v4's trained on train and val "
                        "only); the test splits' shards are new seeds either way")


def val_split(seg: Any) -> str:
    """The split a model's choices are made on: its training run's ``val_split`` (``val``: random windows of the
    training distribution; ``val_rig``: library shapes in the rig's full frames, shaped like deployment)."""
    return str((seg.card or {}).get("train", {}).get("val_split", "val"))


def card_splits(a: argparse.Namespace, seg: Any, splits: tuple[str, ...]) -> tuple[Any, dict[str, Any]]:
    """(data recipe, {split: loaded split}) of the model card's recipe, rendered first if missing
    (``--quick``: 1 tiny MuJoCo-rendered shard per split)."""
    import dataclasses

    from torm.config import from_dict
    from torm.segmentation.training.dataset import DataRecipe, generate, load_split

    if not seg.card:
        raise SystemExit(f"{seg.config.model_path}: no model card (.json) beside it")
    recipe = from_dict(DataRecipe, dict(seg.card["data"]), where="model card data recipe")
    data_dir = a.data or bc.ROOT / "runs" / "seg_data" / recipe.renderer
    if a.quick:
        recipe = dataclasses.replace(recipe, renderer="mujoco", shards={s: 1 for s in splits}, scenes_per_shard=1,
                                     test_views=4)
        data_dir = a.data or (a.cache or bc.ROOT / "runs") / "seg_data_quick_mujoco"
    missing = {s: a.test_shards for s in splits if s.startswith("test") and not recipe.shards.get(s)}
    if missing:
        recipe = dataclasses.replace(recipe, shards={**recipe.shards, **missing})
    generate(recipe, data_dir, splits=splits)
    return recipe, {s: load_split(data_dir, s) for s in splits}


def probabilities(seg: Any, rgb_nxhxwx3: np.ndarray) -> dict[bool, list[np.ndarray]]:
    """{flip_tta: [(C, H, W) maps per view]}: plain, and averaged with the horizontally flipped view."""
    return {f: [seg.maps(im, flip_tta=f) for im in rgb_nxhxwx3] for f in (False, True)}


def score(maps: list[np.ndarray], data: dict[str, Any], setting: dict[str, Any],
          held_out: tuple[str, ...]) -> dict[str, Any]:
    """:func:`evaluate` of the instances that ``setting`` extracts from cached maps."""
    from torm.segmentation.instances import instances_from_maps
    from torm.segmentation.training.evaluate import evaluate

    it = iter(maps)
    st = setting

    def segment(_im: np.ndarray) -> np.ndarray:
        m = next(it)[:5]  # a class-head model's 6th map (transparent vs opaque) does not shape instances
        return instances_from_maps(m, st["grouping"], st["fg_threshold"], st["boundary_threshold"],
                                   st["min_core_px"], 30, st["centre_threshold"], st["nms_px"], st["max_vote_px"])[0]

    return evaluate(segment, data, held_out)


def _row(name: str, setting: dict[str, Any], m: dict[str, Any]) -> dict[str, Any]:
    return {"split": name, **setting, "silhouette_iou": m["silhouette_iou_mean"],
            "object_iou": m["object"]["iou_mean"], "held_out_iou": m["held_out_objects"]["iou_mean"],
            "miss_rate": m["object"]["miss_rate"], "false_pos_per_view": m["false_positives_per_view"],
            "per_type": {k: v["iou_mean"] for k, v in m["per_type"].items()}}


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    bc.setup(a.threads)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from tqdm import tqdm

    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter

    seg = LearnedSegmenter(LearnedConfig(model=a.model, threads=a.threads, input_width=0))
    val = val_split(seg)
    splits = (val, "test_layouts", "test_shapes")
    recipe, data = card_splits(a, seg, splits)
    held = tuple(seg.card["held_out_shapes"])
    t0 = time.perf_counter()
    probs = {s: probabilities(seg, data[s]["rgb"]) for s in splits}
    net_s = time.perf_counter() - t0
    settings = grid(seg.channels, a.quick, flip_tta=not a.no_flip_tta)
    default = DEFAULT_CENTRE if seg.channels >= 5 else DEFAULT  # a centre head (5 maps; 6 with the class head)
    if default not in settings:
        settings.insert(0, dict(default))
    val_rows = []
    for st in tqdm(settings, desc="val grid", unit="setting"):
        val_rows.append(_row(val, st, score(probs[val][st["flip_tta"]], data[val], st, held)))
    best = max(val_rows, key=lambda r: r[a.select_on])
    chosen = {k: best[k] for k in DEFAULT}
    default_val = next(r for r in val_rows if all(r[k] == v for k, v in default.items()))
    test_rows = []
    for s in ("test_layouts", "test_shapes"):
        for name, st in (("default", default), ("chosen on val", chosen)):
            r = _row(s, st, score(probs[s][st["flip_tta"]], data[s], st, held))
            r["setting"] = name
            test_rows.append(r)
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    doc = {"context": bc.context(args), "model": seg.config.model_path.name, "renderer": recipe.renderer,
           "recipe": recipe.to_dict(), "val_split": val, "views": {s: int(len(data[s]["rgb"])) for s in splits},
           "channels": seg.channels, "network_seconds": net_s, "select_on": a.select_on, "default": default,
           "chosen": chosen, "val_default": default_val,
           "val_best": best, "val_grid": val_rows, "test": test_rows}
    a.out.mkdir(parents=True, exist_ok=True)
    bc.write_json(a.out / "seg_postprocess.json", json.loads(json.dumps(doc, default=str)))
    (a.out / "seg_postprocess.md").write_text(report(doc))
    if a.write_card:
        path = seg.config.model_path.with_suffix(".json")
        text = path.read_text()
        card = json.loads(text)
        card["postprocess"] = card_entry(doc)
        lines = text.splitlines()  # keep the card's own indentation
        indent = max(1, len(lines[1]) - len(lines[1].lstrip())) if len(lines) > 1 else 1
        path.write_text(json.dumps(card, indent=indent) + "\n")
        log.info("wrote the chosen post-processing into %s", path)
    log.info("chosen %s: val %s %.3f (default %.3f)", chosen, a.select_on, best[a.select_on],
             default_val[a.select_on])
    return 0


def card_entry(doc: dict[str, Any]) -> dict[str, Any]:
    """The model card's ``postprocess`` entry: the chosen setting, how it was chosen and its test figures."""
    keys = ("silhouette_iou", "object_iou", "held_out_iou", "miss_rate", "false_pos_per_view")
    test = {f"{r['split']} ({r['setting']})": {k: r[k] for k in keys} for r in doc["test"]}
    on = doc.get("select_on", "object_iou")
    return {**doc["chosen"], "chosen_by": f"benchmarks/seg_postprocess.py: best mean {on.replace('_', ' ')} on the "
            f"{doc.get('val_split', 'val')} split",
            "val_silhouette_iou": doc["val_best"]["silhouette_iou"],
            "val_silhouette_iou_default": doc["val_default"]["silhouette_iou"],
            "val_object_iou": doc["val_best"]["object_iou"], "val_object_iou_default": doc["val_default"]["object_iou"],
            "test": test, "date_utc": doc["context"]["date_utc"]}


def report(doc: dict[str, Any]) -> str:
    ctx = doc["context"]
    keys = ["grouping", "fg_threshold", "boundary_threshold", "min_core_px", "centre_threshold", "nms_px",
            "max_vote_px", "flip_tta"]
    names = ["grouping", "fg thr", "boundary thr", "min core px", "centre thr", "NMS px", "max vote px", "flip TTA"]
    head = ["split", "setting", *names, "silhouette IoU", "object IoU", "held-out shapes IoU", "miss rate",
            "false pos / view"]
    rows = [[r["split"], r["setting"], *[r.get(k) for k in keys], r["silhouette_iou"], r["object_iou"],
             r["held_out_iou"], r["miss_rate"], r["false_pos_per_view"]] for r in doc["test"]]
    on = doc.get("select_on", "object_iou")
    top = sorted(doc["val_grid"], key=lambda r: -r[on])[:10]
    best_by = {}
    for r in doc["val_grid"]:
        g = r.get("grouping", "boundary")
        if g not in best_by or r[on] > best_by[g][on]:
            best_by[g] = r
    vrows = [[*[r.get(k) for k in keys], r["silhouette_iou"], r["object_iou"], r["miss_rate"],
              r["false_pos_per_view"]] for r in [doc["val_default"], *top, *best_by.values()]]
    types = sorted({t for r in doc["test"] for t in r["per_type"]})
    trows = [[t, *[r["per_type"].get(t) for r in doc["test"]]] for t in types]
    return (
        f"# Learned segmenter: post-processing calibrated on {doc.get('val_split', 'val')}, measured on the test "
        "splits\n\n"
        "Generated by `benchmarks/seg_postprocess.py`. Model `" + doc["model"] + "`, test renders from its card's "
        f"recipe (renderer `{doc['renderer']}`); views: {doc['views']}. The settings are chosen on "
        f"`{doc.get('val_split', 'val')}` only (best mean "
        f"{doc.get('select_on', 'object_iou').replace('_', ' ')}); `test_layouts` / `test_shapes` are "
        "measured once with the default and once with "
        "the chosen setting. Object IoU: best-match IoU per (view, GT object with >= 100 visible px); a miss is "
        "IoU < 0.5. Flip TTA: the maps averaged with those of the horizontally flipped view (2 network "
        f"runs per view). The model has {doc.get('channels', 2)} output maps"
        + (" (centre head: groupings `boundary`, `centre`, `hybrid` searched)" if doc.get("channels") == 5 else "")
        + ".\n\n**Run context**\n\n" + bc.context_md(ctx) + "\n## Test splits\n\n"
        + bc.md_table(head, rows, 3) + "\n## Per object type (object IoU; columns in the order of the rows above)\n\n"
        + bc.md_table(["type", *[f"{r['split']} {r['setting']}" for r in doc["test"]]], trows, 3)
        + f"\n## Validation grid (`{doc.get('val_split', 'val')}`): the default, the 10 best, then the best of "
        "each grouping\n\n"
        + bc.md_table([*names, "silhouette IoU", "object IoU", "miss rate", "false pos / view"], vrows, 3))


if __name__ == "__main__":
    raise SystemExit(main())
