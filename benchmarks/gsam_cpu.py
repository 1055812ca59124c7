"""Grounding DINO + SAM on the CPU at the published sizes: export time, file size and seconds per view.

Builds the published architectures with ``transformers`` (``GroundingDinoConfig()`` = grounding-dino-tiny:
Swin-T + BERT-base, 900 queries; ``SamConfig()`` = SAM ViT-B) with random weights (no weights can be downloaded
here; the graph, shapes and cost are those of the trained models), exports them with ``torm export-models``'
code, and times torm's ``grounded_sam`` segmenter on a render: Grounding DINO, the SAM image encoder and the
decoder per box, with onnxruntime on ``--threads`` threads. A 50-view capture's cost is extrapolated from the
per-view times. Writes ``benchmarks/results/gsam_cpu.{json,md}`` with the machine state (cores, load).

    python benchmarks/gsam_cpu.py               # full size (a few minutes, 1 GB of ONNX in a temp folder)
    python benchmarks/gsam_cpu.py --tiny        # the test configs (seconds), to check the script
    python benchmarks/gsam_cpu.py --sam-kind sam2 --boxes learned   # SAM 2.1 Hiera-Tiny prompted by torm's
                                                                    # learned segmenter (sam2_cpu.{json,md})

onnxruntime runs ``--threads`` intra-op threads and one inter-op thread (torm's ``open_session``); its worker
threads spin while waiting (onnxruntime's default), so a core taken by another process slows it far more than its
share: the load average at the start and the end is recorded, and a run on a loaded machine is marked contended.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._common import (  # noqa: E402
    RESULTS,
    THREADS,
    context,
    context_md,
    cpu_busy_s,
    md_table,
    own_cpu_s,
    setup,
    write_json,
)

RENDER = Path(__file__).resolve().parents[1] / "tests" / "data" / "learned_seg_view.png"


def _rss_gb(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of this process from /proc/self/status, GB (1e9 bytes)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def time_views(cfg: dict, views: int) -> dict:
    """Run in a fresh process: load the segmenter, segment the render ``views`` times; stage seconds per view, the
    process's resident memory before loading, after loading and at its peak (GB), boxes in the last view."""
    from torm.segmentation.grounded_sam import GroundedSAMConfig, GroundedSAMSegmenter

    rgb = cv2.resize(cv2.cvtColor(cv2.imread(str(RENDER)), cv2.COLOR_BGR2RGB), (1280, 720))  # the D455's size
    mem = {"rss_before_load_gb": _rss_gb("VmRSS")}
    seg = GroundedSAMSegmenter(GroundedSAMConfig(**cfg))
    mem["rss_after_load_gb"] = _rss_gb("VmRSS")
    per: dict[str, list[float]] = {"boxes": [], "sam_encoder": [], "sam_decoder_per_box": [], "view": []}
    busy0, own0, wall0 = cpu_busy_s(), own_cpu_s(), time.perf_counter()
    dets: tuple = ()
    for _ in range(views):
        timings: dict[str, float] = {}
        t = time.perf_counter()
        _, dets = seg.segment_image(rgb, timings)
        per["view"].append(time.perf_counter() - t)
        per["boxes"].append(timings["gdino"])
        per["sam_encoder"].append(timings.get("sam_encoder", 0.0))
        per["sam_decoder_per_box"].append(timings.get("sam_decoder", 0.0) / max(len(dets), 1))
    wall = time.perf_counter() - wall0
    mem["peak_rss_gb"] = _rss_gb("VmHWM")
    # cores other processes kept busy while the views were timed (the load average lags by minutes)
    other = round(max(0.0, (cpu_busy_s() - busy0) - (own_cpu_s() - own0)) / wall, 2)
    return {"per": per, "memory": {k: round(v, 2) for k, v in mem.items()}, "boxes_per_view": len(dets),
            "other_processes_cores": other}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiny", action="store_true", help="small configs (a check of the script, not a result)")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime threads (default: the free cores)")
    ap.add_argument("--views", type=int, default=3, help="views timed (the median is reported)")
    ap.add_argument("--sam-kind", choices=("sam", "sam2"), default="sam", help="SAM ViT-B or SAM 2.1 Hiera-Tiny")
    ap.add_argument("--boxes", choices=("gdino", "learned"), default="gdino",
                    help="box prompts from Grounding DINO or from torm's learned segmenter (no Grounding DINO)")
    ap.add_argument("--no-arena", action="store_true",
                    help="onnxruntime without its CPU memory arena (grounded_sam memory_arena: false, torm's default "
                         "since 2026-12-07; without this flag the run measures onnxruntime's own default, the arena)")
    ap.add_argument("--name", default=None, help="result file stem (default gsam_cpu / sam2_cpu, _tiny with --tiny)")
    ap.add_argument("--summary", action="store_true",
                    help="write gsam_memory.{json,md} from the committed results of every configuration (runs nothing)")
    args = ap.parse_args(argv)
    if args.summary:
        return summary()
    threads = setup(args.threads or THREADS)
    from torm.segmentation.export import (
        export_grounding_dino,
        export_sam,
        export_sam2,
        load_models,
        load_sam2,
        write_vocab,
    )
    from torm.segmentation.tokenizer import WordPieceTokenizer, grounding_text_inputs

    ctx = context(vars(args))
    out: dict = {"context": ctx, "tiny": args.tiny, "onnxruntime_threads": threads, "sam_kind": args.sam_kind,
                 "boxes": args.boxes}
    gdino = args.boxes == "gdino"
    prompt = "clear glass. transparent object."
    hw = (128, 224) if args.tiny else (800, 1333)  # the official resize of a 16:9 image
    n_tokens = 0
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        t0 = time.perf_counter()
        g, s = load_models(random_weights=True, tiny=args.tiny, with_gdino=gdino, with_sam=args.sam_kind == "sam")
        if args.sam_kind == "sam2":
            s = load_sam2(random_weights=True, tiny=args.tiny)
        out["build_s"] = round(time.perf_counter() - t0, 1)
        out["parameters"] = {"sam": sum(p.numel() for p in s.parameters())}
        files, cfg = [], {}
        if gdino:
            out["parameters"]["grounding_dino"] = sum(p.numel() for p in g.parameters())
            vocab = write_vocab(d / "vocab.txt")
            n_tokens = grounding_text_inputs(WordPieceTokenizer.from_file(vocab), prompt).length
            gd = export_grounding_dino(g, d / "gdino.onnx", hw, n_tokens)
            files.append(gd)
            cfg = {"gdino_model": str(gd.path), "bert_vocab": str(vocab), "prompt": prompt, "box_threshold": 0.0,
                   "text_threshold": 0.0}
        else:
            cfg = {"box_source": "learned", "learned": {"fg_threshold": 0.05}}  # boxes on a render of glass
        export = export_sam2 if args.sam_kind == "sam2" else export_sam
        enc, dec = export(s, d / "sam_encoder.onnx", d / "sam_decoder.onnx")
        files += [enc, dec]
        del g, s
        out["exports"] = {m.path.name: {"export_s": m.card["export_s"], "megabytes": round(m.card["bytes"] / 1e6, 1)}
                          for m in files}
        cfg = {"sam_encoder": str(enc.path), "sam_decoder": str(dec.path), "max_detections": 5, "threads": threads,
               "memory_arena": not args.no_arena, **cfg}
        # a fresh process: its peak resident memory is the segmenter's alone (not the export's)
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            timed = pool.submit(time_views, cfg, args.views).result()
        per = timed["per"]
        out["memory"] = timed["memory"]
        out["model_files_gb"] = round(sum(m.card["bytes"] for m in files) / 1e9, 2)
        out["boxes_per_view"] = timed["boxes_per_view"]
        out["other_processes_cores"] = timed["other_processes_cores"]
        out["memory_arena"] = not args.no_arena
    med = {k: round(statistics.median(v), 3) for k, v in per.items()}
    out["seconds_per_view_median"] = med
    out["capture_50_views_min"] = round(50 * med["view"] / 60, 1)
    out["load_avg_end"] = list(os.getloadavg())
    stem = "gsam_cpu" if args.sam_kind == "sam" and gdino else f"{args.sam_kind}_{args.boxes}_cpu"
    stem += "_no_arena" if args.no_arena else ""
    name = args.name or (f"{stem}_tiny" if args.tiny else stem)
    write_json(RESULTS / f"{name}.json", out)
    rows = [[k, f"{v:.2f}"] for k, v in med.items()]
    sam_name = "SAM 2.1 Hiera-Tiny" if args.sam_kind == "sam2" else "SAM ViT-B"
    boxes = (f"Grounding DINO (Swin-T + BERT-base, {out['parameters']['grounding_dino'] / 1e6:.0f} M parameters) at "
             f"{hw[0]}x{hw[1]}, {n_tokens} tokens" if gdino else "torm's learned segmenter (its instances' boxes)")
    contended = out["other_processes_cores"] > 0.25
    note = ": **contended**, which slows onnxruntime disproportionately"
    md = [f"# {'Grounding DINO + ' if gdino else 'Learned boxes + '}{sam_name} on the CPU "
          f"({'tiny test configs' if args.tiny else 'published sizes'}, random weights)", "",
          context_md(ctx), "",
          f"Models built with `transformers` from their default configs ({sam_name}, "
          f"{out['parameters']['sam'] / 1e6:.0f} M parameters) with random weights: the graph, shapes and cost of "
          f"the trained models. Exported with `torm export-models`' code, run by torm's `grounded_sam` segmenter with "
          f"onnxruntime on {threads} intra-op thread(s), 1 inter-op thread, on a 1280x720 render; box prompts from "
          f"{boxes}; up to 5 boxes per view ({out['boxes_per_view']} in the last view); median of {args.views} "
          "views.", "",
          md_table(["export", "seconds", "MB"], [[k, str(v["export_s"]), str(v["megabytes"])]
                                                 for k, v in out["exports"].items()]), "",
          md_table(["stage", "seconds per view (median)"], rows), "",
          md_table(["memory (GB, 1e9 bytes)", "value"], [
              ["ONNX files on disk", f"{out['model_files_gb']:.2f}"],
              ["process before loading (python, numpy, onnxruntime)", f"{out['memory']['rss_before_load_gb']:.2f}"],
              ["after loading the sessions", f"{out['memory']['rss_after_load_gb']:.2f}"],
              ["**peak while segmenting**", f"**{out['memory']['peak_rss_gb']:.2f}**"]]), "",
          f"onnxruntime's CPU memory arena: {'on (default)' if out['memory_arena'] else 'off (memory_arena: false)'}; "
          "the views ran in a fresh process, so the peak is the segmenter's, not the export's.", "",
          f"A 50-view capture: about **{out['capture_50_views_min']} minutes** on this machine "
          f"(other processes' CPU while the views ran: {out['other_processes_cores']} cores"
          f"{note if contended else ''}).",
          ""]
    (RESULTS / f"{name}.md").write_text("\n".join(md))
    print(json.dumps({"median_s": med, "capture_50_views_min": out["capture_50_views_min"]}))  # noqa: T201
    return out


