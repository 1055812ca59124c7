"""Reconstruction benchmark (paper Sec. IV-B/C, Tables I and II, Fig. 5) on the simulated scenes.

Parts (``--parts``, default all, each written to ``<out>/reconstruction_<part>.json`` after every unit so an
interrupted run keeps what it measured; the combined ``reconstruction.json``/``.md``/``_curves.png`` are
(re)built from whatever part files exist at the end of every run, or with ``--report-only``):

- ``fast``: the default fast mode (visual hull + refinement) with GT masks and with corrupted masks
  (noisy segmenter, preset ``--corrupt-preset``): objects found vs present, silhouette IoU vs GT masks over
  all views at the capture resolution, dense Chamfer (mm), volume IoU and ratio, wall time of
  ``reconstruct()``; with GT masks also the Table II depth metrics (rendered depth vs ideal GT depth inside
  the GT masks).
- ``paper``: TORM-paper (DMTet-Multi), the default paper configuration (MLP, sphere, envelope loss, 5000
  steps, no rescue) on ``--paper-scenes``: quality, wall and CPU time with the per-stage breakdown. The time is
  the headline: run it on an idle machine; the optimisation runs with ``DMTetConfig.threads`` (1, measured
  faster than 2 on 2 cores) unless ``--paper-threads`` says otherwise, with the side thread on the second core
  (``--paper-side-thread``) and the MLP's start fit on ``--threads`` (about 100 s a scene here).
- ``table1`` (or ``--table1``): Table I with the paper's MLP: L_init (eq. 1, at 0.1x and 1x learning rate) vs the
  envelope loss (eq. 2), GT vs corrupted masks, ``--table1-iters`` (8000, the paper's) steps, each without and
  with the rescue, on ``--table1-scenes``. Rows are appended one by one and a rerun skips the ones done, so it can
  run for hours in the background (``nice -n 15``, ``--threads 1``): about 4-10 min a run here.
- ``timing``: the fast mode's wall time alone in the process.

The DMTet runs of ``table1`` call :func:`torm.reconstruction.optimise_dmtet` directly (the same call
``reconstruct(mode="paper")`` makes: same grid, masks downsampled to ``mask_res``, sphere start) so that a
collapsed or partial mesh is measured (scored 0) instead of raising; components are split and filtered like
``reconstruct()``.

Every table names the mode: "TORM-fast (hull + DMTet refinement)" or "TORM-paper (DMTet-Multi)".

Run: ``python benchmarks/reconstruction.py [--quick] [--parts fast paper table1 timing] [--table1] [--scenarios ...]``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
import numpy as np  # noqa: E402

from torm.errors import ReconstructionError  # noqa: E402
from torm.mesh import split_components  # noqa: E402
from torm.mesh.split import signed_volume  # noqa: E402
from torm.reconstruction import DMTetConfig, ReconstructionConfig, build_tet_grid, optimise_dmtet, reconstruct  # noqa: E402
from torm.reconstruction.api import DEFAULT_BOUNDS  # noqa: E402
from torm.reconstruction.dmtet import downsample_masks  # noqa: E402
from torm.segmentation import make_segmenter  # noqa: E402

log = logging.getLogger("bench.reconstruction")

ALL_SCENES = [f"syn{i}" for i in range(1, 13)] + [f"rw{i}" for i in range(1, 9)]
PARTS = ("fast", "paper", "table1", "timing")
MODE_FAST = "TORM-fast (hull + DMTet refinement)"
MODE_PAPER = "TORM-paper (DMTet-Multi)"
#: Table I configurations: mask loss, supervision and (L_init only) the learning-rate factor.
TABLE1_CONFIGS: dict[str, dict[str, Any]] = {
    "init_lr0.1": {"loss": "init", "masks": "GT", "init_lr_scale": 0.1, "label": "L_init (eq. 1), lr x0.1"},
    "init_lr1": {"loss": "init", "masks": "GT", "init_lr_scale": 1.0, "label": "L_init (eq. 1), lr x1"},
    "envelope_GT": {"loss": "envelope", "masks": "GT", "label": "L_mask envelope (eq. 2)"},
    "envelope_Seg": {"loss": "envelope", "masks": "corrupted", "label": "L_mask envelope (eq. 2)"},
}
TARGETS = {"silhouette_iou_mean": 0.95, "chamfer_mm": 1.5, "time_s": 10.0}
PAPER_TABLE1 = [("L_init", "GT", "-", 0.151), ("L_mask (envelope)", "GT", 8000, 0.876),
                ("L_mask (envelope)", "Seg.", 8000, 0.808)]
PAPER_TABLE2 = {"rmse": 0.030, "absrel": 0.031, "mae": 0.013, "delta_1.05": 88.7, "delta_1.10": 93.2,
                "delta_1.25": 97.0}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny run for tests: 1 scene, 12 views 320x180, grid 32")
    p.add_argument("--out", type=Path, default=bc.RESULTS, help="result folder")
    p.add_argument("--cache", type=Path, default=bc.CAPTURE_CACHE, help="capture cache folder")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    p.add_argument("--report-only", action="store_true", help="only rebuild the combined files from part files")
    p.add_argument("--scenarios", nargs="+", default=None, help="scenes of the fast part (default all 20)")
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--views", type=int, default=50)
    p.add_argument("--scale", type=float, default=0.5, help="image scale of 1280x720 (0.5 -> 640x360)")
    p.add_argument("--grid", type=int, default=48, help="tet grid cells (all modes)")
    p.add_argument("--refine-iters", type=int, default=None, help="fast-mode refinement steps (default: config)")
    p.add_argument("--corrupt-preset", default="paper")
    p.add_argument("--paper-scenes", nargs="+", default=["syn1", "syn5", "syn10", "rw4", "rw7"],
                   help="scenes of the paper part (TORM-paper timing and quality)")
    p.add_argument("--paper-iters", type=int, default=None, help="paper-part steps (default: DMTetConfig, 5000)")
    p.add_argument("--paper-threads", type=int, default=None,
                   help="paper-part torch threads during the optimisation (default: DMTetConfig.threads, 1; "
                        "0: the process's --threads)")
    p.add_argument("--paper-side-thread", choices=("auto", "on", "off"), default=None,
                   help="paper part: DMTetConfig.side_thread (default auto: on with 1 torch thread and --threads >= 2)")
    p.add_argument("--paper-bf16", choices=("auto", "on", "off"), default=None,
                   help="paper part: DMTetConfig.bf16 (default auto: the band's rows away from the surface and the "
                        "start fit in bfloat16 where the CPU has it natively)")
    p.add_argument("--mlp-fit-iters", type=int, default=None, help="MLP fit to the sphere (default: config)")
    p.add_argument("--table1", action="store_true", help="run the table1 part only (same as --parts table1)")
    p.add_argument("--table1-scenes", nargs="+", default=["syn1", "syn4", "syn5", "syn10"])
    p.add_argument("--table1-iters", type=int, default=8000, help="Table I steps (the paper: 8000)")
    p.add_argument("--table1-configs", nargs="+", default=list(TABLE1_CONFIGS), choices=list(TABLE1_CONFIGS))
    p.add_argument("--table1-rescue", action=argparse.BooleanOptionalAction, default=True,
                   help="also the rows with the rescue (default on)")
    p.add_argument("--table1-merge", nargs="*", type=Path, default=[],
                   help="result folders of other table1 runs (e.g. a second process on other scenes): their rows are "
                        "added to this folder's table1 file when missing")
    p.add_argument("--eval-every", type=int, default=250, help="all-view IoU every this many DMTet steps")
    p.add_argument("--threads", type=int, default=bc.THREADS)
    p.add_argument("--timing-repeats", type=int, default=2, help="fast-mode runs per scene in the timing part")
    p.add_argument("--append", action="store_true",
                   help="add to the existing part file (table1 always resumes; paper skips scenes already done)")
    a = p.parse_args(argv)
    if a.quick:
        a.scenarios = a.scenarios or ["rw4"]
        a.views, a.scale, a.grid = 12, 0.25, 32
        a.refine_iters = 10 if a.refine_iters is None else a.refine_iters
        a.paper_scenes = a.table1_scenes = a.scenarios[:1]
        a.paper_iters, a.table1_iters = 12, 12
        a.mlp_fit_iters = 10 if a.mlp_fit_iters is None else a.mlp_fit_iters
        a.eval_every = 6
    if a.table1:
        a.parts = ["table1"]
    a.scenarios = a.scenarios or ALL_SCENES
    return a


# ----------------------------------------------------------------------------------------------------------
# Runs
# ----------------------------------------------------------------------------------------------------------
def corrupted(scene: bc.Scene, preset: str, seed: int) -> tuple[np.ndarray, dict[str, Any]]:
    """Noisy-segmenter masks (V, H, W) of the scene and their quality against GT."""
    res = make_segmenter("noisy", {"preset": preset, "seed": seed}).segment(scene.capture)
    q = res.info["quality"]
    return res.masks_vxhxw, {"preset": preset, "seed": seed, "input_iou_mean": q["silhouette_iou_mean"],
                             "input_iou_min": q["silhouette_iou_min"], "input_object_iou": q["object_iou_mean"]}


def run_fast(scene: bc.Scene, a: argparse.Namespace, masks: np.ndarray | None, depth: bool) -> dict[str, Any]:
    """Fast-mode ``reconstruct()`` (GT masks or the given ones) and its metrics against the ground truth."""
    kw: dict[str, Any] = {"grid_res": a.grid}
    if a.refine_iters is not None:
        kw["refine_iters"] = a.refine_iters
    cfg = ReconstructionConfig(mode="fast", **kw)
    cap = scene.capture if masks is None else scene.capture.with_masks(masks)
    t = time.perf_counter()
    try:
        rec = reconstruct(cap, cfg)
    except ReconstructionError as exc:
        log.warning("%s: reconstruction failed: %s", scene.name, exc)
        return {"error": str(exc), "n_present": len(scene.gt_meshes), "n_found": 0}
    wall = time.perf_counter() - t
    conf = {"grid_res": cfg.grid_res, "refine_iters": cfg.refine_iters, "vote_tolerance": cfg.vote_tolerance,
            "mask_res": cfg.mask_res}
    out = {"time_s": wall, "timings": rec.timings, "config": conf,
           "dmtet_ms_per_step": rec.info.get("dmtet_ms_per_step"),
           "recon_silhouette_iou_mean": rec.info["silhouette_iou_mean"]}
    out.update(bc.evaluate_meshes(list(rec.object_meshes), scene, depth=depth))
    return out


def split_objects(mesh) -> list:
    """Components of a DMTet mesh kept like ``reconstruct()`` does (>= 20 faces, >= 1e-7 m^3, outward)."""
    if mesh.is_empty:
        return []
    keep = split_components(mesh.verts_vx3, mesh.faces_fx3, min_faces=20, min_volume=1e-7)
    return [m for m in keep if signed_volume(m.verts_vx3, m.faces_fx3) > 0]


def time_to(hist: dict[str, list[float]], thr: float, ms_step: float, fit_s: float) -> dict[str, float | None]:
    """First evaluated step with all-view IoU >= thr and the time (s) to reach it (fit + steps x ms/step)."""
    for it, iou in zip(hist["eval_iter"], hist["iou_all"], strict=True):
        if iou >= thr:
            return {"iter": int(it), "time_s": fit_s + it * ms_step / 1e3}
    return {"iter": None, "time_s": None}


def _dm_conf(dcfg: DMTetConfig) -> dict[str, Any]:
    """The DMTet settings a result row records."""
    keys = ("param", "loss", "start", "iterations", "lr", "lr_min", "mlp_lr", "init_lr_scale", "alpha_max",
            "alpha_min", "views_per_batch", "mask_res", "lambda_mask", "lambda_eikonal", "rescue", "narrow_band",
            "band_rings", "full_pass_every", "eikonal_points", "mlp_hidden", "mlp_layers", "mlp_pe_freqs",
            "mlp_fit_clamp",
            "max_deform", "sphere_scale", "seed", "side_thread", "bf16", "bf16_sign_margin")
    out = {k: getattr(dcfg, k) for k in keys}
    out["alpha_decay_iters"] = dcfg.decay_T
    out["mlp_fit_iters"] = dcfg.mlp_fit_iters if dcfg.param == "mlp" else 0
    out["lr_scale_applied"] = dcfg.init_lr_scale if dcfg.loss == "init" and dcfg.start == "sphere" else 1.0
    return out


def _downsample(xs: list[float], every: int) -> list[float]:
    return [float(f"{x:.5g}") for x in xs[::every]]


def run_dmtet(scene: bc.Scene, a: argparse.Namespace, dcfg: DMTetConfig, masks: np.ndarray | None,
              keep_curves: bool = False) -> dict[str, Any]:
    """DMTet-Multi from the sphere (as ``reconstruct(mode="paper")`` with ``dcfg``) and its metrics.

    A run whose mesh vanished (without rescue it stops there) scores IoU 0 for 'IoU last 5' as the paper counts
    it; the batch IoU of its last five steps before the collapse is kept as ``iou_last5_before_collapse``.
    """
    cap = scene.capture
    inst = cap.masks() if masks is None else masks
    rcfg = ReconstructionConfig(mode="paper", grid_res=a.grid)
    dcfg = replace(dcfg, start="sphere", mask_res=rcfg.mask_res, seed=0, eval_every=a.eval_every)
    bounds = np.asarray(cap.workspace_bounds if cap.workspace_bounds is not None else DEFAULT_BOUNDS)
    table_z = cap.table_height or 0.0
    t0 = time.perf_counter()
    grid = build_tet_grid(bounds, a.grid)
    sup, sup_K = downsample_masks(inst > 0, cap.Ks(), rcfg.mask_res)
    res = optimise_dmtet(grid, sup_K, np.linalg.inv(cap.poses()), sup, dcfg, table_z=table_z)
    objects = split_objects(res.mesh)
    wall = time.perf_counter() - t0
    h = res.history
    ms, fit = res.timings["ms_per_step"], res.timings["mlp_fit_s"]
    collapsed = int(h["collapsed_at"][0])
    last5 = float(np.mean(h["iou"][-5:])) if h["iou"] else 0.0
    out: dict[str, Any] = {
        "mode": MODE_PAPER, "config": {**_dm_conf(dcfg), "grid_res": a.grid},
        "supervision": "GT" if masks is None else "corrupted",
        "time_s": wall, "ms_per_step": ms, "mlp_fit_s": fit, "timings": res.timings,
        "steps_run": int(res.timings["steps_run"]), "collapsed_at": collapsed,
        "empty_steps": int(h["empty_steps"][0]), "rescued_steps": int(h["rescued_steps"][0]),
        "iou_last5_vs_supervision": 0.0 if collapsed >= 0 else last5,
        "iou_last5_before_collapse": last5 if collapsed >= 0 else None,
        "iou_all_final_vs_supervision": h["iou_all"][-1],
        "full_passes": int(h["full_passes"][0]), "boundary_rebuilds": int(h["boundary_rebuilds"][0]),
        "band_misses": int(h["band_misses"][0]),
        "band_verts_mean": _mean(h["band_verts"]), "grid_verts": grid.n_verts,
        "bf16_stats": {k: h[k][0] for k in ("bf16_rows", "f32_rows", "bf16_near_rows", "bf16_late_rows",
                                            "bf16_sign_errors", "bf16_err_max") if k in h},
        "time_to_iou_0.90": time_to(h, 0.90, ms, fit), "time_to_iou_0.95": time_to(h, 0.95, ms, fit),
    }
    out.update(bc.evaluate_meshes(objects, scene))
    if keep_curves:
        every = max(1, len(h["loss"]) // 1000)
        out["curves"] = {"step": list(range(0, len(h["loss"]), every)),
                         **{k: _downsample(h[k], every) for k in ("loss", "mask_loss", "eikonal", "iou", "alpha")},
                         "eval_iter": h["eval_iter"], "iou_all": _downsample(h["iou_all"], 1)}
    log.info("%s %s %s/%s %d it (%d run, collapsed at %d, %d rescued): IoU(GT) %.3f, found %s/%s, %.0f ms/step, "
             "%.0f s", scene.name, MODE_PAPER, dcfg.loss, out["supervision"], dcfg.iterations, out["steps_run"],
             collapsed, out["rescued_steps"], out["silhouette_iou_mean"], out["n_found"], out["n_present"], ms, wall)
    return out


# ----------------------------------------------------------------------------------------------------------
# Part files
# ----------------------------------------------------------------------------------------------------------
def _part_path(out: Path, part: str) -> Path:
    return out / f"reconstruction_{part}.json"


def _load_part(out: Path, part: str) -> dict[str, Any] | None:
    import json

    p = _part_path(out, part)
    return json.loads(p.read_text()) if p.exists() else None


def part_fast(a: argparse.Namespace, ctx: dict[str, Any]) -> None:
    doc: dict[str, Any] = (_load_part(a.out, "fast") if a.append else None) or {"context": ctx, "scenes": {}}
    if doc["context"] is not ctx:
        doc.setdefault("more_contexts", []).append(ctx)
    for seed in a.seeds:
        for name in a.scenarios:
            t = time.perf_counter()
            scene = bc.get_scene(name, seed, a.views, a.scale, a.cache)
            key = f"{name}_s{seed}"
            row: dict[str, Any] = {"scenario": name, "seed": seed, "n_objects": len(scene.gt_meshes),
                                   "threads": bc.torch.get_num_threads(),
                                   "image_size": list(scene.capture.image_size), "n_views": len(scene.capture)}
            row["gt"] = run_fast(scene, a, None, depth=True)
            row["load_avg_1min"] = os.getloadavg()[0]
            masks, q = corrupted(scene, a.corrupt_preset, seed)
            row["corrupted"] = {**q, **run_fast(scene, a, masks, depth=False)}
            # the same silhouettes with every instance id merged into 1: reconstruct() only uses the union for
            # geometry, the ids only for its per-object validation (which spurious blob ids can fail)
            row["corrupted_union"] = run_fast(scene, a, (masks > 0).astype(np.int32), depth=False)
            doc["scenes"][key] = row
            bc.write_json(_part_path(a.out, "fast"), doc)
            g, c = row["gt"], row["corrupted"]
            log.info("%s fast: GT found %s/%s IoU %s Chamfer %s mm %.1f s | corrupted (input IoU %.3f) IoU %s "
                     "found %s (%.0f s for the scene)", key, g.get("n_found"), g.get("n_present"),
                     bc.fmt(g.get("silhouette_iou_mean")), bc.fmt(g.get("chamfer_mm"), 2), g.get("time_s", np.nan),
                     c["input_iou_mean"], bc.fmt(c.get("silhouette_iou_mean")), c.get("n_found"),
                     time.perf_counter() - t)


def part_timing(a: argparse.Namespace, ctx: dict[str, Any]) -> None:
    """Wall time of the default fast ``reconstruct()`` (GT masks) per scene, ``--timing-repeats`` runs each,
    nothing else running in this process (run it when the machine is quiet; the load is recorded per scene)."""
    doc: dict[str, Any] = {"context": ctx, "scenes": {}}
    kw: dict[str, Any] = {"grid_res": a.grid}
    if a.refine_iters is not None:
        kw["refine_iters"] = a.refine_iters
    cfg = ReconstructionConfig(mode="fast", **kw)
    for seed in a.seeds:
        for name in a.scenarios:
            scene = bc.get_scene(name, seed, a.views, a.scale, a.cache)
            times, stages = [], []
            load = os.getloadavg()[0]
            for _ in range(a.timing_repeats):
                t = time.perf_counter()
                try:
                    rec = reconstruct(scene.capture, cfg)
                except ReconstructionError as exc:
                    doc["scenes"][f"{name}_s{seed}"] = {"error": str(exc)}
                    break
                times.append(time.perf_counter() - t)
                stages.append(rec.timings)
            if times:
                doc["scenes"][f"{name}_s{seed}"] = {"time_s": times, "time_s_min": min(times),
                                                    "time_s_median": float(np.median(times)), "timings": stages,
                                                    "dmtet_ms_per_step": rec.info.get("dmtet_ms_per_step"),
                                                    "load_avg_1min": load}
                log.info("%s timing: %s s (load %.2f)", name, ", ".join(f"{x:.2f}" for x in times), load)
            bc.write_json(_part_path(a.out, "timing"), doc)


def _start_doc(a: argparse.Namespace, part: str, ctx: dict[str, Any]) -> dict[str, Any]:
    old = _load_part(a.out, part) if a.append or part == "table1" else None
    if old:
        old.setdefault("more_contexts", []).append(ctx)
        return old
    return {"context": ctx, "runs": []}


def part_paper(a: argparse.Namespace, ctx: dict[str, Any]) -> None:
    """TORM-paper (DMTet-Multi) with the default paper configuration per scene: quality and wall time.

    Calls :func:`run_dmtet` (what ``reconstruct(mode="paper")`` runs, minus its input checks and point
    sampling) so that a scene where an object is missing is still measured; ``reconstruct()`` itself raises
    for such a scene (its coverage check), which is what the grasping pipeline sees. Run it on an idle machine:
    the time is the headline figure. The row's ``threads`` is what the optimisation ran with.
    """
    doc = _start_doc(a, "paper", ctx)
    done = {r["scenario"] for r in doc["runs"]}
    dm = DMTetConfig() if a.paper_iters is None else DMTetConfig(iterations=a.paper_iters)
    if a.mlp_fit_iters is not None:
        dm = replace(dm, mlp_fit_iters=a.mlp_fit_iters)
    if a.paper_threads is not None:
        dm = replace(dm, threads=a.paper_threads)
    if a.paper_side_thread is not None:
        dm = replace(dm, side_thread=a.paper_side_thread)
    if a.paper_bf16 is not None:
        dm = replace(dm, bf16=a.paper_bf16)
    for name in a.paper_scenes:
        if name in done:
            continue
        scene = bc.get_scene(name, a.seeds[0], a.views, a.scale, a.cache)
        row: dict[str, Any] = {"scenario": name, "seed": a.seeds[0], "load_avg_1min_start": os.getloadavg()[0]}
        row.update(run_dmtet(scene, argparse.Namespace(**{**vars(a), "eval_every": 0}), dm, None))
        row["threads"] = int(row["timings"]["torch_threads"])  # what the optimisation ran with
        row["load_avg_1min_end"] = os.getloadavg()[0]
        doc["runs"].append(row)
        bc.write_json(_part_path(a.out, "paper"), doc)


def table1_jobs(a: argparse.Namespace) -> list[tuple[str, str, bool]]:
    """(scene, config name, rescue) in run order: each config on every scene, the no-rescue rows first."""
    jobs = [(s, c, False) for c in a.table1_configs for s in a.table1_scenes]
    if a.table1_rescue:
        jobs += [(s, c, True) for c in a.table1_configs for s in a.table1_scenes]
    return jobs


def part_table1(a: argparse.Namespace, ctx: dict[str, Any]) -> None:
    """Table I with the paper's MLP: L_init vs the envelope loss, GT vs corrupted masks, with and without rescue.

    One row per (scene, config, rescue) appended to ``reconstruction_table1.json`` as it finishes; a rerun skips
    the rows already there (resumable). A rescue row whose no-rescue twin never saw an empty mesh is not rerun:
    the rescue acts only on empty meshes, so the run is identical step for step
    (``tests/test_recon_paper_mode.py::test_rescue_changes_nothing_when_the_mesh_never_vanishes``); the row says so.
    """
    doc = _start_doc(a, "table1", ctx)
    have = {r["key"]: r for r in doc["runs"]}
    for folder in a.table1_merge:
        other = _load_part(folder, "table1") or {"runs": []}
        for r in other["runs"]:
            if r["key"] not in have:
                doc["runs"].append(r)
                have[r["key"]] = r
        if other["runs"]:
            doc.setdefault("merged_from", []).append({"folder": str(folder), "context": other["context"]})
    bc.write_json(_part_path(a.out, "table1"), doc)
    masks_cache: dict[str, tuple[np.ndarray, dict[str, Any]]] = {}
    for name, cname, rescue in table1_jobs(a):
        key = f"{name}/{cname}/{'rescue' if rescue else 'no_rescue'}"
        if key in have:
            continue
        spec = TABLE1_CONFIGS[cname]
        twin = have.get(f"{name}/{cname}/no_rescue")
        if rescue and twin is not None and twin["empty_steps"] == 0:
            row = {**twin, "key": key, "rescue": True, "rescue_ran": False,
                   "note": "identical to the no-rescue run: its mesh never vanished and the rescue acts only on an "
                           "empty mesh"}
        else:
            scene = bc.get_scene(name, a.seeds[0], a.views, a.scale, a.cache)
            masks, q = None, {}
            if spec["masks"] == "corrupted":
                if name not in masks_cache:
                    masks_cache[name] = corrupted(scene, a.corrupt_preset, a.seeds[0])
                masks, q = masks_cache[name]
            dcfg = DMTetConfig(param="mlp", loss=spec["loss"], iterations=a.table1_iters, rescue=rescue,
                               init_lr_scale=spec.get("init_lr_scale", DMTetConfig().init_lr_scale))
            if a.mlp_fit_iters is not None:
                dcfg = replace(dcfg, mlp_fit_iters=a.mlp_fit_iters)
            row = {"key": key, "scenario": name, "seed": a.seeds[0], "table1_config": cname, "rescue": rescue,
                   "rescue_ran": rescue, "load_avg_1min_start": os.getloadavg()[0],
                   **run_dmtet(scene, a, dcfg, masks, keep_curves=True), **q}
            row["load_avg_1min_end"] = os.getloadavg()[0]
        doc["runs"].append(row)
        have[key] = row
        bc.write_json(_part_path(a.out, "table1"), doc)


# ----------------------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------------------
def _mean(xs: list[Any]) -> float:
    v = [float(x) for x in xs if x is not None and np.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def _pct(x: Any) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def _ctx_block(title: str, doc: dict[str, Any] | None) -> str:
    if not doc:
        return ""
    out = f"**{title} run context**\n\n" + bc.context_md(doc["context"])
    for c in doc.get("more_contexts", []):
        out += (f"- continued/extended by a second invocation (`--append`) at {c['date_utc']}: torch threads "
                f"{c['threads']}, load at start {c['load_avg_start'][0]:.2f}, arguments `{c['args']}`\n")
    return out + "\n"


def _fast_md(fast: dict[str, Any], timing: dict[str, Any] | None) -> tuple[str, dict[str, Any]]:
    rows, crows, drows = [], [], []
    summary: dict[str, Any] = {}
    scenes = fast["scenes"]
    tsc = (timing or {}).get("scenes", {})
    for key, s in scenes.items():
        g = s["gt"]
        t_quiet = tsc.get(key, {}).get("time_s_min")
        g["time_s_timing_pass"] = t_quiet
        t_target = t_quiet if t_quiet is not None else g.get("time_s", float("inf"))
        ok = ("error" not in g and g["n_found"] == g["n_present"] and g["n_spurious"] == 0
              and g["silhouette_iou_mean"] >= TARGETS["silhouette_iou_mean"]
              and g["chamfer_mm"] <= TARGETS["chamfer_mm"] and t_target <= TARGETS["time_s"])
        rows.append([key, f"{g.get('n_found', 0)}/{g['n_present']}" + (f" +{g['n_spurious']}" if g.get("n_spurious")
                                                                        else ""),
                     g.get("silhouette_iou_mean"), g.get("silhouette_iou_min"), g.get("chamfer_mm"),
                     g.get("volume_iou"), g.get("volume_ratio"), g.get("time_s"),
                     s.get("threads", fast["context"]["threads"]), s.get("load_avg_1min"), t_quiet,
                     tsc.get(key, {}).get("load_avg_1min"), "yes" if ok else "**no**"])
        for variant in ("corrupted", "corrupted_union"):
            c = s.get(variant)
            if c is None:
                continue
            crows.append([key, "instance ids" if variant == "corrupted" else "union (ids merged)",
                          s["corrupted"]["input_iou_mean"], s["corrupted"]["input_iou_min"],
                          f"{c.get('n_found', 0)}/{c['n_present']}" + (f" +{c['n_spurious']}" if c.get("n_spurious")
                                                                        else ""),
                          c.get("silhouette_iou_mean"), c.get("silhouette_iou_min"), c.get("chamfer_mm"),
                          c.get("volume_iou"), c.get("time_s"), c.get("error", "")[:90]])
        if "depth" in g:
            d = g["depth"]
            drows.append([key, d["rmse"], d["absrel"], d["mae"], _pct(d["delta_1.05"]), _pct(d["delta_1.10"]),
                          _pct(d["delta_1.25"]), _pct(d["coverage"])])
    gts = [s["gt"] for s in scenes.values() if "error" not in s["gt"]]
    n_ok = sum(1 for r in rows if r[-1] == "yes")
    summary["fast_gt"] = {
        "scenes": len(scenes), "scenes_meeting_all_targets": n_ok,
        "all_objects_found": sum(1 for g in gts if g["n_found"] == g["n_present"]),
        "iou_mean": _mean([g["silhouette_iou_mean"] for g in gts]),
        "iou_min": float(np.min([g["silhouette_iou_min"] for g in gts])) if gts else float("nan"),
        "chamfer_mm_mean": _mean([g["chamfer_mm"] for g in gts]),
        "chamfer_mm_max": float(np.max([g["chamfer_mm"] for g in gts])) if gts else float("nan"),
        "volume_iou_mean": _mean([g["volume_iou"] for g in gts]),
        "time_s_mean": _mean([g["time_s"] for g in gts]),
        "time_s_max": float(np.max([g["time_s"] for g in gts])) if gts else float("nan"),
        "time_s_timing_pass_mean": _mean([g["time_s_timing_pass"] for g in gts]),
        "time_s_timing_pass_max": float(np.nanmax([g["time_s_timing_pass"] if g["time_s_timing_pass"] is not None
                                                   else np.nan for g in gts])) if tsc and gts else float("nan"),
        "dmtet_ms_per_step_mean": _mean([g.get("dmtet_ms_per_step") for g in gts]),
    }
    csum_rows = []
    for variant in ("corrupted", "corrupted_union"):
        have = [s for s in scenes.values() if variant in s]
        cs = [s[variant] for s in have if "error" not in s[variant]]
        summary[f"fast_{variant}"] = d = {
            "scenes": len(have), "failed": len(have) - len(cs),
            "all_objects_found": sum(1 for c in cs if c["n_found"] == c["n_present"]),
            "spurious": sum(c.get("n_spurious", 0) for c in cs),
            "input_iou_mean": _mean([s["corrupted"]["input_iou_mean"] for s in have]),
            "iou_mean": _mean([c["silhouette_iou_mean"] for c in cs]),
            "chamfer_mm_mean": _mean([c["chamfer_mm"] for c in cs]),
            "volume_iou_mean": _mean([c["volume_iou"] for c in cs]),
        }
        if have:
            csum_rows.append(["instance ids" if variant == "corrupted" else "union (ids merged)", d["scenes"],
                              d["failed"], d["all_objects_found"], d["spurious"], d["input_iou_mean"], d["iou_mean"],
                              d["chamfer_mm_mean"], d["volume_iou_mean"]])
    dsum = {}
    for grp, pref in (("synthetic", "syn"), ("real-world layouts", "rw"), ("all", "")):
        ds = [s["gt"]["depth"] for k, s in scenes.items() if k.startswith(pref) and "depth" in s["gt"]]
        if ds:
            dsum[grp] = {k: _mean([d[k] for d in ds]) for k in ("rmse", "absrel", "mae", "delta_1.05", "delta_1.10",
                                                              "delta_1.25", "coverage")}
            dsum[grp]["n_scenes"] = len(ds)
    summary["depth"] = dsum
    from sim.scenes.scenario import get_scenario

    def has_cup(key: str) -> bool:
        return any("cup" in o for o in get_scenario(scenes[key]["scenario"]).objects)

    grows = []
    for label, sel in (("scenes without an open cup", False), ("scenes with an open cup", True)):
        gg = [s["gt"] for k, s in scenes.items() if "error" not in s["gt"] and has_cup(k) == sel]
        if not gg:
            continue
        geo_ok = sum(1 for g in gg if g["n_found"] == g["n_present"] and g["n_spurious"] == 0
                     and g["silhouette_iou_mean"] >= TARGETS["silhouette_iou_mean"]
                     and g["chamfer_mm"] <= TARGETS["chamfer_mm"])
        d = {"scenes": len(gg), "geometry_targets_met": geo_ok,
             "iou_mean": _mean([g["silhouette_iou_mean"] for g in gg]),
             "chamfer_mm_mean": _mean([g["chamfer_mm"] for g in gg]),
             "chamfer_mm_max": float(np.max([g["chamfer_mm"] for g in gg])),
             "volume_iou_mean": _mean([g["volume_iou"] for g in gg]),
             "volume_ratio_mean": _mean([g["volume_ratio"] for g in gg])}
        summary["fast_gt"][label.replace(" ", "_")] = d
        grows.append([label, d["scenes"], d["geometry_targets_met"], d["iou_mean"], d["chamfer_mm_mean"],
                      d["chamfer_mm_max"], d["volume_iou_mean"], d["volume_ratio_mean"]])
    sg = summary["fast_gt"]
    md = [f"## Fast mode, {MODE_FAST} (default config), GT masks\n",
          f"Targets (issue): every object found, mean silhouette IoU >= {TARGETS['silhouette_iou_mean']}, Chamfer <= "
          f"{TARGETS['chamfer_mm']} mm, <= {TARGETS['time_s']} s. **{n_ok} of {len(rows)} scenes meet all targets**; "
          f"all objects found in {sg['all_objects_found']}/{len(gts)}; mean IoU {bc.fmt(sg['iou_mean'])} "
          f"(worst view {bc.fmt(sg['iou_min'])}); Chamfer mean {bc.fmt(sg['chamfer_mm_mean'], 2)} mm, max "
          f"{bc.fmt(sg['chamfer_mm_max'], 2)} mm; volume IoU mean {bc.fmt(sg['volume_iou_mean'])}; time mean "
          f"{bc.fmt(sg['time_s_mean'], 1)} s, max {bc.fmt(sg['time_s_max'], 1)} s in the (contended) metric run, "
          f"mean {bc.fmt(sg['time_s_timing_pass_mean'], 1)} s, max {bc.fmt(sg['time_s_timing_pass_max'], 1)} s in the "
          f"timing pass ({timing['context']['threads'] if timing else '-'} torch thread(s); the time target is "
          "checked on the timing pass when it exists).\n",
          "Silhouette IoU: the union of the reconstructed objects rendered in every view at the capture resolution "
          f"vs the GT masks. Chamfer: {bc.CHAMFER_POINTS} seeded area-uniform samples on the union of the "
          "reconstructed objects and on the union of the GT outer shells, two-sided mean distance / 2. Volume IoU "
          "and ratio: union vs union on 1 mm voxel centres (coarser when the box is large; `volume_pitch_mm`). "
          "Time: wall time of `reconstruct()` (masks + cameras in, per-object meshes + point clouds out), in the "
          "metric run (other benchmark processes and other users running; 1-min load average in 'load') and in the "
          "separate timing pass (`--parts timing`: only `reconstruct()` in the process, min over repeats).\n",
          bc.md_table(["scene", "found/present (+spurious)", "IoU mean", "IoU min", "Chamfer mm", "vol IoU",
                      "vol ratio", "time s", "threads", "load", "time s (timing pass)", "load (timing pass)",
                      "targets met"], rows),
          "\nBy scene type: silhouettes cannot reveal a concavity, so the open cup's cavity is filled in (volume "
          "ratio > 1, the filled-in cap lies far from the GT inner wall), which raises Chamfer on every scene "
          "holding a cup ('opaque_cup' included). 'Geometry targets' = all objects found, no spurious one, "
          "IoU >= 0.95 and Chamfer <= 1.5 mm (time not included).\n\n",
          bc.md_table(["scenes", "n", "geometry targets met", "IoU mean", "Chamfer mm mean", "Chamfer mm max",
                       "vol IoU mean", "vol ratio mean"], grows),
          f"\n## Table II: depth from the reconstruction ({MODE_FAST}, GT masks)\n",
          "Depth of the reconstructed mesh rendered in every view, compared with the ideal simulator depth inside "
          "the GT masks (pixels the reconstruction does not cover are excluded and counted in coverage). "
          "The paper averages its 12 synthetic scenes (100 views each, Blender); here the simulated scenes, "
          "50 views at the capture resolution.\n",
          bc.md_table(["scenes", "RMSE m", "AbsRel", "MAE m", "d1.05 %", "d1.10 %", "d1.25 %", "coverage %"],
                     [[f"{g} (mean of {d['n_scenes']})", d["rmse"], d["absrel"], d["mae"], _pct(d["delta_1.05"]),
                       _pct(d["delta_1.10"]), _pct(d["delta_1.25"]), _pct(d["coverage"])] for g, d in dsum.items()]
                     + [["paper: TORM (Ours)", *[PAPER_TABLE2[k] for k in ("rmse", "absrel", "mae")],
                         *[f"{PAPER_TABLE2[k]:.1f}" for k in ("delta_1.05", "delta_1.10", "delta_1.25")], "-"]],
                     nd=4),
          "\nPer scene:\n\n",
          bc.md_table(["scene", "RMSE m", "AbsRel", "MAE m", "d1.05 %", "d1.10 %", "d1.25 %", "coverage %"], drows,
                      nd=4),
          f"\n## Fast mode, {MODE_FAST}, with corrupted masks (noisy segmenter, preset "
          f"`{fast['context']['args']['corrupt_preset']}`, seed = scene seed)\n",
          "Input IoU: corrupted masks vs GT masks (union silhouettes, per view). IoU/Chamfer/volume IoU of the "
          "reconstruction against the GT (not against the corrupted masks). Two variants of the same corrupted "
          "masks: 'instance ids' = as the segmenter labels them (spurious blobs get their own id); 'union (ids "
          "merged)' = every instance id set to 1. `reconstruct()` builds the geometry from the union either way; "
          "the ids only feed its per-object input validation and coverage check, which a spurious blob seen in a "
          "few views can fail (ReconstructionError, counted as failed, excluded from the means).\n",
          bc.md_table(["masks", "scenes", "failed", "scenes with all objects found", "spurious objects",
                       "input IoU mean", "IoU vs GT mean", "Chamfer mm mean", "vol IoU mean"], csum_rows),
          "\nPer scene:\n\n",
          bc.md_table(["scene", "masks", "input IoU mean", "input IoU min", "found/present (+spurious)", "IoU mean",
                       "IoU min", "Chamfer mm", "vol IoU", "time s", "error"], crows)]
    return "\n".join(md), summary


def _dmtet_rows(runs: list[dict[str, Any]]) -> list[list[Any]]:
    rows = []
    for r in runs:
        c = r["config"]
        coll = r.get("collapsed_at", -1)
        rows.append([r["scenario"], r.get("table1_config", c["loss"]), r["supervision"],
                     "yes" if r.get("rescue") else "no", c["iterations"], r["steps_run"],
                     "-" if coll is None or coll < 0 else coll, r.get("rescued_steps", 0),
                     f"{r['n_found']}/{r['n_present']}" + (f" +{r['n_spurious']}" if r.get("n_spurious") else ""),
                     r["iou_last5_vs_supervision"], r["silhouette_iou_mean"], r["chamfer_mm"], r["volume_iou"],
                     r["ms_per_step"], r["time_s"], r.get("band_misses", "-"),
                     "no (identical run)" if r.get("rescue") and not r.get("rescue_ran") else "yes"])
    return rows


DMTET_HEADER = ["scene", "config", "masks", "rescue", "iterations", "steps run", "collapsed at step", "rescued steps",
                "found/present", "IoU last 5 (vs sup.)", "IoU vs GT", "Chamfer mm", "vol IoU", "ms/step", "total s",
                "band misses", "ran"]


def _steps(xs: list[Any]) -> str:
    return ", ".join(str(int(s)) for s in xs)


def _table1(doc: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    groups: dict[tuple[str, bool], list[dict[str, Any]]] = {}
    for r in doc["runs"]:
        groups.setdefault((r["table1_config"], bool(r["rescue"])), []).append(r)
    rows, summ = [], {}
    for (cname, rescue), rs in sorted(groups.items(), key=lambda kv: (list(TABLE1_CONFIGS).index(kv[0][0]), kv[0][1])):
        spec = TABLE1_CONFIGS[cname]
        coll = [r for r in rs if r.get("collapsed_at", -1) >= 0]
        d = {"n_runs": len(rs), "scenes": [r["scenario"] for r in rs], "iterations": rs[0]["config"]["iterations"],
             "iou_last5_vs_supervision": _mean([r["iou_last5_vs_supervision"] for r in rs]),
             "collapsed": len(coll), "collapse_steps": [r["collapsed_at"] for r in coll],
             "runs_with_rescued_steps": sum(1 for r in rs if r.get("rescued_steps", 0) > 0),
             "rescued_steps_total": sum(int(r.get("rescued_steps", 0)) for r in rs),
             "iou_vs_gt": _mean([r["silhouette_iou_mean"] for r in rs]),
             "chamfer_mm": _mean([r["chamfer_mm"] for r in rs]), "volume_iou": _mean([r["volume_iou"] for r in rs]),
             "objects_found": f"{sum(r['n_found'] for r in rs)}/{sum(r['n_present'] for r in rs)}",
             "lr_scale": rs[0]["config"].get("lr_scale_applied")}
        summ[f"{cname}/{'rescue' if rescue else 'no_rescue'}"] = d
        rows.append([spec["label"], "x" if spec["masks"] == "GT" else "", "x" if spec["masks"] != "GT" else "",
                     "yes" if rescue else "no", d["iterations"], d["iou_last5_vs_supervision"],
                     f"{d['collapsed']}/{d['n_runs']}" + (f" (steps {_steps(d['collapse_steps'])})"
                                                          if d["collapse_steps"] else ""),
                     f"{d['runs_with_rescued_steps']} runs, {d['rescued_steps_total']} steps" if rescue else "-",
                     d["iou_vs_gt"], d["objects_found"], d["chamfer_mm"], d["volume_iou"], ", ".join(d["scenes"])])
    paper = [[f"paper: {n}", "x" if s == "GT" else "", "x" if s != "GT" else "", "-", it, iou, "-", "-", "-", "-", "-",
              "-", "Syn1-12"] for n, s, it, iou in PAPER_TABLE1]
    ctx = doc["context"]
    md = (f"## Table I: mask loss ablation, {MODE_PAPER} with the paper's MLP\n\n"
          f"Every run: 3-layer MLP f(v) (hidden 128, Adam), oversized sphere start, eikonal term (eq. 4), "
          f"{TABLE1_CONFIGS and doc['runs'][0]['config']['views_per_batch']} views per step, grid "
          f"{ctx['args']['grid']}, masks at {doc['runs'][0]['config']['mask_res']} px, same seed. 'IoU last 5': the "
          "paper's metric, the mean batch IoU of the last five steps against the supervision masks, **0 for a run "
          "whose mesh vanished** (the paper records a collapsed run as 0). Without rescue a vanished mesh ends the run "
          "(no gradient reaches the field again); with rescue (`DMTetConfig.rescue`, not in the paper) the step pulls "
          "the SDF down inside the batch silhouettes and the run goes on. L_init's learning rate: the paper applies "
          "'a lower learning rate' without a value; we run 0.1x (our default `init_lr_scale`) and 1x. IoU vs GT: "
          "final mesh vs GT masks over all views at the capture resolution.\n\n"
          + bc.md_table(["mask loss (eq.)", "GT", "Seg.", "rescue", "iterations", "IoU last 5 (vs sup.)",
                         "collapsed runs", "rescued", "IoU vs GT", "objects found", "Chamfer mm", "vol IoU", "scenes"],
                        rows + paper)
          + "\nPer run:\n\n" + bc.md_table(DMTET_HEADER, _dmtet_rows(doc["runs"])))
    return md, summ


def _curves_png(doc: dict[str, Any], path: Path) -> str | None:
    """IoU and loss vs iteration of the no-rescue Table I runs on one scene (cf. the paper's Fig. 5)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in doc["runs"] if "curves" in r and not r["rescue"]]
    if not runs:
        return None
    scenes = [r["scenario"] for r in runs]
    scene = "syn5" if "syn5" in scenes else scenes[0]
    runs = [r for r in runs if r["scenario"] == scene]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r in runs:
        cv = r["curves"]
        lab = f"{TABLE1_CONFIGS[r['table1_config']]['label']}, {r['supervision']}"
        it = np.asarray(cv["step"])
        iou = np.asarray(cv["iou"])
        k = max(1, min(20, len(iou) // 10))
        sm = np.convolve(iou, np.ones(k) / k, mode="valid")
        (line,) = ax[0].plot(it[k - 1:], sm, label=lab, lw=1.2)
        ax[0].plot(cv["eval_iter"], cv["iou_all"], "o", ms=3, color=line.get_color())
        ax[1].semilogy(it, np.maximum(cv["loss"], 1e-8), label=lab, lw=1.0, color=line.get_color())
        if r.get("collapsed_at", -1) >= 0:
            for a_ in ax:
                a_.axvline(r["collapsed_at"], color=line.get_color(), ls=":", lw=1)
            ax[0].plot([r["collapsed_at"]], [0.0], "x", ms=8, color=line.get_color())
    ax[0].set(xlabel="iteration", ylabel="IoU vs supervision masks", ylim=(-0.02, 1),
              title=f"{scene}: IoU (line: batch, {k}-sample mean; dots: all views; x: mesh vanished)")
    ax[1].set(xlabel="iteration", ylabel="loss (eq. 5)", title=f"{scene}: loss, {MODE_PAPER}")
    ax[0].legend(fontsize=8)
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return scene


def _paper_md(doc: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    rows = []
    for r in doc["runs"]:
        dt_ = r["timings"]
        coll = r.get("collapsed_at", -1)
        rows.append([r["scenario"], r["config"]["iterations"], "-" if coll < 0 else coll,
                     f"{r['n_found']}/{r['n_present']}" + (f" +{r['n_spurious']}" if r.get("n_spurious") else ""),
                     r["iou_last5_vs_supervision"], r["silhouette_iou_mean"], r["chamfer_mm"], r["volume_iou"],
                     r["time_s"], dt_.get("total_cpu_s"), r["ms_per_step"], r["mlp_fit_s"],
                     dt_.get("field_ms_per_step"), dt_.get("full_pass_ms_per_step"),
                     dt_.get("marching_tets_ms_per_step"), dt_.get("render_loss_ms_per_step"),
                     dt_.get("eikonal_ms_per_step", dt_.get("eikonal_wait_ms_per_step")),
                     dt_.get("backward_step_ms_per_step"), dt_.get("field_grad_ms_per_step"), r.get("band_verts_mean"),
                     r.get("band_misses"), r["threads"], {1.0: "on", 0.0: "off"}.get(dt_.get("side_thread"), "-"),
                     dt_.get("fit_threads", "-"), r["load_avg_1min_start"], r["load_avg_1min_end"]])
    runs = doc["runs"]
    summ = {"scenes": len(runs), "collapsed": sum(1 for r in runs if r.get("collapsed_at", -1) >= 0),
            "all_found": sum(1 for r in runs if r["n_found"] == r["n_present"]),
            "time_s_mean": _mean([r["time_s"] for r in runs]),
            "time_s_max": float(np.max([r["time_s"] for r in runs])) if runs else float("nan"),
            "cpu_s_mean": _mean([r["timings"].get("total_cpu_s") for r in runs]),
            "iou_mean": _mean([r["silhouette_iou_mean"] for r in runs]),
            "chamfer_mm_mean": _mean([r["chamfer_mm"] for r in runs]),
            "volume_iou_mean": _mean([r["volume_iou"] for r in runs])}
    md = (f"\n## {MODE_PAPER}: the default paper configuration per scene, GT masks\n\n"
          "`DMTetConfig()`: 3-layer MLP f(v), oversized sphere start, envelope loss (eq. 2) with alpha 3 -> 1 "
          "linearly over half the steps (eq. 3), eikonal term (eq. 4), 5000 steps, no rescue, narrow-band "
          "evaluation (exact; `narrow_band`, `band_rings`, a full pass every `full_pass_every` steps). Quality vs the "
          "GT meshes/masks; IoU last 5 vs the supervision masks (Table I's metric). Time: wall time of the run "
          "(grid, masks, MLP fit, steps, split); CPU s: CPU time of the process over all its threads, robust to "
          "other processes on the cores (on an otherwise idle 2-core machine the wall time lies between CPU s / 2 "
          "and CPU s). Per-step columns are ms per step by stage: field = MLP on the band without gradients; full "
          "pass = MLP on every vertex (amortised); field grad = MLP with gradients on the vertices the loss "
          "reaches. Side thread (`DMTetConfig.side_thread`): a second thread computes eq. (4) and its gradient "
          "while the main thread renders (the eikonal column is then the main thread's wait for it) and half of "
          "each gradient-free evaluation (field, full pass) and of the field grad pass; same values as without "
          "it. Threads: torch threads of the loop; fit threads: of the MLP's start fit. The paper: 5k steps in "
          "177.3 s on a GPU. "
          "`reconstruct(mode=\"paper\")` runs the same and then "
          "raises when an object's silhouettes are not covered.\n\n"
          + bc.md_table(["scene", "steps", "collapsed at", "found/present", "IoU last 5", "IoU vs GT", "Chamfer mm",
                         "vol IoU", "wall s", "CPU s", "ms/step", "MLP fit s", "field ms", "full pass ms",
                         "marching tets ms", "render+loss ms", "eikonal ms", "backward+Adam ms", "field grad ms",
                         "band verts (mean)", "band misses", "threads", "side thread", "fit threads", "load start",
                         "load end"], rows, nd=2))
    return md, summ


def build_report(out: Path) -> None:
    """Combine the part files in ``out`` into reconstruction.json / .md / _curves.png."""
    fast, paper, table1, timing = (_load_part(out, p) for p in PARTS)
    doc: dict[str, Any] = {"parts": {}, "summary": {}, "chamfer_points": bc.CHAMFER_POINTS, "targets": TARGETS}
    md = ["# Reconstruction benchmark\n",
          "Generated by `benchmarks/reconstruction.py` from the part files "
          "`reconstruction_{fast,paper,table1,timing}.json` "
          "(which hold every per-scene/per-run number; this file's JSON twin is `reconstruction.json`). Captures: "
          "simulated scenes (`sim.world.build_world(scenario, seed)`), MuJoCo renders with GT instance masks and "
          "ideal depth, hemisphere of radius 0.5 m, 91.5 deg horizontal FOV. GT meshes: the objects' outer shells "
          "(sealed inner shells dropped).\n"]
    if fast:
        a = fast["context"]["args"]
        md.append(f"**What was run (fast part)**: scenes {', '.join(fast['scenes'])}; {a['views']} views, image scale "
                  f"{a['scale']} of 1280x720; grid {a['grid']}; refinement steps "
                  f"{a['refine_iters'] if a['refine_iters'] is not None else 'default (100)'}.\n")
        md.append(_ctx_block("Fast part", fast))
        m, s = _fast_md(fast, timing)
        md.append(m)
        doc["summary"].update(s)
        doc["parts"]["fast"] = fast
    if paper and paper["runs"]:
        m, s = _paper_md(paper)
        md.append(m)
        md.append(_ctx_block("Paper part", paper))
        doc["summary"]["paper"] = s
        doc["parts"]["paper"] = paper
    if table1 and table1["runs"]:
        md.append("\n")
        m, s = _table1(table1)
        md.append(m)
        md.append(_ctx_block("Table I part", table1))
        doc["summary"]["table1"] = s
        doc["parts"]["table1"] = {**table1, "runs": [{k: v for k, v in r.items() if k != "curves"}
                                                   for r in table1["runs"]]}
        which = _curves_png(table1, out / "reconstruction_curves.png")
        if which:
            md.append(f"\n![IoU and loss vs iteration](reconstruction_curves.png)\n\n`reconstruction_curves.png`: IoU "
                      f"and loss vs iteration on {which}, the Table I configurations without rescue (cf. the paper's "
                      "Fig. 5); a cross marks the step where a mesh vanished.\n")
    # timing table
    trows = []
    if fast:
        sg = doc["summary"].get("fast_gt", {})
        trows.append([MODE_FAST, "GT", sg.get("dmtet_ms_per_step_mean"), "-", "-",
                      sg.get("time_s_mean"),
                      "/".join(str(t) for t in sorted({s.get("threads", fast["context"]["threads"])
                                                       for s in fast["scenes"].values()})),
                      fast["context"]["contended"]])
    if timing and timing["scenes"]:
        ts = [v for v in timing["scenes"].values() if "time_s_min" in v]
        trows.append([f"{MODE_FAST}, timing pass ({len(ts)} scenes, min of "
                      f"{timing['context']['args']['timing_repeats']})",
                      "GT", _mean([v.get("dmtet_ms_per_step") for v in ts]), "-", "-",
                      _mean([v["time_s_min"] for v in ts]), timing["context"]["threads"],
                      timing["context"]["contended"]])
        doc["parts"]["timing"] = timing
    for r in (paper or {}).get("runs", []):
        trows.append([f"{MODE_PAPER}, {r['scenario']}, {r['config']['iterations']} steps", "GT",
                      r.get("ms_per_step"), "-", "-", r["time_s"], r["threads"], r["load_avg_1min_start"] > 1.5])
    for r in (table1 or {}).get("runs", []):
        if r.get("rescue") and not r.get("rescue_ran"):
            continue
        trows.append([f"{MODE_PAPER}, Table I {r['key']}, {r['steps_run']} of {r['config']['iterations']} steps",
                      r["supervision"], r["ms_per_step"], r["time_to_iou_0.90"]["time_s"],
                      r["time_to_iou_0.95"]["time_s"], r["time_s"], table1["context"]["threads"],
                      r["load_avg_1min_start"] > 1.5])
    extra = out / "reconstruction_timing_1thread_contended.json"
    if extra.exists():
        import json

        ex = json.loads(extra.read_text())
        ts = [v["time_s_min"] for v in ex["scenes"].values() if "time_s_min" in v]
        trows.append([f"{MODE_FAST}, earlier timing pass under load ({len(ts)} scenes, {extra.name})", "GT", "-",
                      "-", "-", _mean(ts), ex["context"]["threads"], ex["context"]["contended"]])
    if trows:
        hdr = ["run", "masks", "ms per DMTet step", "t to IoU 0.90 s", "t to IoU 0.95 s", "total s", "torch threads",
               "contended"]
        md.append("\n## Timing\n\n" + bc.md_table(hdr, trows, nd=1))
    bc.write_json(out / "reconstruction.json", doc)
    (out / "reconstruction.md").write_text("\n".join(md))
    log.info("wrote %s", out / "reconstruction.md")


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    if not a.report_only:
        bc.setup(a.threads)
        logging.getLogger("torm.reconstruction.dmtet").setLevel(logging.INFO)  # progress of the long DMTet runs
        args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
        for part in a.parts:
            ctx = bc.context(args)
            t = time.perf_counter()
            {"fast": part_fast, "paper": part_paper, "table1": part_table1, "timing": part_timing}[part](a, ctx)
            log.info("part %s done in %.0f s", part, time.perf_counter() - t)
    else:
        bc.setup()
    build_report(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
