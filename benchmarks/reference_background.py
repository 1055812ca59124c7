"""How well the reference mode's background check tells a valid reference pass from a stale one.

``torm segment --reference`` refuses a reference pass whose static background no longer matches the scene
(:func:`torm.segmentation.reference.check_background`: the median over views of the median exposure-normalised
|scene - reference| outside the objects, against ``max_grey``). This script measures both of its errors on the
cached captures of ``benchmarks/segmentation_reference.py`` (the same fixed camera rig for every layout seed):

- **valid** pairs: each scenario's scene with its own reference pass (layout seed ``--valid-offset`` + k; independent
  render noise, nothing else changed): a refusal here is a false refusal;
- **stale** pairs: the same scene with the reference pass of layout seed ``--stale-offset`` + k (the same scenario
  and cameras, another table texture and colour, other lights): an acceptance here is a false acceptance, the
  situation "the table or the light changed since the reference was recorded".

Objects are taken out by the masks of ``--masks`` (where they cover more than half a view, the check reads the whole
view): ``none`` (the whole view), ``truth`` (the simulator's masks of every object: the check alone), ``learned``
(the shipped RGB segmenter, which does not read the reference) or ``difference`` (the plain difference, which does,
and on a stale reference marks much of the table). Each ``--blur`` setting of the check's difference is a row.
Writes ``<results>/<out>.{json,md}`` (default ``benchmarks/results``).

Run (captures cached by segmentation_reference.py with ``--seed-offset`` 0, 100 and 200):
``python benchmarks/reference_background.py --valid-offset 100 --stale-offset 0 --out reference_background_dev``
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks._common import RESULTS, ROOT, context, context_md, md_table, setup, write_json  # noqa: E402

log = logging.getLogger("reference_background")


def folder(cache: Path, name: str, seed: int, renderer: str) -> Path:
    """The cached capture of ``segmentation_reference.py`` (6 views at half of 1280x720, 16 spp)."""
    return cache / f"{name}_s{seed}_v6_x0.5_{renderer}_spp16"


def object_masks(kind: str, capture: Any) -> np.ndarray:
    """(V, H, W) masks of the objects by ``kind`` (truth, learned or difference)."""
    if kind == "truth":
        return capture.masks()
    if kind == "none":
        return np.zeros((len(capture), *capture.image_size), np.int32)
    from torm.segmentation import make_segmenter

    seg = make_segmenter(kind, {"threads": 2} if kind == "learned" else {})
    return seg.segment(capture).masks_vxhxw


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suites", default="rw,lab,syn_hard")
    ap.add_argument("--renderer", default="pbr", choices=("pbr", "pbr_scalar", "mujoco"))
    ap.add_argument("--valid-offset", type=int, default=0)
    ap.add_argument("--stale-offset", type=int, default=200)
    ap.add_argument("--masks", default="truth,learned,difference")
    ap.add_argument("--blur", default="0,auto", help="the check's smoothing settings (px or auto), one row each")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "seg_reference_captures"))
    ap.add_argument("--limit", type=int, default=0, help="only the first N scenarios (0: all)")
    ap.add_argument("--results", default=str(RESULTS), help="folder for the result files")
    ap.add_argument("--out", default="reference_background")
    args = ap.parse_args(argv)
    setup()
    from dataclasses import replace

    from benchmarks.segmentation_reference import scenarios
    from torm.capture.io import load_capture
    from torm.segmentation.reference import BACKGROUND_MAX_GREY, DifferenceConfig, check_background

    max_grey = BACKGROUND_MAX_GREY
    blurs: list[float | str] = [b if b == "auto" else float(b) for b in args.blur.split(",") if b]
    for b in blurs:
        DifferenceConfig(blur_sigma_px=b)  # refuses a bad setting before any work
    cache = Path(args.cache)
    rows: list[dict[str, Any]] = []
    todo = scenarios([s for s in args.suites.split(",") if s])
    for _, name, k in todo[:args.limit] if args.limit > 0 else todo:
        valid_dir = folder(cache, name, args.valid_offset + k, args.renderer)
        stale_dir = folder(cache, name, args.stale_offset + k, args.renderer)
        for d in (valid_dir, stale_dir):
            if not (d / "transforms.json").exists():
                raise SystemExit(f"{d} is not cached: render it with benchmarks/segmentation_reference.py "
                                 f"--renderer {args.renderer} --seed-offset <its offset> --views 6")
        valid, other = load_capture(valid_dir), load_capture(stale_dir)
        stale = replace(valid, views=tuple(v.with_(reference_rgb=o.reference_rgb)
                                           for v, o in zip(valid.views, other.views, strict=True)))
        for pair, cap in (("valid", valid), ("stale", stale)):
            for kind in [m for m in args.masks.split(",") if m]:
                masks = object_masks(kind, cap)
                for b in blurs:
                    grey = check_background(cap, masks, max_grey=float("inf"), blur_sigma_px=b)
                    rows.append({"scenario": name, "pair": pair, "masks": kind, "blur": b, "grey": grey,
                                 "mask_fraction": float(np.mean(masks > 0))})
        log.info("%s: %s", name, ", ".join(f"{r['pair']}/{r['masks']}/{r['blur']}: {r['grey']:.1f}"
                                           for r in rows[-2 * len(blurs) * len(args.masks.split(",")):]))
    doc = {"context": context(vars(args)), "max_grey": max_grey, "rows": rows}
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{args.out}.json", doc)
    body = []
    for kind in [m for m in args.masks.split(",") if m]:
        for b in blurs:
            v = np.array([r["grey"] for r in rows if r["pair"] == "valid" and r["masks"] == kind and r["blur"] == b])
            s = np.array([r["grey"] for r in rows if r["pair"] == "stale" and r["masks"] == kind and r["blur"] == b])
            body.append([kind, f"{b:g} px" if b != "auto" else "auto", f"{np.median(v):.2f}", f"{v.max():.2f}",
                         f"{np.min(s):.2f}", f"{np.median(s):.2f}", f"{int(np.sum(v > max_grey))}/{len(v)}",
                         f"{int(np.sum(s <= max_grey))}/{len(s)}"])
    L = [f"# Reference background check: valid against stale reference passes ({args.renderer})", "",
         context_md(doc["context"]), "",
         f"Scenarios of {args.suites}; valid: layout seed {args.valid_offset} + k with its own reference pass; stale: "
         f"the same scene with the reference pass of layout seed {args.stale_offset} + k (same cameras, another "
         f"table and lights). Value: median over views of the median exposure-normalised |scene - reference| "
         f"outside the objects (dilated 15 px; the whole view where they cover more than half of it), grey levels; "
         f"refused above max_grey = {max_grey:g} (the error counts are at that limit).", "",
         md_table(["object masks", "check blur", "valid median", "valid max", "stale min", "stale median",
                   "false refusals", "false acceptances"], body), ""]
    (out / f"{args.out}.md").write_text("\n".join(L) + "\n")
    print("\n".join(" | ".join(b) for b in body))
    return 0


if __name__ == "__main__":
    sys.exit(main())
