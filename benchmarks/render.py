"""Physically based renderer benchmark: time per view vs spp and resolution, noise, a 50-view capture, cache hits.

On one scene (``rw3`` seed 0 by default: solid glass cylinder + hexagonal prism), with the rig's 640x360 cameras
and 2 render threads:

1. **Reference**: ``--ref-spp`` (256) spp renders of ``--noise-views`` views, plus the same views with the
   objects removed (the empty table, for the proxy segmenter); linear radiance cached under
   ``$TORM_CACHE_DIR/bench_render``: a re-run reuses them.
2. **spp sweep** (``--spps``: 4, 16, 64, the ldsampler's square powers of two; counts in between with another
   sampler, ``36:multijitter``): wall and CPU time per view
   (render + tone map + denoise, median over the views, after one
   warm-up render that compiles the kernels) and noise against the reference for every denoiser: RMSE in 8-bit
   grey levels (whole image and inside the glass silhouettes), PSNR, Canny edge F1 (1 px tolerance) and the
   **segmenter proxy**: IoU between a pixel-reading segmenter's masks on the test render and on the reference.
   The default proxy is background subtraction (5x5 Gaussian on both, |render - empty-table reference| > 12 grey
   levels on any channel, 3x3 opening, components >= 30 px): it reads pixels, glass shows up through refraction,
   and noise flips its decisions like it would flip a learned segmenter's. ``--segmenter MODULE:FUNCTION``
   replaces it by any ``f(rgb_hxwx3 uint8) -> mask (H, W)`` (e.g. the learned segmenter when it exists); the IoU
   is then over its foreground (mask > 0). Every image of a view is tone-mapped with its reference's
   auto-exposure gain. **Chosen setting**: the cheapest (spp, denoiser) in CPU seconds whose proxy IoU agreement
   is >= ``--agreement`` (0.98) on every noise view.
3. **Resolution sweep** at the chosen setting: 320x180, 640x360, 1280x720.
4. **50-view capture** through ``SimCameraRig`` + ``MitsubaRenderer`` (``capture.renderer=pbr``) at the chosen
   setting (the default ``PbrSettings`` when the chosen one costs > 6 CPU s per view) into an empty cache
   folder, then the same capture again (every view a cache hit).
5. ``render_side_by_side.png``: the same view rendered by MuJoCo and by the PBR renderer (chosen setting).

Writes ``benchmarks/results/render.json`` and ``render.md``. Run under the shared lock (about 8 minutes on a
quiet 2-core machine; the reference renders are cached, so a re-run is faster):
``flock /work/heavy.lock python benchmarks/render.py`` (``--quick``: a tiny smoke run for tests).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402

log = logging.getLogger("bench.render")

DENOISERS = ("none", "nlmeans", "bilateral")
#: settings that shape the linear radiance (the reference cache key)
LINEAR_FIELDS = ("max_depth", "rr_depth", "integrator", "sampler", "render_scale", "variant")
BGSUB_THRESHOLD = 12  # grey levels
MIN_COMPONENT_PX = 30
#: the capture uses the chosen setting unless it costs more CPU s per view than this (then the default)
CAPTURE_CPU_CAP_S = 6.0
RESOLUTIONS = ((320, 180), (640, 360), (1280, 720))


def _spp_entry(text: str) -> tuple[int, str]:
    """``"36:multijitter"`` -> ``(36, "multijitter")``; a bare count uses the ldsampler."""
    from torm.capture.render_settings import SAMPLERS

    spp, _, sampler = text.partition(":")
    sampler = sampler or "ldsampler"
    if sampler not in SAMPLERS:
        raise argparse.ArgumentTypeError(f"--spps entry {text!r}: unknown sampler {sampler!r}; valid: {SAMPLERS}")
    try:
        return int(spp), sampler
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--spps entry {text!r}: expected SPP or SPP:SAMPLER, e.g. 16 or 36:multijitter") from None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny smoke run: 160x90, 2 noise views, 4 capture views")
    p.add_argument("--out", type=Path, default=bc.RESULTS, help="result folder")
    p.add_argument("--cache", type=Path, default=None, help="render cache for the reference (default TORM_CACHE_DIR)")
    p.add_argument("--scenario", default="rw3")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spps", nargs="+", type=_spp_entry,
                   default=[(4, "ldsampler"), (16, "ldsampler"), (64, "ldsampler")],
                   help="SPP or SPP:SAMPLER entries; the ldsampler takes 4, 16, 64, 256...; other counts need "
                        "another sampler, e.g. 36:multijitter")
    p.add_argument("--ref-spp", type=int, default=256)
    p.add_argument("--noise-views", type=int, default=3)
    p.add_argument("--capture-views", type=int, default=50)
    p.add_argument("--scale", type=float, default=0.5, help="image scale of 1280x720 (0.5 -> 640x360)")
    p.add_argument("--agreement", type=float, default=0.98, help="proxy IoU agreement the chosen setting needs")
    p.add_argument("--segmenter", default=None, help="MODULE:FUNCTION f(rgb) -> mask replacing the proxy")
    p.add_argument("--threads", type=int, default=bc.THREADS)
    a = p.parse_args(argv)
    if a.quick:
        a.spps, a.ref_spp, a.noise_views, a.capture_views, a.scale = [(4, "ldsampler")], 16, 2, 4, 0.125
    return a


# ---------------------------------------------------------------------------------------------- metrics
def bgsub_segmenter(background: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Background subtraction against the empty-table reference: 5x5 Gaussian (sigma 1 px) on both, any channel
    off by > 12 levels, 3x3 opening, components under 30 px dropped (a segmenter reads neighbourhoods too)."""
    kernel = np.ones((3, 3), np.uint8)
    bg = cv2.GaussianBlur(background.astype(np.float32), (5, 5), 1.0)

    def seg(rgb: np.ndarray) -> np.ndarray:
        d = np.abs(cv2.GaussianBlur(rgb.astype(np.float32), (5, 5), 1.0) - bg).max(axis=2) > BGSUB_THRESHOLD
        m = cv2.morphologyEx(d.astype(np.uint8), cv2.MORPH_OPEN, kernel)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        keep = np.zeros(n, bool)
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= MIN_COMPONENT_PX
        return keep[lab]

    return seg


