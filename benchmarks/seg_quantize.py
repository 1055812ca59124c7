"""An int8 copy of a learned-segmenter model: quantize on its own validation renders, then time both side by side.

Calibrates :func:`torm.segmentation.quantize.quantize_model` on the first ``--calibration`` views of the model
card's validation split (renders; the real frames stay for scoring), writes the int8 model and its card, and times
fp32 and int8 on ``--views`` views at the model's input size, interleaved (A B A B) in one process with the same
threads. Quality is measured by the scripts that measure every model (``segmentation_real.py``, ``seg_compare.py``)
with ``--models <the int8 file>``.

Writes ``benchmarks/results/seg_quantize[_<tag>].{json,md}``. Run:
``python benchmarks/seg_quantize.py --model v7 --data runs/seg_data/v7 --out-model runs/quant/learned_seg_v7q.onnx``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._common import RESULTS, check_tag, context, context_md, md_table, setup, write_json  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="v7", help="the fp32 model (short name or .onnx path)")
    ap.add_argument("--data", required=True, help="shard folder of the model's data recipe (its val split)")
    ap.add_argument("--out-model", required=True, help="the int8 .onnx to write")
    ap.add_argument("--calibration", type=int, default=48, help="validation views to calibrate on")
    ap.add_argument("--views", type=int, default=50, help="views per timing pass")
    ap.add_argument("--repeats", type=int, default=2, help="A B rounds")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--full-range", action="store_true", help="8-bit weights (default 7: reduce_range)")
    ap.add_argument("--tag", default="")
    a = ap.parse_args(argv)
    setup(a.threads)
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter, model_fingerprint
    from torm.segmentation.quantize import quantize_model
    from torm.segmentation.training.dataset import load_split

    val = load_split(Path(a.data), "val")["rgb"]
    calib = list(val[: a.calibration])
    out = quantize_model(a.model, a.out_model, calib, f"{a.data}/val, the first {len(calib)} views",
                         reduce_range=not a.full_range, threads=a.threads)
    fp = LearnedSegmenter(LearnedConfig(model=a.model, threads=a.threads))
    q = LearnedSegmenter(LearnedConfig(model=str(out), threads=a.threads))
    views = [val[i % len(val)] for i in range(a.views)]
    for seg in (fp, q):  # warm-up
        seg.maps(views[0])
    times: dict[str, list[float]] = {"fp32": [], "int8": []}
    for _ in range(a.repeats):
        for name, seg in (("fp32", fp), ("int8", q)):
            t = time.perf_counter()
            for v in views:
                seg.maps(v, flip_tta=False)
            times[name].append(time.perf_counter() - t)
    agree = []
    for v in views[:10]:
        m0, m1 = fp.maps(v, flip_tta=False)[0] > 0.5, q.maps(v, flip_tta=False)[0] > 0.5
        agree.append(float((m0 & m1).sum() / max((m0 | m1).sum(), 1)))
    best = {k: min(v) for k, v in times.items()}
    ctx = context(vars(a))
    doc = {"context": ctx, "fp32": model_fingerprint(fp.config.model_path), "int8": model_fingerprint(out),
           "input_width": fp.input_width, "views": a.views, "seconds": times, "best_seconds": best,
           "speedup": best["fp32"] / best["int8"], "foreground_iou_fp32_vs_int8": float(np.mean(agree)),
           "size_mb": {"fp32": fp.config.model_path.stat().st_size / 1e6, "int8": out.stat().st_size / 1e6}}
    stem = f"seg_quantize_{check_tag(a.tag)}" if a.tag else "seg_quantize"
    write_json(RESULTS / f"{stem}.json", doc)
    md = [f"# Int8 copy of `{doc['fp32']}`\n",
          f"Quantized by `torm.segmentation.quantize.quantize_model` (onnxruntime QDQ, per-channel int8 weights, "
          f"{'8' if a.full_range else '7'}-bit weight range, uint8 activations) on {len(calib)} views of "
          f"`{a.data}/val` (renders). Time of the segmenter's maps (resize, network, probabilities) for "
          f"{a.views} views at {fp.input_width} px input on {a.threads} "
          f"threads, fp32 and int8 interleaved {a.repeats} times (best of each). Foreground IoU: the two models' "
          "foreground (p > 0.5) on 10 of the views.\n",
          md_table(["model", "file", "size (MB)", f"s / {a.views} views (best)", "all rounds"],
                   [[k, f"`{doc[k]}`", f"{doc['size_mb'][k]:.1f}", f"{best[k]:.2f}",
                     ", ".join(f"{t:.2f}" for t in times[k])] for k in ("fp32", "int8")]),
          f"\nSpeed-up {doc['speedup']:.2f}x; foreground IoU fp32 vs int8 {doc['foreground_iou_fp32_vs_int8']:.3f}. "
          "Quality on real frames and held-out renders: `segmentation_real.md`, `seg_compare_*.md` (rows of the "
          "int8 file).\n", "## Run context\n", context_md(ctx)]
    (RESULTS / f"{stem}.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