#: result stems of the configurations the summary reads (box source, SAM kind; each with and without the arena)
CONFIGS = (("gsam_cpu", "gdino", "sam"), ("sam2_gdino_cpu", "gdino", "sam2"), ("sam_learned_cpu", "learned", "sam"),
           ("sam2_learned_cpu", "learned", "sam2"))


def estimate_gb(doc: dict, boxes: str, sam_kind: str) -> float:
    """:func:`torm.resources.grounded_sam_bytes` for a result's configuration (GB): what the segmenter would have
    refused against before loading."""
    from torm.resources import GDINO_REFERENCE_PX, grounded_sam_bytes

    return grounded_sam_bytes(int(doc["model_files_gb"] * 1e9), GDINO_REFERENCE_PX if boxes == "gdino" else 0,
                              sam_kind, 1024, bool(doc["memory_arena"])) / 1e9


def summary() -> dict:
    """One table of every configuration's measured memory and time beside the segmenter's estimate."""
    rows, out = [], {"rows": []}
    for stem, boxes, kind in CONFIGS:
        for suffix in ("", "_no_arena"):
            path = RESULTS / f"{stem}{suffix}.json"
            if not path.is_file() or "memory" not in (doc := json.loads(path.read_text())):
                continue
            est = estimate_gb(doc, boxes, kind)
            m = doc["memory"]
            row = {"result": path.name, "boxes": boxes, "sam_kind": kind, "memory_arena": doc["memory_arena"],
                   "date": doc["context"].get("date_utc"), "model_files_gb": doc["model_files_gb"],
                   "after_load_gb": m["rss_after_load_gb"], "peak_gb": m["peak_rss_gb"], "estimate_gb": round(est, 2),
                   "seconds_per_view": doc["seconds_per_view_median"]["view"],
                   "other_processes_cores": doc["other_processes_cores"]}
            out["rows"].append(row)
            rows.append([f"`{path.stem}`", "Grounding DINO" if boxes == "gdino" else "learned",
                         "SAM ViT-B" if kind == "sam" else "SAM 2.1 Hiera-Tiny", "on" if row["memory_arena"] else
                         "**off**", f"{row['model_files_gb']:.2f}", f"{row['after_load_gb']:.2f}",
                         f"**{row['peak_gb']:.2f}**", f"{row['estimate_gb']:.2f}", f"{row['seconds_per_view']:.2f}"])
    write_json(RESULTS / "gsam_memory.json", out)
    md = ["# Grounding DINO / SAM on the CPU: peak memory and time per view, every configuration", "",
          "Each row is one `benchmarks/gsam_cpu.py` run (published architectures, random weights, onnxruntime on 2 "
          "threads, a 1280x720 render, median of 3 views in a fresh process; its own file names the date, git and "
          "machine). GB = 1e9 bytes. Estimate: what `grounded_sam` computes before loading anything "
          "(`torm.resources.grounded_sam_bytes`) and refuses against the machine's free memory; it must stay above "
          "every measured peak (`tests/test_resources.py`). Memory arena: onnxruntime's CPU arena, torm's "
          "`grounded_sam.memory_arena` (off by default since these runs).", "",
          md_table(["result", "boxes", "SAM", "arena", "ONNX files", "after loading", "peak", "estimate",
                    "s / view"], rows), ""]
    (RESULTS / "gsam_memory.md").write_text("\n".join(md))
    return out


if __name__ == "__main__":
    main()
