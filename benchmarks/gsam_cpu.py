"""Grounding DINO + SAM on the CPU at the published sizes: export time, file size and seconds per view.

Builds the published architectures with ``transformers`` (``GroundingDinoConfig()`` = grounding-dino-tiny:
Swin-T + BERT-base, 900 queries; ``SamConfig()`` = SAM ViT-B) with random weights (no weights can be downloaded
here; the graph, shapes and cost are those of the trained models), exports them with ``torm export-models``'
code, and times torm's ``grounded_sam`` segmenter on a render: Grounding DINO, the SAM image encoder and the
decoder per box, with onnxruntime on ``--threads`` threads. A 50-view capture's cost is extrapolated from the
per-view times. Writes ``benchmarks/results/gsam_cpu.{json,md}`` with the machine state (cores, load).

    python benchmarks/gsam_cpu.py               # full size (a few minutes, 1 GB of ONNX in a temp folder)
    python benchmarks/gsam_cpu.py --tiny        # the test configs (seconds), to check the script
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._common import RESULTS, THREADS, context, context_md, md_table, setup, write_json  # noqa: E402

RENDER = Path(__file__).resolve().parents[1] / "tests" / "data" / "learned_seg_view.png"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiny", action="store_true", help="small configs (a check of the script, not a result)")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime threads (default: the free cores)")
    ap.add_argument("--views", type=int, default=3, help="views timed (the median is reported)")
    ap.add_argument("--name", default=None, help="result file stem (default gsam_cpu, gsam_cpu_tiny with --tiny)")
    args = ap.parse_args(argv)
    threads = setup(args.threads or THREADS)
    from torm.segmentation.export import export_grounding_dino, export_sam, load_models, write_vocab
    from torm.segmentation.grounded_sam import GroundedSAMConfig, GroundedSAMSegmenter
    from torm.segmentation.tokenizer import WordPieceTokenizer, grounding_text_inputs

    ctx = context(vars(args))
    rgb = cv2.resize(cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB), (1280, 720))  # the D455's size
    out: dict = {"context": ctx, "tiny": args.tiny, "onnxruntime_threads": threads}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        t0 = time.perf_counter()
        g, s = load_models(random_weights=True, tiny=args.tiny)
        out["build_s"] = round(time.perf_counter() - t0, 1)
        out["parameters"] = {"grounding_dino": sum(p.numel() for p in g.parameters()),
                             "sam": sum(p.numel() for p in s.parameters())}
        vocab = write_vocab(d / "vocab.txt")
        prompt = "clear glass. transparent object."
        n_tokens = grounding_text_inputs(WordPieceTokenizer.from_file(vocab), prompt).length
        hw = (128, 224) if args.tiny else (800, 1333)  # the official resize of a 16:9 image
        gd = export_grounding_dino(g, d / "gdino.onnx", hw, n_tokens)
        enc, dec = export_sam(s, d / "sam_encoder.onnx", d / "sam_decoder.onnx")
        del g, s
        out["exports"] = {m.path.name: {"export_s": m.card["export_s"], "megabytes": round(m.card["bytes"] / 1e6, 1)}
                          for m in (gd, enc, dec)}
        seg = GroundedSAMSegmenter(GroundedSAMConfig(
            gdino_model=str(gd.path), bert_vocab=str(vocab), sam_encoder=str(enc.path), sam_decoder=str(dec.path),
            prompt=prompt, box_threshold=0.0, text_threshold=0.0, max_detections=5, threads=threads))
        per: dict[str, list[float]] = {"gdino": [], "sam_encoder": [], "sam_decoder_per_box": [], "view": []}
        for _ in range(args.views):
            timings: dict[str, float] = {}
            t = time.perf_counter()
            _, dets = seg.segment_image(rgb, timings)
            per["view"].append(time.perf_counter() - t)
            per["gdino"].append(timings["gdino"])
            per["sam_encoder"].append(timings.get("sam_encoder", 0.0))
            per["sam_decoder_per_box"].append(timings.get("sam_decoder", 0.0) / max(len(dets), 1))
    med = {k: round(statistics.median(v), 3) for k, v in per.items()}
    out["seconds_per_view_median"] = med
    out["capture_50_views_min"] = round(50 * med["view"] / 60, 1)
    out["load_avg_end"] = list(os.getloadavg())
    name = args.name or ("gsam_cpu_tiny" if args.tiny else "gsam_cpu")
    write_json(RESULTS / f"{name}.json", out)
    rows = [[k, f"{v:.2f}"] for k, v in med.items()]
    md = [f"# Grounding DINO + SAM on the CPU ({'tiny test configs' if args.tiny else 'published sizes'}, random "
          "weights)", "", context_md(ctx), "",
          f"Models built with `transformers` from their default configs (Grounding DINO Swin-T + BERT-base, "
          f"{out['parameters']['grounding_dino'] / 1e6:.0f} M parameters; SAM ViT-B, "
          f"{out['parameters']['sam'] / 1e6:.0f} M) with random weights: the graph, shapes and cost of the trained "
          f"models. Exported with `torm export-models`' code, run by torm's `grounded_sam` segmenter with "
          f"onnxruntime on {threads} thread(s) on a 1280x720 render, Grounding DINO at {hw[0]}x{hw[1]}, "
          f"{n_tokens} tokens, up to 5 boxes per view; median of {args.views} views.", "",
          md_table(["export", "seconds", "MB"], [[k, str(v["export_s"]), str(v["megabytes"])]
                                                 for k, v in out["exports"].items()]), "",
          md_table(["stage", "seconds per view (median)"], rows), "",
          f"A 50-view capture: about **{out['capture_50_views_min']} minutes** on this machine "
          f"(load average at the end {out['load_avg_end'][0]:.1f}).", ""]
    (RESULTS / f"{name}.md").write_text("\n".join(md))
    print(json.dumps({"median_s": med, "capture_50_views_min": out["capture_50_views_min"]}))  # noqa: T201
    return out


if __name__ == "__main__":
    main()
