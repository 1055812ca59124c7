"""Seconds to segment a 50-view capture with the learned segmenters, on 2 threads, at each model's input size.

The views are the first ``--views`` rig frames (640x360 PBR renders) of a data folder's ``test_layouts`` split (rendered
by ``torm train-segmenter``; default ``runs/seg_data/v6``). Each row builds :class:`LearnedSegmenter` with
``threads`` onnxruntime threads and its card's post-processing (mirror test-time augmentation as the card says),
reads every view at ``input_width`` (the card's when 0 is not given) and reports the total for ``--views`` views
(the first view, which warms the session, is timed apart), the median per view and the network input size. What the
network costs is separated from the instance post-processing (``maps`` alone vs ``segment_image``).

Writes ``benchmarks/results/segmentation_speed.{json,md}``.
Run: ``python benchmarks/segmentation_speed.py --models v3,v4,v6 --widths 320,640`` (about a minute per row).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks._common import RESULTS, ROOT, check_tag, context, context_md, md_table, setup, write_json  # noqa: E402


def time_row(model: str, width: int, views: np.ndarray, threads: int) -> dict[str, Any]:
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter, model_fingerprint

    seg = LearnedSegmenter(LearnedConfig(model=model, input_width=width, threads=threads))
    t0 = time.perf_counter()
    seg.segment_image(views[0])
    first = time.perf_counter() - t0
    per_net, per_all = [], []
    for v in views:
        t = time.perf_counter()
        seg.maps(v)
        per_net.append(time.perf_counter() - t)
    for v in views:
        t = time.perf_counter()
        seg.segment_image(v)
        per_all.append(time.perf_counter() - t)
    w = seg.input_width or views.shape[2]
    h = int(round(views.shape[1] * w / views.shape[2]))
    return {"model": model_fingerprint(seg.config.model_path), "input_width": w,
            "network_input": [h + (-h % seg.stride), w + (-w % seg.stride)],
            "flip_tta": bool(seg.postprocess["flip_tta"]),
            "first_view_s": first, "total_s": float(np.sum(per_all)), "median_view_s": float(np.median(per_all)),
            "network_total_s": float(np.sum(per_net)), "views": len(views), "threads": threads}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="v3,v4,v6")
    ap.add_argument("--widths", default="0", help="input widths (px); 0 = each model card's")
    ap.add_argument("--data", default=str(ROOT / "runs" / "seg_data" / "v6"))
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    stem = f"segmentation_speed_{check_tag(args.tag)}" if args.tag else "segmentation_speed"
    setup()
    from torm.segmentation.training.dataset import load_split

    rgb = load_split(Path(args.data), "test_layouts")["rgb"]
    if len(rgb) < args.views:
        raise SystemExit(f"{args.data}/test_layouts has {len(rgb)} views, fewer than --views {args.views}")
    views = rgb[:args.views]
    out: dict[str, Any] = {"context": context(vars(args)), "results": []}
    rows = []
    for m in [m for m in args.models.split(",") if m]:
        for w in [int(x) for x in args.widths.split(",")]:
            r = time_row(m, w if w else None, views, args.threads)
            out["results"].append(r)
            rows.append([f"`{r['model']}`", f"{r['input_width']} ({r['network_input'][1]}x{r['network_input'][0]})",
                         "on" if r["flip_tta"] else "off", r["total_s"], r["network_total_s"], r["median_view_s"],
                         r["first_view_s"]])
    write_json(RESULTS / f"{stem}.json", out)
    L = ["# Learned segmenters: seconds to segment a 50-view capture", "", context_md(out["context"]), "",
         f"{args.views} rig views (640x360 PBR renders, `{Path(args.data).name}/test_layouts`), {args.threads} "
         "onnxruntime threads, each model's card post-processing. Total: every view through `segment_image` "
         "(network, resizing, instances); network: `maps` alone. The first view (session warm-up) is timed apart.", "",
         md_table(["model", "input width (network input, px)", "mirror TTA", f"total s / {args.views} views",
                   "network s", "median s / view", "first view s"], rows), ""]
    (RESULTS / f"{stem}.md").write_text("\n".join(L) + "\n")
    print("\n".join(str(r) for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