def load_hook(spec: str) -> Callable[[np.ndarray], np.ndarray]:
    mod, _, fn = spec.partition(":")
    if not fn:
        raise SystemExit(f"--segmenter {spec!r} must be MODULE:FUNCTION")
    f = getattr(importlib.import_module(mod), fn)
    return lambda rgb: np.asarray(f(rgb)) > 0


def edge_f1(a: np.ndarray, b: np.ndarray) -> float:
    """F1 of Canny edges (50/150) of ``a`` against ``b``'s, each counted as matched within 1 px."""
    ea = cv2.Canny(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), 50, 150) > 0
    eb = cv2.Canny(cv2.cvtColor(b, cv2.COLOR_RGB2GRAY), 50, 150) > 0
    k = np.ones((3, 3), np.uint8)
    da, db = cv2.dilate(ea.astype(np.uint8), k) > 0, cv2.dilate(eb.astype(np.uint8), k) > 0
    prec = (ea & db).sum() / max(1, ea.sum())
    rec = (eb & da).sum() / max(1, eb.sum())
    return float(2 * prec * rec / max(prec + rec, 1e-9))


def noise_metrics(img: np.ndarray, ref: np.ndarray, glass: np.ndarray, seg: Callable, seg_ref: np.ndarray
                  ) -> dict[str, float]:
    d = img.astype(np.float64) - ref.astype(np.float64)
    rmse = float(np.sqrt(np.mean(d**2)))
    m = seg(img)
    inter, union = (m & seg_ref).sum(), (m | seg_ref).sum()
    return {"rmse": rmse, "rmse_glass": float(np.sqrt(np.mean(d[glass] ** 2))) if glass.any() else None,
            "psnr_db": float(20 * np.log10(255.0 / max(rmse, 1e-9))), "edge_f1": edge_f1(img, ref),
            "proxy_iou": float(inter / union) if union else 1.0}


# ---------------------------------------------------------------------------------------------- parts
class Clock:
    """Wall and process-CPU seconds of a block (CPU time counts every thread of this process)."""

    def __enter__(self) -> Clock:
        self.w, self.c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall, self.cpu = time.perf_counter() - self.w, time.process_time() - self.c


