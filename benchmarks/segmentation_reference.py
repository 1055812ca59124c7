"""Segmenters with and without a reference pass, on PBR captures of the benchmark suites, per table texture.

For every scenario of ``--suites`` (rw, lab, syn_hard; scenario k of the list gets layout seed k, so table textures
and lights vary across scenes), a PBR capture of ``--views`` rig views at ``--scale`` x 1280x720 is rendered with its
reference pass (``SimCameraRig.capture(reference=True)``: the same cameras over the empty workspace, independent
render noise) and cached under ``--cache``. Each segmenter of ``--rows`` then segments every capture:

``learned:<model>``   the learned segmenter with that model file (RGB only; ``learned_seg`` = the shipped v3);
``reference:<model>`` a reference-mode learned model (reads scene + reference);
``difference``        the plain thresholded difference (``torm.segmentation.reference``);
``difference:<sigma>`` the same after Gaussian smoothing of both images (sigma in px; ``auto``, the default: none on
                      a noise-free pair, 1.5 px otherwise).

Scores per view: union-mask IoU against the simulator's masks of the glass objects (``glass``; opaque objects count
as background, what a transparent-object segmenter should output) and of every object (``all``); precision and
recall of the glass union. Grouped by suite and by the table pattern the layout seed drew (wood, stone, checker,
solid). Writes ``benchmarks/results/segmentation_reference.{json,md}``.

Run: ``python benchmarks/segmentation_reference.py --rows learned:learned_seg,learned:runs/seg_v4/learned_seg_v4.onnx,
reference:runs/seg_v4ref/learned_seg_v4ref.onnx,difference`` (capture rendering: minutes, cached).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks._common import RESULTS, ROOT, context, context_md, md_table, setup, write_json  # noqa: E402

log = logging.getLogger("segmentation_reference")


def scenarios(suites: list[str], seed_offset: int = 0) -> list[tuple[str, str, int]]:
    """(suite, scenario, layout seed) for every scenario of the suites, seeds ``seed_offset`` + 0, 1, 2, ... in
    order (another offset draws other layouts, tables and lights: a development set for choosing a setting)."""
    from sim.scenes.scenario import list_scenarios

    out: list[tuple[str, str, int]] = []
    for suite in suites:
        for name in list_scenarios(suite):
            out.append((suite, name, seed_offset + len(out)))
    return out


def _capture_job(args: tuple[str, int, int, float, int, str, str]) -> str:
    """Render one scenario's capture with its reference pass into the cache (one process, one thread)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    scenario, seed, views, scale, spp, folder, renderer = args
    if (Path(folder) / "transforms.json").exists():
        return folder
    from sim.cameras.renderers import make_renderer
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world
    from torm.capture.io import save_capture
    from torm.capture.render_settings import PbrSettings

    world = build_world(scenario, seed, robot=None)
    r = None
    if renderer != "mujoco":
        variant = "scalar_rgb" if renderer == "pbr_scalar" else "auto"
        r = make_renderer("pbr", world, PbrSettings(spp=spp, threads=1, cache=False, variant=variant))
    with SimCameraRig.from_world(world, CameraRigConfig(n_views=views, scale=scale), rgb_renderer=r) as rig:
        cap = rig.capture(reference=True)
    cap.metadata["transparent_ids"] = [o.instance_id for o in world.objects if o.transparent]
    save_capture(cap, folder)
    return folder


def make_row(row: str) -> tuple[str, Any]:
    """(label, segmenter) of a ``--rows`` entry."""
    from torm.segmentation import make_segmenter
    from torm.segmentation.learned import LearnedConfig, model_fingerprint

    kind, _, model = row.partition(":")
    if kind == "difference":  # difference (the default smoothing), difference:<blur sigma px> or difference:auto
        seg = make_segmenter("difference", {"blur_sigma_px": model if model == "auto" else float(model)}
                             if model else {})
        b = seg.config.blur_sigma_px
        return "difference, blur " + ("auto (0 on noise-free pairs, else 1.5 px)" if b == "auto" else f"{b:g} px"), seg
    path = LearnedConfig(model=model).model_path
    seg = make_segmenter("learned", {"model": str(path), "threads": 2})
    if kind == "reference" and not seg.needs_reference:
        raise SystemExit(f"{path} is not a reference-mode model (3 input channels); use learned:{model}")
    return f"{kind} `{model_fingerprint(path)}`", seg


def score(pred_hxw: np.ndarray, true_hxw: np.ndarray) -> dict[str, float]:
    """IoU, precision and recall of a (H, W) bool prediction against a (H, W) bool truth. A view without glass
    (rw2 holds only an opaque cup) scores 1 on all three when nothing is predicted there, 0 otherwise."""
    tp, fp, fn = (float(np.sum(pred_hxw & true_hxw)), float(np.sum(pred_hxw & ~true_hxw)),
                  float(np.sum(~pred_hxw & true_hxw)))
    if tp + fp + fn == 0:
        return {"iou": 1.0, "precision": 1.0, "recall": 1.0}
    return {"iou": tp / max(tp + fp + fn, 1.0), "precision": tp / max(tp + fp, 1.0), "recall": tp / max(tp + fn, 1.0)}


