"""Speed against silhouette quality of the realistic perception settings (PBR capture + learned segmenter).

A realistic trial spends most of its time rendering the 50 PBR views (``capture.pbr``) and segmenting them
(``segmentation.options``). This benchmark puts each candidate setting's cost beside what it does to the
silhouettes, on one thread per process, so that a faster default is chosen on evidence:

- ``--renders``: PBR settings as ``SPPxRENDER_SCALE[:DENOISER]`` (``16x1.0`` = the default 16 spp traced at the
  camera's 640x360 with the default denoiser; ``16x0.5`` = traced at 320x180 and resized to 640x360; ``4x1.0:oidn``
  = 4 spp denoised by OIDN, ``capture.pbr.denoise``). For every scenario of ``--suites`` (scenario k
  gets layout seed k, so table textures and lights vary) a capture of ``--views`` rig views is rendered once per
  setting (one thread per worker process, ``--workers`` processes) and cached under ``--cache`` for the scores.
  The render timing is measured apart: each setting renders ``--time-views`` views of the first scenario in a
  fresh process of its own, one setting at a time, nothing cached.
- ``--rows``: learned segmenters as ``MODEL@INPUT_WIDTH`` with an optional ``:notta`` (mirror test-time
  augmentation off) or ``:tta`` (on); ``MODEL`` is a shipped name (``learned_seg`` = v3, ``learned_seg_v4``) or an
  ``.onnx`` path; ``@auto`` reads each capture at the width it was traced at (``render_scale x 640``: render only
  what the segmenter reads). Each row segments every capture of every render setting on one onnxruntime thread.

Scores per view, averaged: union IoU of the predicted silhouettes against the glass objects' masks (opaque
objects count as background), its precision and recall, and the IoU against every object's mask. The table
projects a 50-view trial: ``50 x`` render seconds per view (the PBR capture) and ``50 x`` segmentation seconds per
view (the median view after the first; the first view, which loads the scene and compiles Mitsuba's kernels, is
added once). Writes ``benchmarks/results/perception_speed.{json,md}``; ``contended`` in the context says whether other
work shared the machine (timings are then pessimistic).

Run: ``MUJOCO_GL=egl python benchmarks/perception_speed.py`` (the defaults are the committed run's settings;
renders: minutes, cached; segmentation: about 25 min on one thread of this 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks._common import RESULTS, ROOT, context, context_md, md_table, setup, write_json  # noqa: E402

log = logging.getLogger("perception_speed")

#: views of a realistic trial's capture (``capture.n_views``), for the projected per-trial seconds
TRIAL_VIEWS = 50


def parse_render(text: str) -> tuple[int, float, str]:
    """``"16x0.5"`` -> (16 spp, render scale 0.5, the default denoiser); ``"4x1.0:oidn"`` -> (4, 1.0, ``oidn``)."""
    from torm.capture.render_settings import DENOISERS, PbrSettings

    head, _, dn = text.partition(":")
    spp, _, rs = head.partition("x")
    dn = dn or PbrSettings().denoise
    if dn not in DENOISERS:
        raise SystemExit(f"--renders entry {text!r}: denoiser {dn!r} is not one of {DENOISERS}")
    try:
        return int(spp), float(rs or 1.0), dn
    except ValueError:
        raise SystemExit(f"--renders entry {text!r}: write SPPxRENDER_SCALE[:DENOISER], e.g. 16x1.0, 16x0.5 or "
                         "4x1.0:oidn") from None


def render_label(spp: int, render_scale: float, denoise: str) -> str:
    """The row label of a render setting: ``16x1.0`` with the default denoiser, else ``4x1.0:oidn``."""
    from torm.capture.render_settings import PbrSettings

    return f"{spp}x{render_scale}" + ("" if denoise == PbrSettings().denoise else f":{denoise}")


def parse_row(text: str) -> tuple[str, int, bool | None]:
    """``"learned_seg_v4@320:notta"`` -> (model, input width 320, flip_tta False); no suffix = the card's choice;
    ``@auto`` -> input width 0 (= the width the view was traced at, ``render_scale x 640``)."""
    head, _, tta = text.partition(":")
    model, _, width = head.partition("@")
    if tta not in ("", "tta", "notta"):
        raise SystemExit(f"--rows entry {text!r}: the suffix is :tta or :notta")
    try:
        w = 0 if width == "auto" else int(width or 640)
    except ValueError:
        raise SystemExit(f"--rows entry {text!r}: write MODEL@INPUT_WIDTH[:tta|:notta] (INPUT_WIDTH a number or "
                         "auto)") from None
    return model, w, {"": None, "tta": True, "notta": False}[tta]


def _capture_job(args: tuple[str, int, int, int, float, str, str]) -> dict[str, Any]:
    """Render one scenario's capture into the cache (one process, one thread); returns folder and seconds/view.

    ``args``: (scenario, seed, views, spp, render_scale, folder, denoiser)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    scenario, seed, views, spp, render_scale, folder, denoise = args
    from torm.capture.render_settings import PbrSettings
    timing = Path(folder) / "render_timing.json"
    if timing.exists():
        return json.loads(timing.read_text())
    from sim.cameras.renderers import make_renderer
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world
    from torm.capture.io import save_capture

    world = build_world(scenario, seed, robot=None)
    r = make_renderer("pbr", world, PbrSettings(spp=spp, render_scale=render_scale, denoise=denoise, threads=1,
                                                cache=False))
    per_view: list[float] = []
    render = r.render

    def timed(*a: Any, **k: Any) -> Any:  # the rig renders one view per call
        t = time.perf_counter()
        out = render(*a, **k)
        per_view.append(time.perf_counter() - t)
        return out

    r.render = timed
    with SimCameraRig.from_world(world, CameraRigConfig(n_views=views, scale=0.5), rgb_renderer=r) as rig:
        cap = rig.capture()
    cap.metadata["transparent_ids"] = [o.instance_id for o in world.objects if o.transparent]
    save_capture(cap, folder)
    out = {"folder": folder, "render_s_per_view": float(np.median(per_view[1:] or per_view)),
           "first_view_s": per_view[0], "described": r.describe()}
    timing.write_text(json.dumps(out))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suites", default="rw,lab,syn_hard")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--renders", default="16x1.0,16x0.7,16x0.5,4x1.0")
    ap.add_argument("--rows", default="learned_seg@640,learned_seg@640:notta,learned_seg@auto:notta,"
                                      "learned_seg_v4@640,learned_seg_v4@auto")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "perception_speed_captures"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--time-views", type=int, default=8, help="views rendered per setting for the timing")
    ap.add_argument("--limit", type=int, default=0, help="only the first N scenarios (0 = all)")
    ap.add_argument("--results", default=str(RESULTS), help="folder of the result files")
    ap.add_argument("--out", default="perception_speed", help="result file stem")
    ap.add_argument("--append", action="store_true",
                    help="add these render settings to the existing result file (replacing the same settings)")
    args = ap.parse_args(argv)
    setup(threads=1)
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from benchmarks.segmentation_reference import scenarios, segment_and_score
    from sim.render.textures import table_texture
    from torm.capture.io import load_capture
    from torm.segmentation import make_segmenter
    from torm.segmentation.learned import LearnedConfig, model_fingerprint

    renders = [parse_render(r) for r in args.renders.split(",") if r]
    rows = [parse_row(r) for r in args.rows.split(",") if r]
    scs = scenarios([s for s in args.suites.split(",") if s])[:args.limit or None]
    ctx = context(vars(args))
    cache = Path(args.cache)
    jobs = [(name, seed, args.views, spp, rs,
             str(cache / (f"{name}_s{seed}_v{args.views}_spp{spp}_rs{rs}" + ("" if dn == "bilateral" else f"_{dn}"))),
             dn)
            for spp, rs, dn in renders for _, name, seed in scs]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max(1, args.workers), mp_context=mp.get_context("spawn")) as ex:
        caps = list(ex.map(_capture_job, jobs))  # cached captures for the scores (their timings are not used)
    log.info("captures ready in %.0f s", time.perf_counter() - t0)
    # timing: each render setting once more in a fresh process of its own (a trial's first view pays the imports
    # and kernel compilation too), one at a time, on the first scenario, nothing cached
    timing: dict[tuple[int, float, str], dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for spp, rs, dn in renders:
            _, name, seed = scs[0]
            with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
                timing[(spp, rs, dn)] = ex.submit(_capture_job, (name, seed, args.time_views, spp, rs,
                                                                 str(Path(tmp) / f"{spp}x{rs}_{dn}"), dn)).result()
            log.info("%s: %.3f s per view after a first view of %.2f s", render_label(spp, rs, dn),
                     timing[(spp, rs, dn)]["render_s_per_view"], timing[(spp, rs, dn)]["first_view_s"])
    segs: dict[tuple[int, str, bool | None], tuple[str, Any]] = {}

    def segmenter(model: str, width: int, tta: bool | None) -> tuple[str, Any]:
        if (width, model, tta) not in segs:
            path = LearnedConfig(model=model).model_path
            opts: dict[str, Any] = {"model": str(path), "threads": 1, "input_width": width}
            if tta is not None:
                opts["flip_tta"] = tta
            seg = make_segmenter("learned", opts)
            label = f"{model_fingerprint(path)} @{width}" + ("" if seg.postprocess["flip_tta"] is False else " +tta")
            segs[(width, model, tta)] = (label, seg)
        return segs[(width, model, tta)]

    results: list[dict[str, Any]] = []
    for job in jobs:
        name, seed, _, spp, rs, folder, dn = job
        suite = next(s for s, n, k in scs if n == name and k == seed)
        cap = load_capture(folder)
        traced_w = int(round(cap.views[0].rgb.shape[1] * rs))
        row_segs = [segmenter(model, width or traced_w, tta) for model, width, tta in rows]
        for label, seg in row_segs:
            m = segment_and_score(seg, cap)
            results.append({"render": render_label(spp, rs, dn), "spp": spp, "render_scale": rs, "denoise": dn,
                            "segmenter": label, "suite": suite, "scenario": name, "seed": seed,
                            "table": table_texture(seed, (1.7, 1.8)).pattern,
                            "render_s_per_view": timing[(spp, rs, dn)]["render_s_per_view"],
                            "first_view_s": timing[(spp, rs, dn)]["first_view_s"],
                            "seg_s_per_view": m.pop("seconds_per_view"), **m})
        log.info("%s %s: %s", name, render_label(spp, rs, dn), ", ".join(f"{r['segmenter']}: {r['glass_iou']:.2f}"
                                                          for r in results[-len(row_segs):]))
    doc = {"context": ctx, "scenarios": len(scs), "trial_views": TRIAL_VIEWS, "timing_scenario": scs[0][1],
           "results": results,
           "described": sorted({c["described"] for c in caps})}
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    if args.append and (out / f"{args.out}.json").is_file():  # keep the earlier run's other render settings
        old = json.loads((out / f"{args.out}.json").read_text())
        if (old["scenarios"], old["timing_scenario"]) != (doc["scenarios"], doc["timing_scenario"]):
            raise SystemExit(f"--append: {args.out}.json scored other scenarios; use the same --suites / --limit")
        mine = {r["render"] for r in results}
        doc["results"] = [r for r in old["results"] if r["render"] not in mine] + results
        doc["described"] = sorted({*old["described"], *doc["described"]})
        doc["earlier_runs"] = [*old.get("earlier_runs", []), old["context"]]
    write_json(out / f"{args.out}.json", doc)
    (out / f"{args.out}.md").write_text(report(doc, args))
    return 0


def _mean(sel: list[dict[str, Any]], key: str) -> float:
    return float(np.mean([r[key] for r in sel])) if sel else float("nan")


def report(doc: dict[str, Any], args: argparse.Namespace) -> str:
    """The Markdown page of a result document."""
    res = doc["results"]
    combos = list(dict.fromkeys((r["render"], r["segmenter"]) for r in res))
    suites = sorted({r["suite"] for r in res})
    body, per_suite = [], []
    for rnd, seg in combos:
        sel = [r for r in res if r["render"] == rnd and r["segmenter"] == seg]
        rs, ss = _mean(sel, "render_s_per_view"), _mean(sel, "seg_s_per_view")
        first = _mean(sel, "first_view_s")
        body.append([rnd, seg, rs, ss, first + (TRIAL_VIEWS - 1) * rs, TRIAL_VIEWS * ss, *(_mean(sel, k) for k in (
            "glass_iou", "glass_precision", "glass_recall", "all_iou"))])
        per_suite.append([rnd, seg, *(_mean([r for r in sel if r["suite"] == s], "glass_iou") for s in suites)])
    head = ["render (spp x scale)", "segmenter (model @ input width)", "render s / view", "segment s / view",
            f"capture s / {TRIAL_VIEWS} views", f"segment s / {TRIAL_VIEWS} views", "glass IoU", "precision",
            "recall", "all-objects IoU"]
    L = ["# Perception speed against silhouette quality (PBR capture + learned segmenter, one thread)", "",
         context_md(doc["context"]), "",
         *(f"Rows of an earlier run of this script kept beside them (`--append`): {c['date_utc']}, git "
           f"{c['versions'].get('git', '?')}, contended: {c['contended']}, arguments {c['args']}."
           for c in doc.get("earlier_runs", [])), "",
         f"{doc['scenarios']} scenarios ({', '.join(suites)}; scenario k has layout seed k), {args.views} rig views "
         "each at 640x360. Render settings: " + "; ".join(f"`{d}`" for d in doc["described"]) + ". Render seconds "
         f"per view: the median after the first view of {args.time_views} views of `{doc['timing_scenario']}` "
         "rendered in a fresh process per setting, one thread, one setting at a time; the capture column adds "
         "the first view (scene load and kernel compilation) to "
         f"{TRIAL_VIEWS - 1} more; segmentation seconds per view on one onnxruntime thread, maps and instance "
         "grouping included. Scores per view, averaged: union IoU "
         "against the glass objects' masks (opaque objects are background), precision and recall of that union, "
         "IoU against every object's mask.", "",
         md_table(head, body), "", "## Glass IoU per suite", "", md_table(["render", "segmenter", *suites], per_suite),
         ""]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    sys.exit(main())