def render_views(r: Any, cams: list, settings: Any) -> tuple[list[float], list[float]]:
    """Render every camera with ``settings`` (cache off); wall and CPU seconds of each."""
    r.settings = settings
    wall, cpu = [], []
    for cam in cams:
        with Clock() as c:
            r.render([cam], instance=False)
        wall.append(c.wall)
        cpu.append(c.cpu)
    return wall, cpu


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    bc.setup(a.threads)
    if a.cache is not None:
        os.environ["TORM_CACHE_DIR"] = str(a.cache)
    from sim.cameras.renderers import make_renderer
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.render import MitsubaRenderer, PbrSettings, RenderCache, RenderCamera, cache_key, cache_root
    from sim.render.mitsuba_env import find_libllvm
    from sim.render.mitsuba_renderer import auto_exposure_gain, denoise, render_linear, tone_map
    from sim.render.scene import load_scene
    from sim.world import build_world

    ctx = bc.context(vars(a) | {"out": str(a.out), "cache": str(a.cache) if a.cache else None})
    world = build_world(a.scenario, a.seed, robot=None)
    rig_cfg = CameraRigConfig(n_views=a.capture_views, scale=a.scale)
    W, H = rig_cfg.image_width, rig_cfg.image_height
    poses = rig_cfg.poses()
    pick = np.linspace(0, len(poses) - 1, a.noise_views + 2)[1:-1].round().astype(int)
    cams = [RenderCamera(rig_cfg.K(), poses[i], W, H, f"view_{i:03d}") for i in pick]
    base = PbrSettings(spp=a.ref_spp, denoise="none", threads=a.threads)
    r = MitsubaRenderer(world, base)
    ctx["renderer"] = {"mitsuba_variant": r.variant, "mitsuba": r.mi.__version__, "libllvm": find_libllvm(),
                       "integrator": base.integrator, "max_depth": base.max_depth}
    doc: dict[str, Any] = {"context": ctx, "scene": {"scenario": a.scenario, "seed": a.seed, "width": W, "height": H,
                                                      "noise_views": [int(i) for i in pick]}}

    # 1. reference renders and empty-table backgrounds (linear radiance, cached on disk)
    t0 = time.perf_counter()
    mi_scene, pbr = r.scene()
    empty_scene = load_scene(dataclasses.replace(pbr, scene_dict={k: v for k, v in pbr.scene_dict.items()
                                                                  if k not in pbr.shape_instances}))
    key = cache_key({"bench": "render-reference", "scene": pbr.description.digest(), "spp": a.ref_spp,
                     "cams": [[c.K, c.T_world_cam, c.width, c.height] for c in cams], "variant": r.variant,
                     "mitsuba": r.mi.__version__, "linear": {k: getattr(base, k) for k in LINEAR_FIELDS}})
    ref_file = cache_root() / "bench_render" / f"{key}.npz"
    if ref_file.exists():
        with np.load(ref_file) as z:
            lin_refs, lin_bgs = list(z["refs"]), list(z["bgs"])
        log.info("reference loaded from %s", ref_file)
    else:
        lin_refs = [render_linear(mi_scene, c, base, 7 + i) for i, c in enumerate(cams)]
        lin_bgs = [render_linear(empty_scene, c, base, 17 + i) for i, c in enumerate(cams)]
        ref_file.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(ref_file, refs=np.stack(lin_refs), bgs=np.stack(lin_bgs))
    # every image of a view is tone-mapped with its reference's auto-exposure gain (no exposure jitter)
    gains = [auto_exposure_gain(x) for x in lin_refs]
    refs = [tone_map(x, g) for x, g in zip(lin_refs, gains, strict=True)]
    bgs = [tone_map(x, g) for x, g in zip(lin_bgs, gains, strict=True)]
    mj = make_renderer("mujoco", world)
    masks = [v.instance for v in mj.render(cams, rgb=False)]
    mj.close()
    glass_ids = [o.instance_id for o in world.objects if o.transparent]
    glass = [np.isin(m, glass_ids) for m in masks]
    hook = load_hook(a.segmenter) if a.segmenter else None
    segs = [hook or bgsub_segmenter(bg) for bg in bgs]
    seg_refs = [s(ref) for s, ref in zip(segs, refs, strict=True)]
    doc["reference"] = {"spp": a.ref_spp, "seconds": time.perf_counter() - t0,
                        "proxy": a.segmenter or (f"background subtraction (5x5 Gaussian, > {BGSUB_THRESHOLD} levels, "
                                                 f"3x3 opening, components >= {MIN_COMPONENT_PX} px)"),
                        "proxy_foreground_px": [int(s.sum()) for s in seg_refs]}
    log.info("reference ready in %.1f s", doc["reference"]["seconds"])

    # 2. spp sweep (one warm-up render per spp compiles the kernels; it is not timed; nor is the denoisers' first call)
    for dn in DENOISERS:
        denoise(refs[0], dn, 5.0)
    rows = []
    for spp, sampler in a.spps:
        s = dataclasses.replace(base, spp=spp, sampler=sampler, cache=False)
        r.settings = s
        t = time.perf_counter()
        r.render(cams[:1], instance=False)
        compile_s = time.perf_counter() - t
        mi_scene, _ = r.scene()
        lins, t_render, c_render = [], [], []
        for i, cam in enumerate(cams):
            with Clock() as c:
                lins.append(render_linear(mi_scene, cam, s, 1000 + i))
            t_render.append(c.wall)
            c_render.append(c.cpu)
        for dn in DENOISERS:
            strengths = [0.0] if dn == "none" else [5.0, 10.0]
            for strength in strengths:
                imgs, t_post, c_post = [], [], []
                for lin, g in zip(lins, gains, strict=True):
                    with Clock() as c:
                        imgs.append(denoise(tone_map(lin, g), dn, strength))
                    t_post.append(c.wall)
                    c_post.append(c.cpu)
                m = [noise_metrics(img, ref, g, sg, sr) for img, ref, g, sg, sr
                     in zip(imgs, refs, glass, segs, seg_refs, strict=True)]
                row = {"spp": spp, "sampler": sampler, "denoise": dn, "strength": strength,
                       "s_per_view": float(np.median(np.add(t_render, t_post))),
                       "render_s": float(np.median(t_render)), "post_s": float(np.median(t_post)),
                       "cpu_s_per_view": float(np.median(np.add(c_render, c_post))),
                       "first_view_s": compile_s,
                       **{k: _mean([x[k] for x in m]) for k in m[0]},
                       "proxy_iou_min": float(min(x["proxy_iou"] for x in m))}
                rows.append(row)
                log.info("spp %d %s %s %.0f: %.2f s/view, rmse %.1f, proxy IoU min %.3f", spp, sampler, dn, strength,
                         row["s_per_view"], row["rmse"], row["proxy_iou_min"])
    doc["sweep"] = rows
    ok = [x for x in rows if x["proxy_iou_min"] >= a.agreement]
    chosen = min(ok, key=lambda x: x["cpu_s_per_view"]) if ok else max(rows, key=lambda x: x["proxy_iou_min"])
    doc["chosen"] = {"spp": chosen["spp"], "sampler": chosen["sampler"], "denoise": chosen["denoise"],
                     "strength": chosen["strength"],
                     "meets_agreement": bool(ok), "agreement": a.agreement, "s_per_view": chosen["s_per_view"]}
    default = PbrSettings()
    doc["default_settings"] = {"spp": default.spp, "sampler": default.sampler, "denoise": default.denoise,
                               "denoise_strength": default.denoise_strength}
    dflt = [x for x in rows if (x["spp"], x["sampler"], x["denoise"], x["strength"]) ==
            (default.spp, default.sampler, default.denoise, default.denoise_strength)]
    doc["default_row"] = dflt[0] if dflt else None
    chosen_s = dataclasses.replace(base, spp=chosen["spp"], sampler=chosen["sampler"], denoise=chosen["denoise"],
                                   denoise_strength=chosen["strength"] or default.denoise_strength, cache=False)

    # 3. resolution sweep at the chosen setting
    res_rows = []
    for w, h in ((160, 90), (320, 180)) if a.quick else RESOLUTIONS:
        cfg = CameraRigConfig(n_views=a.capture_views, width=w, height=h)
        rc = [RenderCamera(cfg.K(), cfg.poses()[i], w, h) for i in pick]
        render_views(r, rc[:1], chosen_s)
        ts, cs = render_views(r, rc, chosen_s)
        res_rows.append({"width": w, "height": h, "s_per_view": float(np.median(ts)),
                         "cpu_s_per_view": float(np.median(cs))})
        log.info("%dx%d: %.2f s/view", w, h, res_rows[-1]["s_per_view"])
    doc["resolution"] = res_rows

    # 4. the capture through the rig, then again from the cache
    with tempfile.TemporaryDirectory() as tmp:
        cache = RenderCache(Path(tmp))
        cap_s = dataclasses.replace(chosen_s, cache=True)
        if chosen["cpu_s_per_view"] > CAPTURE_CPU_CAP_S:  # keep the run bounded: capture at the default setting
            cap_s = dataclasses.replace(default, threads=a.threads, cache=True)
        doc["capture_settings"] = {"spp": cap_s.spp, "sampler": cap_s.sampler, "denoise": cap_s.denoise,
                                   "strength": cap_s.denoise_strength}
        rr = MitsubaRenderer(world, cap_s, cache=cache)
        with SimCameraRig.from_world(world, rig_cfg, rgb_renderer=rr) as rig:
            with Clock() as c_cap:
                cap = rig.capture()
            with Clock() as c_hit:
                rig.capture()
        with SimCameraRig.from_world(world, rig_cfg) as plain, Clock() as c_mj:
            plain.capture()
    t_cap, t_hit, t_mj = c_cap.wall, c_hit.wall, c_mj.wall
    doc["capture"] = {"views": len(cap), "width": W, "height": H, "seconds": t_cap, "cpu_seconds": c_cap.cpu,
                      "cache_hit_seconds": t_hit, "mujoco_seconds": t_mj, "renderer": cap.metadata["renderer"],
                      "stats": rr.stats}
    log.info("capture %d views: %.1f s; from the cache %.2f s; MuJoCo %.2f s", len(cap), t_cap, t_hit, t_mj)

    # 5. side by side (MuJoCo | PBR) of one view
    view = int(pick[len(pick) // 2])
    side = np.concatenate([_mujoco_rgb(world, rig_cfg, poses[view]), cap.views[view].rgb], axis=1)
    a.out.mkdir(parents=True, exist_ok=True)
    png = a.out / "render_side_by_side.png"
    cv2.imwrite(str(png), side[..., ::-1])
    doc["side_by_side"] = {"file": png.name, "view": view, "left": "mujoco", "right": cap.metadata["renderer"]}
    doc["context"]["load_avg_end"] = list(os.getloadavg())
    bc.write_json(a.out / "render.json", doc)
    (a.out / "render.md").write_text(markdown(doc))
    log.info("wrote %s", a.out / "render.json")
    return 0


def _mean(xs: list) -> float | None:
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else None


def _mujoco_rgb(world: Any, cfg: Any, T: np.ndarray) -> np.ndarray:
    from sim.cameras.rig import SimCameraRig

    with SimCameraRig.from_world(world, cfg) as rig:
        return rig.render_arrays(T, channels=["rgb"])["rgb"]


def markdown(doc: dict[str, Any]) -> str:
    c, sc, ch = doc["context"], doc["scene"], doc["chosen"]
    rend = c["renderer"]
    out = [f"# Physically based renderer ({sc['scenario']} seed {sc['seed']}, {sc['width']}x{sc['height']})\n",
           f"Renderer: Mitsuba {rend['mitsuba']} `{rend['mitsuba_variant']}` (libLLVM: {rend['libllvm']}), "
           f"integrator `{rend['integrator']}`, max depth {rend['max_depth']}, {c['threads']} threads. "
           f"Reference: {doc['reference']['spp']} spp. Segmenter proxy: {doc['reference']['proxy']}; "
           f"agreement = IoU of its masks on the test render vs on the reference.\n", bc.context_md(c),
           f"\n**Chosen**: {ch['spp']} spp ({ch.get('sampler', 'ldsampler')}), denoise `{ch['denoise']}` "
           f"(strength {ch['strength']}): "
           f"{ch['s_per_view']:.2f} s per view; proxy agreement >= {ch['agreement']} on every view: "
           f"{ch['meets_agreement']}.\n",
           "\n## spp sweep (median per view; noise vs the reference, mean over views)\n"]
    rows = [[x["spp"], x.get("sampler", "ldsampler"), x["denoise"], x["strength"], x["s_per_view"],
             x["cpu_s_per_view"], x["render_s"], x["post_s"],
             x["rmse"], x["rmse_glass"], x["psnr_db"], x["edge_f1"], x["proxy_iou"], x["proxy_iou_min"]]
            for x in doc["sweep"]]
    out.append(bc.md_table(["spp", "sampler", "denoise", "strength", "wall s/view", "CPU s/view", "render s", "post s",
                            "RMSE",
                            "RMSE glass", "PSNR dB", "edge F1", "proxy IoU", "proxy IoU min"], rows, 3))
    out.append("\nCPU s/view counts every thread: on 2 free cores the wall time is at least CPU s / 2.\n")
    out.append("\n## Resolution (chosen setting)\n")
    out.append(bc.md_table(["width", "height", "wall s/view", "CPU s/view"],
                           [[x["width"], x["height"], x["s_per_view"], x["cpu_s_per_view"]]
                            for x in doc["resolution"]], 2))
    cap = doc["capture"]
    out.append(f"\n## Capture\n{cap['views']} views {cap['width']}x{cap['height']} through the rig "
               f"(`{cap['renderer']}`): **{cap['seconds']:.1f} s** wall, {cap['cpu_seconds']:.1f} CPU s "
               f"(RGB from PBR; depth + masks from MuJoCo, "
               f"cache writes included); again from the render cache: **{cap['cache_hit_seconds']:.2f} s**; "
               f"MuJoCo-only capture: {cap['mujoco_seconds']:.2f} s.\n")
    out.append(f"\nSide by side (MuJoCo | PBR), view {doc['side_by_side']['view']}: "
               f"`{doc['side_by_side']['file']}`\n")
    return "".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