def segment_and_score(seg: Any, cap: Any) -> dict[str, float]:
    """Segment a capture with ``seg`` and score each view's union mask (:func:`score`) against the glass objects'
    masks (``metadata["transparent_ids"]``, else every object) and against every object's; means over the views,
    plus the segmentation seconds per view."""
    masks = cap.masks()
    true_all = masks > 0
    true_glass = np.isin(masks, cap.metadata.get("transparent_ids", list(cap.object_ids)))
    t = time.perf_counter()
    pred = seg.segment(cap).masks_vxhxw > 0
    sec = (time.perf_counter() - t) / len(cap)
    g = [score(p, m) for p, m in zip(pred, true_glass, strict=True)]
    a = [score(p, m) for p, m in zip(pred, true_all, strict=True)]
    return {"glass_iou": float(np.mean([s["iou"] for s in g])),
            "glass_precision": float(np.mean([s["precision"] for s in g])),
            "glass_recall": float(np.mean([s["recall"] for s in g])),
            "all_iou": float(np.mean([s["iou"] for s in a])), "seconds_per_view": sec}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suites", default="rw,lab,syn_hard")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--renderer", default="pbr", choices=("pbr", "pbr_scalar", "mujoco"),
                    help="who renders the captures (pbr: Mitsuba llvm_ad_rgb; pbr_scalar: scalar_rgb; mujoco)")
    ap.add_argument("--rows", default="learned:learned_seg,difference")
    ap.add_argument("--seed-offset", type=int, default=0,
                    help="layout seeds start here (0: the reported set; another value: a development set)")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "seg_reference_captures"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="", help="result file stem (default segmentation_reference[_<renderer>])")
    args = ap.parse_args(argv)
    args.out = args.out or ("segmentation_reference" + ("" if args.renderer == "pbr" else f"_{args.renderer}"))
    setup()
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from sim.render.textures import table_texture
    from torm.capture.io import load_capture

    scs = scenarios([s for s in args.suites.split(",") if s], args.seed_offset)
    cache = Path(args.cache)
    jobs = [(name, seed, args.views, args.scale, args.spp,
             str(cache / f"{name}_s{seed}_v{args.views}_x{args.scale}_{args.renderer}_spp{args.spp}"), args.renderer)
            for _, name, seed in scs]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max(1, args.workers), mp_context=mp.get_context("spawn")) as ex:
        folders = list(ex.map(_capture_job, jobs))
    t_render = time.perf_counter() - t0
    rows = [make_row(r) for r in args.rows.split(",") if r]
    results: list[dict[str, Any]] = []
    for (suite, name, seed), folder in zip(scs, folders, strict=True):
        cap = load_capture(folder)
        pattern = table_texture(seed, (1.7, 1.8)).pattern
        for label, seg in rows:
            results.append({"row": label, "suite": suite, "scenario": name, "seed": seed, "table": pattern,
                            **segment_and_score(seg, cap)})
        log.info("%s (%s, %s): %s", name, suite, pattern,
                 ", ".join(f"{r['row']}: {r['glass_iou']:.2f}" for r in results[-len(rows):]))
    doc = {"context": context(vars(args)), "render_s": t_render, "scenarios": len(scs), "results": results}
    write_json(RESULTS / f"{args.out}.json", doc)
    labels = [lab for lab, _ in rows]

    def mean(sel: list[dict[str, Any]], k: str) -> float:
        return float(np.mean([r[k] for r in sel])) if sel else float("nan")

    head = ["segmenter", "glass IoU", "precision", "recall", "all-objects IoU", "s / view"]
    body = [[lab, *(mean([r for r in results if r["row"] == lab], k) for k in (
        "glass_iou", "glass_precision", "glass_recall", "all_iou", "seconds_per_view"))] for lab in labels]
    suites = sorted({r["suite"] for r in results})
    tables = sorted({r["table"] for r in results})
    by_suite = [[lab, *(mean([r for r in results if r["row"] == lab and r["suite"] == s], "glass_iou")
                        for s in suites)] for lab in labels]
    by_table = [[lab, *(mean([r for r in results if r["row"] == lab and r["table"] == t], "glass_iou")
                        for t in tables)] for lab in labels]
    n_table = {t: len({r["scenario"] for r in results if r["table"] == t}) for t in tables}
    look = {"pbr": "Mitsuba PBR (llvm_ad_rgb, glass_path)", "pbr_scalar": "Mitsuba PBR (scalar_rgb, plain path)",
            "mujoco": "MuJoCo rasteriser"}[args.renderer]
    L = [f"# Segmentation with and without a reference pass ({look} captures of the suites)", "",
         context_md(doc["context"]), "",
         f"{len(scs)} scenarios ({', '.join(suites)}; scenario k has layout seed {args.seed_offset} + k), "
         f"{args.views} rig views each at "
         f"{round(1280 * args.scale)}x{round(720 * args.scale)}, {look}"
         + (f" at {args.spp} spp" if args.renderer != "mujoco" else "") + ", each with its "
         "reference pass (the same cameras over the empty workspace, independent render noise). Scores per view, "
         "averaged: union IoU against the glass objects' masks (opaque objects are background), precision and "
         "recall of that union, and IoU against every object's mask (rw2 and rw5 hold an opaque cup).", "",
         md_table(head, body), "", "## Glass IoU per suite", "", md_table(["segmenter", *suites], by_suite), "",
         "## Glass IoU per table texture", "",
         md_table(["segmenter", *(f"{t} ({n_table[t]} scenes)" for t in tables)], by_table), "",
         f"Capture rendering: {t_render:.0f} s with {args.workers} processes (cached in `{Path(args.cache).name}`).",
         ""]
    (RESULTS / f"{args.out}.md").write_text("\n".join(L) + "\n")
    print("\n".join(str(b) for b in body))
    return 0


if __name__ == "__main__":
    sys.exit(main())
