"""Segmentation-error benchmark: how mask errors propagate into the fast-mode reconstruction.

For every noisy-segmenter preset (``none``, ``mild``, ``moderate``, ``severe``, ``paper``) and scene, the GT
masks of the cached capture are corrupted (seed = scene seed), their quality against GT is measured
(union-silhouette IoU mean/min per view, object IoU, missed/spurious fractions) and the default fast-mode
``reconstruct()`` is run on them; the reconstruction is scored against the ground truth (objects found vs
present, silhouette IoU vs GT masks over all views at the capture resolution, dense Chamfer mm, volume IoU).
This gives the GT-vs-segmented row of the paper's Table I a measured counterpart for the fast mode.

Writes ``<out>/segmentation.json`` (after every scene, so an interrupted run keeps what it measured) and
``<out>/segmentation.md``.

Run: ``python benchmarks/segmentation.py [--quick] [--scenarios rw3 rw4 rw7 syn5] [--presets ...]``.
``--presets ... learned`` adds a row whose masks come from the learned segmenter reading the capture's RGB
(the shipped U-Net; per-view ids without correspondence) instead of corrupted GT masks.

``--learned [--renderer mujoco|pbr]`` instead measures the learned segmenter itself on the held-out rendered
splits of its data recipe (``test_layouts``: seen shapes, unseen layouts; ``test_shapes``: scenes holding the
held-out shapes), 12 full 640x360 views per scene on the capture rig's layout: object IoU per type, miss rate
per view, false positives per view and the miss correlation between neighbouring views; writes
``<out>/segmentation_learned_<renderer>.{json,md}`` and a figure of its masks on one render
(``<out>/learned_<renderer>_masks.png``). The test splits (the model card's recipe with that renderer,
``--spp``, optionally ``--test-shards`` shards of the first ``--test-scenes`` scenes) are rendered on first use
(resumable shards under ``runs/seg_data/<renderer>[_test]``): ~5 min with MuJoCo; with PBR ~7 s per 640x360
view at 16 spp on one core (96 views for ``--test-scenes 4``), far longer when the machine is shared;
evaluation ~0.3 s per view. Run: ``python benchmarks/segmentation.py --learned [--renderer pbr
--test-shards 1 --test-scenes 4] [--model FILE]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
import numpy as np  # noqa: E402

from torm.errors import ReconstructionError  # noqa: E402
from torm.reconstruction import ReconstructionConfig, reconstruct  # noqa: E402
from torm.segmentation import make_segmenter  # noqa: E402

log = logging.getLogger("bench.segmentation")

PRESETS = ("none", "mild", "moderate", "severe", "paper")
#: rows that run a segmenter on the capture's RGB instead of corrupting its GT masks
SEGMENTER_ROWS = ("learned",)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny run for tests: 1 scene, 12 views 320x180, grid 32")
    p.add_argument("--out", type=Path, default=bc.RESULTS, help="result folder")
    p.add_argument("--cache", type=Path, default=bc.CAPTURE_CACHE, help="capture cache folder")
    p.add_argument("--scenarios", nargs="+", default=None)
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS + SEGMENTER_ROWS)
    p.add_argument("--learned", action="store_true", help="held-out evaluation of the learned segmenter (see above)")
    p.add_argument("--renderer", default="mujoco", choices=("mujoco", "pbr"), help="--learned: data renderer")
    p.add_argument("--model", default="", help="--learned: ONNX file (default: the shipped model)")
    p.add_argument("--data", type=Path, default=None,
                   help="--learned: shard folder (default runs/seg_data/<renderer>_test)")
    p.add_argument("--spp", type=int, default=16, help="--learned, pbr: samples per pixel (16 = capture.pbr default)")
    p.add_argument("--test-scenes", type=int, default=None,
                   help="--learned: scenes per test shard (default: the model's recipe; the first N of its scenes)")
    p.add_argument("--test-shards", type=int, default=None, help="--learned: shards per test split (default: recipe)")
    p.add_argument("--fixture-shards", type=int, default=None,
                   help="--learned: shards of test_fixtures (glassware in a tube rack or a tray; default: recipe)")
    p.add_argument("--views", type=int, default=50)
    p.add_argument("--scale", type=float, default=0.5, help="image scale of 1280x720 (0.5 -> 640x360)")
    p.add_argument("--grid", type=int, default=48)
    p.add_argument("--refine-iters", type=int, default=None, help="fast-mode refinement steps (default: config)")
    p.add_argument("--threads", type=int, default=bc.THREADS)
    p.add_argument("--no-union", dest="union", action="store_false",
                   help="skip the second reconstruction from the same masks with the instance ids merged")
    a = p.parse_args(argv)
    if a.quick:
        a.scenarios = a.scenarios or ["rw4"]
        a.presets = ["none", "paper"] if a.presets == list(PRESETS) else a.presets
        a.views, a.scale, a.grid = 12, 0.25, 32
        a.refine_iters = 10 if a.refine_iters is None else a.refine_iters
    a.scenarios = a.scenarios or ["rw3", "rw4", "rw7", "syn5"]
    return a


def run_one(scene: bc.Scene, preset: str, a: argparse.Namespace) -> dict[str, Any]:
    """Corrupt the GT masks with ``preset``, reconstruct (fast mode) and score against the ground truth."""
    if preset in SEGMENTER_ROWS:
        seg = make_segmenter(preset, {"threads": a.threads}).segment(scene.capture)
    else:
        seg = make_segmenter("noisy", {"preset": preset, "seed": scene.seed}).segment(scene.capture)
    q = seg.info["quality"]
    ev = seg.info.get("events", [])
    out: dict[str, Any] = {
        "input_iou_mean": q["silhouette_iou_mean"], "input_iou_min": q["silhouette_iou_min"],
        "input_object_iou": q["object_iou_mean"], "input_missed_fraction": q["missed_fraction"],
        "input_spurious_fraction": q["spurious_fraction"], "n_events": len(ev) if isinstance(ev, list) else None,
    }
    kw: dict[str, Any] = {"grid_res": a.grid}
    if a.refine_iters is not None:
        kw["refine_iters"] = a.refine_iters
    cfg = ReconstructionConfig(mode="fast", **kw)
    out["config"] = {"grid_res": cfg.grid_res, "refine_iters": cfg.refine_iters, "vote_tolerance": cfg.vote_tolerance}
    t = time.perf_counter()
    try:
        rec = reconstruct(seg.apply(scene.capture), cfg)
        out["time_s"] = time.perf_counter() - t
        out.update(bc.evaluate_meshes(list(rec.object_meshes), scene))
    except ReconstructionError as exc:
        log.warning("%s/%s: reconstruction failed: %s", scene.name, preset, exc)
        out.update({"error": str(exc), "n_present": len(scene.gt_meshes), "n_found": 0})
    if a.union:
        # the same silhouettes with every id merged into 1: the geometry only uses the union; the ids only feed
        # reconstruct()'s per-object validation, which spurious blob ids can fail
        u: dict[str, Any] = {}
        t = time.perf_counter()
        try:
            rec = reconstruct(scene.capture.with_masks((seg.masks_vxhxw > 0).astype(np.int32)), cfg)
            u["time_s"] = time.perf_counter() - t
            u.update(bc.evaluate_meshes(list(rec.object_meshes), scene))
        except ReconstructionError as exc:
            u.update({"error": str(exc), "n_present": len(scene.gt_meshes), "n_found": 0})
        out["union"] = u
    return out


def build_report(doc: dict[str, Any], out: Path) -> None:
    rows, srows = [], []
    by_preset: dict[str, list[dict[str, Any]]] = {}
    for key, sc in doc["scenes"].items():
        for preset, r in sc["presets"].items():
            by_preset.setdefault(preset, []).append(r)
            found = f"{r.get('n_found', 0)}/{r['n_present']}" + (f" +{r['n_spurious']}" if r.get("n_spurious") else "")
            rows.append([key, preset, "ids", r["input_iou_mean"], r["input_iou_min"], r["input_object_iou"], found,
                         r.get("silhouette_iou_mean"), r.get("silhouette_iou_min"), r.get("chamfer_mm"),
                         r.get("volume_iou"), r.get("time_s"), r.get("error", "")[:90]])
            if "union" in r:
                u = r["union"]
                inp = {k: v for k, v in r.items() if k.startswith("input_")}
                by_preset.setdefault(preset + " (union)", []).append({**inp, **u})
                found = f"{u.get('n_found', 0)}/{u['n_present']}" + (f" +{u['n_spurious']}" if u.get("n_spurious")
                                                                      else "")
                rows.append([key, preset, "union", r["input_iou_mean"], r["input_iou_min"], r["input_object_iou"],
                             found, u.get("silhouette_iou_mean"), u.get("silhouette_iou_min"), u.get("chamfer_mm"),
                             u.get("volume_iou"), u.get("time_s"), u.get("error", "")[:90]])

    def mean(rs: list[dict[str, Any]], k: str) -> float:
        v = [r[k] for r in rs if r.get(k) is not None and np.isfinite(r[k])]
        return float(np.mean(v)) if v else float("nan")

    summary = {}
    for preset in [p for q in PRESETS + SEGMENTER_ROWS for p in (q, q + " (union)")]:
        rs = by_preset.get(preset)
        if not rs:
            continue
        ok = [r for r in rs if "error" not in r]
        s = {"scenes": len(rs), "failed": len(rs) - len(ok),
             "objects_found": f"{sum(r.get('n_found', 0) for r in rs)}/{sum(r['n_present'] for r in rs)}",
             "spurious": sum(r.get("n_spurious", 0) for r in ok),
             **{k: mean(rs, k) for k in ("input_iou_mean", "input_object_iou")},
             "input_iou_min": float(min(r["input_iou_min"] for r in rs)),
             **{k: mean(ok, k) for k in ("silhouette_iou_mean", "chamfer_mm", "volume_iou", "time_s")}}
        summary[preset] = s
        srows.append([preset, s["scenes"], s["input_iou_mean"], s["input_iou_min"], s["input_object_iou"],
                      s["objects_found"], s["spurious"], s["failed"], s["silhouette_iou_mean"], s["chamfer_mm"],
                      s["volume_iou"], s["time_s"]])
    # which instance id made reconstruct() fail: a GT object (1..n_objects) or a spurious one the segmenter added
    import re

    fails = [(sc["n_objects"], re.search(r"object (\d+)", r.get("error", ""))) for sc in doc["scenes"].values()
             for r in sc["presets"].values() if "error" in r]
    n_spur = sum(1 for n, m in fails if m and int(m.group(1)) > n)
    summary["failures_with_instance_ids"] = {"total": len(fails), "caused_by_a_spurious_instance_id": n_spur}
    doc["summary"] = summary
    bc.write_json(out / "segmentation.json", doc)
    a = doc["context"]["args"]
    md = ["# Segmentation errors -> reconstruction (fast mode)\n",
          f"Generated by `benchmarks/segmentation.py`. Scenes {', '.join(doc['scenes'])}; {a['views']} views at scale "
          f"{a['scale']} of 1280x720; noisy-segmenter presets {', '.join(a['presets'])} (seed = scene seed); default "
          f"fast mode (grid {a['grid']}, refinement steps "
          f"{a['refine_iters'] if a['refine_iters'] is not None else 'default (100)'}). Input IoU: corrupted vs GT "
          "union silhouettes per view (mean over views; min = worst view); object IoU: best-match IoU per (view, "
          "GT object). Reconstruction metrics are against the ground truth: silhouette IoU vs GT masks over all "
          f"views at the capture resolution, Chamfer from {bc.CHAMFER_POINTS} dense samples per side, volume IoU "
          "of the union of objects vs the union of GT shells. A failed reconstruction (ReconstructionError) counts "
          "0 objects found and is left out of the IoU/Chamfer/volume means. Each preset is reconstructed twice: "
          "with the masks' instance ids as the segmenter labels them (spurious blobs get their own id) and as "
          "'(union)' with every id merged into 1; `reconstruct()` builds the geometry from the union either way, the "
          "ids only feed its per-object input validation and coverage check.\n",
          "**Run context**\n", bc.context_md(doc["context"]),
          "## Per preset (mean over scenes)\n",
          bc.md_table(["preset", "scenes", "input IoU mean", "input IoU min", "input object IoU", "objects found",
                       "spurious", "failed", "IoU vs GT", "Chamfer mm", "vol IoU", "time s"], srows),
          f"\nReconstructions that failed with the segmenter's instance ids: {len(fails)}, of which {n_spur} named an "
          "instance id that is not a GT object (a spurious blob the segmenter added, seen in a few views), which "
          "`reconstruct()`'s per-object validation/coverage check rejects although the visual hull carves it away.\n",
          "\nPaper Table I (DMTet-Multi, envelope loss, 8000 iterations): IoU 0.876 with GT silhouettes, 0.808 with "
          "segmented ones (IoU against the supervision masks). The `none` row is the GT-mask reference here.\n",
          "## Per scene\n",
          bc.md_table(["scene", "preset", "mask ids", "input IoU mean", "input IoU min", "input object IoU",
                       "found/present", "IoU vs GT mean", "IoU vs GT min", "Chamfer mm", "vol IoU", "time s",
                       "error"], rows)]
    (out / "segmentation.md").write_text("\n".join(md))
    log.info("wrote %s", out / "segmentation.md")


def _ci(stats: dict[str, Any]) -> str:
    ci = stats.get("iou_ci95_scenes")
    return f"{ci[0]:.3f}-{ci[1]:.3f}" if ci else "-"


def _learned_report(doc: dict[str, Any], out: Path, tag: str) -> None:
    """Markdown of the held-out evaluation (``segmentation_<tag>.md``)."""
    card = doc["model_card"]
    rows, trows = [], []
    for split, r in doc["splits"].items():
        if "error" in r:
            rows.append([split, r["error"][:80], *[None] * 11])
            continue
        c = r["miss_correlation_neighbour_views"]
        rows.append([split, r["scenes"], r["views"], r["silhouette_iou_mean"], r["object"]["iou_mean"],
                     _ci(r["object"]), r["held_out_objects"]["iou_mean"], _ci(r["held_out_objects"]),
                     r["miss_rate_per_view_mean"], r["views_with_a_miss"],
                     r["false_positives_per_view"], c.get("phi"),
                     f"{bc.fmt(c.get('p_miss_given_neighbour_missed'))} vs {bc.fmt(c.get('p_miss'))}"])
        for t, st in r["per_type"].items():
            trows.append([split, t, "held out" if t in card["held_out_shapes"] else "seen", st["n"], st["iou_mean"],
                          st["iou_median"], st["miss_rate"]])
    tgt = doc["targets"]
    d = card["data"]
    md = ["# Learned segmenter on held-out renders\n",
          f"Generated by `benchmarks/segmentation.py --learned`. Segmenter `learned` (model `{doc['model']}`, "
          f"{card['parameters']} parameters, trained on `{d['renderer']}` renders: "
          f"{card['dataset']['train_views']} views of {card['dataset']['train_scenes']} scenes, "
          f"{card['training']['steps']} steps, {card['training']['wall_s'] / 60:.0f} min on "
          f"{card['train'].get('threads', 1)} thread(s)). Test renderer "
          f"`{doc['renderer']}`; full {d['full_width']}x{d['full_height']} frames, {d['test_views']} views per scene "
          "on the capture rig's layout (radius 0.5 m, elevation 20-80 deg). Held-out shapes (never in training): "
          f"{', '.join(card['held_out_shapes'])}. Object IoU: per (view, GT object with >= {doc['min_visible_px']} "
          f"visible px), best IoU with any predicted instance; a miss is IoU < {doc['match_iou']}; a false positive "
          f"is a predicted instance with IoU < {doc['match_iou']} against every GT object. Miss correlation: phi "
          "coefficient of an object's miss indicators in a view and in its nearest view (by viewing direction), "
          "and P(miss | neighbour missed) vs P(miss). 95 % CI: percentile bootstrap of the mean over scenes (the "
          "views of a scene are not independent). Nothing was tuned on these splits (checkpoint and "
          f"post-processing chosen on `{card['train'].get('val_split', 'val')}`). Post-processing: "
          + (", ".join(f"{k} {v}" for k, v in doc["postprocess"].items()) if doc.get("postprocess")
             else "0.5 / 0.5 / 8")
          + " (`benchmarks/seg_postprocess.md`).\n",
          f"Targets: object IoU >= {tgt['unseen_layouts_iou']} on unseen layouts (`test_layouts`: "
          f"{bc.fmt(tgt['unseen_layouts_measured'])}, **{'met' if tgt['unseen_layouts_met'] else 'not met'}**); "
          f">= {tgt['unseen_shapes_iou']} on unseen shapes (held-out objects of `test_shapes`: "
          f"{bc.fmt(tgt['unseen_shapes_measured'])}, **{'met' if tgt['unseen_shapes_met'] else 'not met'}**).\n",
          "**Run context**\n", bc.context_md(doc["context"]),
          "## Per split\n",
          bc.md_table(["split", "scenes", "views", "silhouette IoU", "object IoU", "object IoU 95% CI",
                       "held-out object IoU", "held-out 95% CI",
                       "miss rate / view", "views with a miss", "false pos. / view", "miss phi (neighbours)",
                       "P(miss | nb missed) vs P(miss)"], rows),
          "\n## Per object type\n",
          bc.md_table(["split", "object", "shape", "n (view, object)", "IoU mean", "IoU median", "miss rate"], trows),
          f"\nSegmentation time: {bc.fmt(doc['seconds_per_view'], 3)} s per 640x360 view (onnxruntime, "
          f"{doc['context']['args']['threads']} thread(s)).\n"]
    (out / f"segmentation_{tag}.md").write_text("\n".join(md))


def _mask_figure(seg: Any, data: dict[str, Any], index: int, path: Path) -> None:
    """RGB | predicted instances (colours) | GT for view ``index`` of a loaded split."""
    import cv2

    rgb = data["rgb"][index]
    pred = seg.segment_image(rgb)[0]
    gt = data["mask"][index].astype(np.int32)
    pal = (np.random.default_rng(3).uniform(60, 255, (256, 3))).astype(np.uint8)
    pal[0] = 0

    def over(m: np.ndarray) -> np.ndarray:
        o = rgb.copy()
        o[m > 0] = (0.45 * rgb[m > 0] + 0.55 * pal[m[m > 0] % 256]).astype(np.uint8)
        edge = cv2.morphologyEx((m > 0).astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        o[edge] = 255
        return o

    img = np.concatenate([rgb, over(pred), over(gt)], axis=1)
    for i, t in enumerate(("render", "learned segmenter", "simulator GT")):
        cv2.putText(img, t, (i * rgb.shape[1] + 8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def run_learned(a: argparse.Namespace) -> int:
    """Held-out evaluation of the learned segmenter (``--learned``)."""
    import json

    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter
    from torm.segmentation.training.dataset import DataRecipe, generate, load_split, stored_recipe
    from torm.segmentation.training.evaluate import evaluate

    seg = LearnedSegmenter(LearnedConfig(model=a.model, threads=a.threads))
    card = seg.card
    if not card:
        raise SystemExit(f"{seg.config.model_path}: no model card (.json) beside it; train with torm train-segmenter")
    from torm.config import from_dict

    over: dict[str, Any] = {"renderer": a.renderer}
    if a.renderer == "pbr":
        over["spp"] = a.spp
    over["shards"] = dict(card["data"].get("shards", {}))
    if a.test_shards:
        over["shards"].update(test_layouts=a.test_shards, test_shapes=a.test_shards)
    if a.fixture_shards is not None:
        over["shards"]["test_fixtures"] = a.fixture_shards
    if a.test_scenes:
        over["scenes_per_shard"] = a.test_scenes
    recipe = from_dict(DataRecipe, dict(card["data"], **over), where="model card data recipe")
    # the model's own recipe (shard counts aside: shard i does not depend on them): its test splits sit beside its
    # training data
    same = ({k: v for k, v in stored_recipe(recipe.to_dict()).items() if k != "shards"}
            == {k: v for k, v in stored_recipe(card["data"]).items() if k != "shards"})
    data_dir = a.data or bc.ROOT / "runs" / "seg_data" / (a.renderer if same else f"{a.renderer}_test")
    splits = ("test_layouts", "test_shapes") + (("test_fixtures",) if recipe.shards.get("test_fixtures") else ())
    generate(recipe, data_dir, splits=splits)
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    doc: dict[str, Any] = {"context": bc.context(args), "segmenter": "learned", "model": seg.config.model_path.name,
                           "renderer": a.renderer, "test_recipe": recipe.to_dict(), "model_card": {k: card[k] for k in (
                               "parameters", "data", "train", "held_out_shapes", "dataset", "training")},
                           "postprocess": dict(seg.postprocess), "splits": {}, "match_iou": 0.5,
                           "min_visible_px": 100}
    t_total, n_total = 0.0, 0
    for split in splits:
        data = load_split(data_dir, split)
        t = time.perf_counter()
        doc["splits"][split] = evaluate(lambda im: seg.segment_image(im)[0], data, tuple(card["held_out_shapes"]))
        t_total += time.perf_counter() - t
        n_total += len(data["rgb"])
        log.info("%s: object IoU %.3f, held-out %s", split, doc["splits"][split]["object"]["iou_mean"],
                 doc["splits"][split]["held_out_objects"]["iou_mean"])
    doc["seconds_per_view"] = t_total / max(n_total, 1)
    lay = doc["splits"]["test_layouts"]["object"]["iou_mean"]
    held = doc["splits"]["test_shapes"]["held_out_objects"]["iou_mean"]
    doc["targets"] = {"unseen_layouts_iou": 0.85, "unseen_layouts_measured": lay,
                      "unseen_layouts_met": bool(lay is not None and lay >= 0.85), "unseen_shapes_iou": 0.75,
                      "unseen_shapes_measured": held, "unseen_shapes_met": bool(held is not None and held >= 0.75)}
    a.out.mkdir(parents=True, exist_ok=True)
    tag = f"learned_{a.renderer}"
    bc.write_json(a.out / f"segmentation_{tag}.json", json.loads(json.dumps(doc, default=str)))
    _learned_report(doc, a.out, tag)
    _mask_figure(seg, load_split(data_dir, "test_shapes"), 6, a.out / f"{tag}_masks.png")
    log.info("wrote %s", a.out / f"segmentation_{tag}.md")
    return 0


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    bc.setup(a.threads)
    if a.learned:
        return run_learned(a)
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    doc: dict[str, Any] = {"context": bc.context(args), "chamfer_points": bc.CHAMFER_POINTS, "scenes": {}}
    for seed in a.seeds:
        for name in a.scenarios:
            scene = bc.get_scene(name, seed, a.views, a.scale, a.cache)
            key = f"{name}_s{seed}"
            doc["scenes"][key] = {"scenario": name, "seed": seed, "n_objects": len(scene.gt_meshes), "presets": {}}
            for preset in a.presets:
                r = run_one(scene, preset, a)
                doc["scenes"][key]["presets"][preset] = r
                log.info("%s %s: input IoU %.3f -> found %s/%s, IoU %s, Chamfer %s mm", key, preset,
                         r["input_iou_mean"], r.get("n_found"), r["n_present"], bc.fmt(r.get("silhouette_iou_mean")),
                         bc.fmt(r.get("chamfer_mm"), 2))
                build_report(doc, a.out)
    build_report(doc, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
