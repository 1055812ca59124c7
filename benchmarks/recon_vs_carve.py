"""Reconstruction vs peers (issue #13): TORM-fast, TORM-paper (optional), voxel carves, Open3D, on the sim scenes.

Every scene (``--scenarios``, default rw1-8 and syn1-12), the same GT masks and cameras for every method, in
one process: the input views are all views but every ``--holdout-every``-th, which are held out and only
scored. Methods:

- ``TORM-fast``: ``reconstruct()`` with the default config (``mode_label`` names the design);
- ``TORM-paper (DMTet-Multi)`` with ``--paper`` (slow: minutes per scene on 2 cores; whatever paper mode the
  checked-out code runs);
- ``carve N^3``: the numpy survivors-only carve + marching cubes (:mod:`torm.reconstruction.carve`) at
  ``--carve-res`` (default 64 128 192 256) voxels along the longest box axis;
- ``open3d carve N^3``: Open3D's ``VoxelGrid.carve_silhouette`` (+ the same marching cubes) when ``open3d``
  is importable.

Scores: Chamfer (mm, dense samples on the union of the objects vs the GT outer shells), volume IoU (1 mm
voxels), silhouette IoU on the held-out views at the capture resolution, objects found, and wall time
(masks + cameras in, mesh out; for TORM the whole ``reconstruct()``: objects, checks, point clouds). Each
method runs once to warm up (numba, caches), then ``--repeats`` timed runs, interleaved across methods so
the machine's load hits all of them alike; the minimum is reported, all runs are recorded. "Best carve"
= the numpy carve resolution with the lowest Chamfer on that scene; TORM-fast "wins" a scene when its
time is <= the best carve's and its Chamfer is lower and its volume IoU higher.

Also per scene: a per-stage ablation of TORM-fast (``--ablation``), and the corrupted-mask case (noisy
segmenter, preset ``--corrupt-preset``) for TORM-fast and the carves. Part ``recorded``: the synthetic
recorded-frames captures of :mod:`torm.capture.synthetic_frames` (no table, soft masks, border cuts), default vs
a plain voxel hull on the same input views, held-out IoU and time.

Resumable: the JSON is rewritten after each scene and finished scenes are skipped (``--redo`` to rerun).
Time here: ~30 s per scene for the default parts on a quiet 2-core machine (about 10 minutes for all 20;
run it in chunks with ``--scenarios`` under the lock), plus minutes per scene with ``--paper``.

Run: ``python benchmarks/recon_vs_carve.py [--quick] [--scenarios rw1 rw4] [--paper] [--parts sim recorded]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

# numpy's BLAS single-threaded for every method (before numpy loads): a multithreaded BLAS made small
# (N, 3) x (3, 3) products 100-300x slower on the loaded 2-core machine (measured here)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
import numpy as np  # noqa: E402

from torm.errors import ReconstructionError  # noqa: E402
from torm.mesh.split import signed_volume, split_components  # noqa: E402
from torm.metrics import chamfer_distance_mm, volume_iou  # noqa: E402
from torm.reconstruction import ReconstructionConfig, reconstruct  # noqa: E402
from torm.reconstruction.api import mode_label  # noqa: E402
from torm.reconstruction.carve import carve_visual_hull, occupancy_mesh, voxel_grid_shape  # noqa: E402
from torm.reconstruction.raster import render_mask_fast  # noqa: E402
from torm.segmentation import make_segmenter  # noqa: E402
from torm.types import Capture, TriMesh  # noqa: E402

log = logging.getLogger("bench.recon_vs_carve")

ALL_SCENES = [f"rw{i}" for i in range(1, 9)] + [f"syn{i}" for i in range(1, 13)]
FAST = "TORM-fast"
#: Per-stage ablation of TORM-fast: (row name, config overrides). Built up from the previous default.
ABLATION: list[tuple[str, dict[str, Any]]] = [
    ("previous default: hull 48 cells, 15 % vote, 100 DMTet steps", {"refine_iters": 100, "vote_tolerance": 0.15}),
    ("hull 48 cells, 15 % vote (no refinement)", {"band_levels": 1, "fine_vote_views": "15%"}),
    ("+ strict after mask repair: 48 cells", {"band_levels": 1, "fine_vote_views": 0}),
    ("+ narrow band: 96 cells", {"band_levels": 2, "fine_vote_views": 0}),
    ("+ narrow band: 192 cells", {"band_levels": 3, "fine_vote_views": 0}),
    ("+ narrow band: 384 cells", {"band_levels": 4, "fine_vote_views": 0}),
    ("default without the mask repair", {"repair_coverage": 1e-9}),
    ("default (auto levels, tolerance chosen by the rim test)", {}),
]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tests: 1 scene, 15 views 320x180, carves 32/64, 1 repeat")
    p.add_argument("--out", type=Path, default=bc.RESULTS)
    p.add_argument("--cache", type=Path, default=bc.CAPTURE_CACHE)
    p.add_argument("--parts", nargs="+", default=["sim", "recorded"], choices=["sim", "recorded"])
    p.add_argument("--scenarios", nargs="+", default=None)
    p.add_argument("--cases", nargs="+", default=None, help="recorded-frames cases (default: all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=50)
    p.add_argument("--scale", type=float, default=0.5)
    p.add_argument("--holdout-every", type=int, default=5)
    p.add_argument("--carve-res", nargs="+", type=int, default=None, help="default 64 128 192 256")
    p.add_argument("--open3d-res", nargs="*", type=int, default=None, help="default 64 128 (none: skip)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--paper", action="store_true", help="also run TORM-paper (slow)")
    p.add_argument("--paper-only", action="store_true",
                   help="add TORM-paper to the scenes already in the JSON (skipping those that have it), nothing else")
    p.add_argument("--ablation-scenes", nargs="*", default=None,
                   help="scenes that also get the per-stage ablation and the corrupted-mask case")
    p.add_argument("--corrupt-preset", default="paper", help="noisy-segmenter preset of the corrupted case ('' = skip)")
    p.add_argument("--threads", type=int, default=bc.THREADS)
    p.add_argument("--redo", action="store_true", help="rerun scenes already in the result file")
    p.add_argument("--report-only", action="store_true")
    a = p.parse_args(argv)
    if a.quick:
        a.scenarios = a.scenarios or ["rw3"]
        a.views, a.scale, a.repeats = 15, 0.25, 1
        a.carve_res = a.carve_res or [32, 64]
        a.open3d_res = [32] if a.open3d_res is None else a.open3d_res
        a.ablation_scenes = a.scenarios if a.ablation_scenes is None else a.ablation_scenes
    a.scenarios = a.scenarios or ALL_SCENES
    a.carve_res = a.carve_res or [64, 128, 192, 256]
    a.open3d_res = [64, 128] if a.open3d_res is None else a.open3d_res
    if a.ablation_scenes is None:
        a.ablation_scenes = ["rw1", "rw4", "rw8", "syn5", "syn12"]
    return a


# ----------------------------------------------------------------------------------------------------------
# Methods: each maps an input capture to a list of object meshes
# ----------------------------------------------------------------------------------------------------------
def _objects(mesh: TriMesh) -> list[TriMesh]:
    """Components kept the way ``reconstruct()`` keeps them (>= 20 faces, >= 1e-7 m^3, outward)."""
    if mesh.is_empty:
        return []
    keep = split_components(mesh.verts_vx3, mesh.faces_fx3, min_faces=20, min_volume=1e-7)
    return [m for m in keep if signed_volume(m.verts_vx3, m.faces_fx3) > 0]


def _bf16_label(dm: dict[str, Any] | None) -> str:
    """``DMTetConfig.bf16`` as it ran: the band's rows away from the surface, the MLP's start fit ("-": not recorded,
    runs before 2026-12-04 22:00, all float32 rows and fit)."""
    if not dm or dm.get("bf16") is None:
        return "-"
    return f"{'yes' if dm['bf16'] else 'no'}, {'yes' if dm.get('fit_bf16') else 'no'}"


def torm_method(cfg: ReconstructionConfig) -> Callable[[Capture], tuple[list[TriMesh], dict[str, Any]]]:
    def run(cap: Capture) -> tuple[list[TriMesh], dict[str, Any]]:
        rec = reconstruct(cap, cfg)
        keep = ("band_levels", "grid_cells", "vote_views", "repaired_views", "rejected_objects", "unexplained_views")
        extra: dict[str, Any] = {}
        dm = rec.info.get("dmtet_timings")
        if cfg.mode == "paper" and dm:  # what ran: the loop's threads, the side thread, bfloat16 (band rows, fit)
            extra["dmtet"] = {k: dm.get(k) for k in ("ms_per_step", "mlp_fit_s", "steps_run", "torch_threads",
                                                     "side_thread", "bf16", "fit_bf16")}
        return list(rec.object_meshes), {"timings": rec.timings, **{k: rec.info.get(k) for k in keep}, **extra}
    return run


def carve_method(res: int) -> Callable[[Capture], tuple[list[TriMesh], dict[str, Any]]]:
    def run(cap: Capture) -> tuple[list[TriMesh], dict[str, Any]]:
        r = carve_visual_hull(cap.masks() > 0, cap.Ks(), cap.poses(), cap.workspace_bounds, res,
                              table_z=cap.table_height)
        return _objects(r.mesh), {"voxels": list(r.occupancy.shape), "pitch_mm": 1e3 * r.pitch}
    return run


def auto_box(cap: Capture) -> np.ndarray:
    """(2, 3) m: the automatic box of a capture without one (silhouette cones, coarse hull, margin)."""
    from torm.reconstruction.bounds import auto_bounds

    return auto_bounds(cap.masks() > 0, cap.Ks(), cap.poses())


def auto_box_hull(res: int) -> Callable[[Capture], tuple[list[TriMesh], dict[str, Any]]]:
    """A plain numpy voxel hull at ``res`` over the automatic box, no table (what a user would write)."""
    def run(c: Capture) -> tuple[list[TriMesh], dict[str, Any]]:
        b = auto_box(c)
        r = carve_visual_hull(c.masks() > 0, c.Ks(), c.poses(), b, res, table_z=None)
        return _objects(r.mesh), {"bounds": b.tolist()}
    return run


def open3d_method(res: int, box: Callable[[Capture], np.ndarray] | None = None
                  ) -> Callable[[Capture], tuple[list[TriMesh], dict[str, Any]]] | None:
    """Open3D's dense VoxelGrid carved by every silhouette (voxels outside an image are kept), or None; over the
    capture's workspace box, or ``box(capture)``."""
    try:
        import open3d as o3d
    except ImportError:
        return None

    def run(cap: Capture) -> tuple[list[TriMesh], dict[str, Any]]:
        b = box(cap) if box is not None else cap.workspace_bounds
        shape, pitch = voxel_grid_shape(b, res)
        ext = np.asarray(shape) * pitch
        vg = o3d.geometry.VoxelGrid.create_dense(b[0], np.zeros(3), pitch, *ext)
        H, W = cap.image_size
        for v in cap.views:
            cam = o3d.camera.PinholeCameraParameters()
            cam.intrinsic = o3d.camera.PinholeCameraIntrinsic(W, H, v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2])
            cam.extrinsic = v.T_cam_world
            sil = o3d.geometry.Image((v.mask > 0).astype(np.float32))
            vg.carve_silhouette(sil, cam, keep_voxels_outside_image=True)
        occ = np.zeros(shape, dtype=bool)
        idx = np.array([x.grid_index for x in vg.get_voxels()], dtype=np.int64).reshape(-1, 3)
        idx = idx[np.all((idx >= 0) & (idx < shape), axis=1)]
        occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        if cap.table_height is not None:  # same table rule as the numpy carve: no voxel centre below it
            zc = b[0, 2] + (np.arange(shape[2]) + 0.5) * pitch
            occ[:, :, zc < cap.table_height] = False
        return _objects(occupancy_mesh(occ, b[0], pitch)), {"voxels": list(shape), "pitch_mm": 1e3 * pitch,
                                                           "open3d": o3d.__version__}
    return run


# ----------------------------------------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------------------------------------
def score(objects: list[TriMesh], gt_meshes: list[TriMesh], held: Capture) -> dict[str, Any]:
    """Chamfer (mm), volume IoU, held-out silhouette IoU (capture resolution) and objects found."""
    from torm.metrics import match_meshes

    if not objects:
        return {"n_found": 0, "chamfer_mm": None, "volume_iou": 0.0, "heldout_iou_mean": 0.0, "heldout_iou_min": 0.0}
    union = bc.concat(objects)
    H, W = held.image_size
    ious = []
    for v in held.views:
        r = render_mask_fast(union.verts_vx3, union.faces_fx3, v.K, v.T_cam_world, H, W)
        g = v.mask > 0
        u = (r | g).sum()
        ious.append(float((r & g).sum() / u) if u else 1.0)
    from torm.mesh.sample import sample_surface

    pa = sample_surface(union, bc.CHAMFER_POINTS, np.random.default_rng(1)).points_nx3
    pb = sample_surface(bc.concat(gt_meshes), bc.CHAMFER_POINTS, np.random.default_rng(2)).points_nx3
    m = match_meshes(objects, gt_meshes)
    vi = volume_iou(objects, gt_meshes)
    return {"n_found": m["n_found"], "n_spurious": m["n_spurious"], "n_components": len(objects),
            "chamfer_mm": chamfer_distance_mm(pa, pb), "volume_iou": vi["iou"], "volume_ratio": vi["volume_ratio"],
            "heldout_iou_mean": float(np.mean(ious)), "heldout_iou_min": float(np.min(ious))}


def split_views(cap: Capture, every: int) -> tuple[Capture, Capture]:
    """(input views, held-out views): every ``every``-th view (0, every, 2 every, ...) is held out."""
    held = [i for i in range(len(cap)) if i % every == 0]
    return cap.subset([i for i in range(len(cap)) if i % every]), cap.subset(held)


def run_methods(methods: dict[str, Callable], cap: Capture, held: Capture, gt: list[TriMesh], repeats: int,
                timed: set[str]) -> dict[str, dict[str, Any]]:
    """Warm up every method, time the ``timed`` ones ``repeats`` times interleaved, score every one once."""
    out: dict[str, dict[str, Any]] = {}
    results: dict[str, tuple[list[TriMesh], dict[str, Any]]] = {}
    for name, fn in methods.items():
        t = time.perf_counter()
        try:
            results[name] = fn(cap)
        except ReconstructionError as exc:
            out[name] = {"error": str(exc)}
            log.warning("%s failed: %s", name, exc)
            continue
        out[name] = {"times_s": [time.perf_counter() - t], "warmup": True}
    for _ in range(repeats):
        for name in (n for n in methods if n in timed and n in results):
            t = time.perf_counter()
            results[name] = methods[name](cap)
            out[name].setdefault("timed_s", []).append(time.perf_counter() - t)
    for name, (objs, extra) in results.items():
        ts = out[name].get("timed_s") or out[name]["times_s"]
        out[name].update(time_s=float(min(ts)), **extra, **score(objs, gt, held))
    return out


def _resolve(kw: dict[str, Any], n_views: int) -> dict[str, Any]:
    """Ablation overrides with "15%" view counts turned into views of this capture."""
    return {k: (round(0.15 * n_views) if v == "15%" else v) for k, v in kw.items()}


def corrupted_capture(cap: Capture, preset: str, seed: int) -> tuple[Capture, dict[str, Any]]:
    res = make_segmenter("noisy", {"preset": preset, "seed": seed}).segment(cap)
    q = res.info["quality"]
    return cap.with_masks(res.masks_vxhxw), {"preset": preset, "input_iou_mean": q["silhouette_iou_mean"]}


PAPER = mode_label(ReconstructionConfig(mode="paper"))


def paper_methods(cap: Capture, held: Capture, gt: list[TriMesh]) -> dict[str, dict[str, Any]]:
    """TORM-paper (``reconstruct(mode="paper")``, default config) scored like the others; one untimed run (its
    time is minutes, so a warm-up repeat would not change it)."""
    t_load = os.getloadavg()[0]
    out = run_methods({PAPER: torm_method(ReconstructionConfig(mode="paper"))}, cap, held, gt, 0, set())
    out[PAPER]["load_avg_1min"] = t_load
    return out


def sim_scene_paper_only(a: argparse.Namespace, name: str, row: dict[str, Any]) -> None:
    """Add TORM-paper to a scene row measured earlier (same scene, views and held-out split)."""
    scene = bc.get_scene(name, a.seed, a.views, a.scale, a.cache)
    cap, held = split_views(scene.capture, a.holdout_every)
    if len(cap) != row["n_input_views"] or len(held) != row["n_heldout_views"]:
        raise SystemExit(f"{name}: the split ({len(cap)}/{len(held)} views) differs from the stored row's "
                         f"({row['n_input_views']}/{row['n_heldout_views']}); rerun the scene with --redo --paper")
    row["methods"].update(paper_methods(cap, held, scene.gt_meshes))


def sim_scene(a: argparse.Namespace, name: str) -> dict[str, Any]:
    scene = bc.get_scene(name, a.seed, a.views, a.scale, a.cache)
    cap, held = split_views(scene.capture, a.holdout_every)
    fast_cfg = ReconstructionConfig()
    methods: dict[str, Callable] = {FAST: torm_method(fast_cfg)}
    for r in a.carve_res:
        methods[f"carve {r}^3"] = carve_method(r)
    for r in a.open3d_res:
        m = open3d_method(r)
        if m is not None:
            methods[f"open3d carve {r}^3"] = m
    row: dict[str, Any] = {"scenario": name, "seed": a.seed, "n_objects": len(scene.gt_meshes),
                           "n_input_views": len(cap), "n_heldout_views": len(held),
                           "image_size": list(cap.image_size), "load_avg_1min": os.getloadavg()[0],
                           "fast_label": mode_label(fast_cfg)}
    row["methods"] = run_methods(methods, cap, held, scene.gt_meshes, a.repeats, set(methods))
    if a.paper:
        row["methods"].update(paper_methods(cap, held, scene.gt_meshes))
    if name not in a.ablation_scenes:
        row["load_avg_1min_end"] = os.getloadavg()[0]
        return row
    abl = {label: torm_method(ReconstructionConfig(**_resolve(kw, len(cap)))) for label, kw in ABLATION}
    row["ablation"] = run_methods(abl, cap, held, scene.gt_meshes, 0, set())
    if a.corrupt_preset:
        ccap, q = corrupted_capture(cap, a.corrupt_preset, a.seed)
        cm = {FAST: torm_method(fast_cfg), "previous default": torm_method(ReconstructionConfig(**ABLATION[0][1])),
              "default without the mask repair": torm_method(ReconstructionConfig(**ABLATION[-2][1])),
              "strict narrow band 192 (no tolerance)": torm_method(ReconstructionConfig(fine_vote_views=0))}
        for r in a.carve_res[-2:]:
            cm[f"carve {r}^3"] = carve_method(r)
        row["corrupted"] = {**q, "methods": run_methods(cm, ccap, held, scene.gt_meshes, 0, set())}
    row["load_avg_1min_end"] = os.getloadavg()[0]
    return row


# ----------------------------------------------------------------------------------------------------------
# Recorded-frames cases (synthetic, known meshes)
# ----------------------------------------------------------------------------------------------------------
def recorded_case(a: argparse.Namespace, case: str) -> dict[str, Any]:
    from torm.capture.io import load_capture
    from torm.capture.synthetic_frames import RECORDED_CASES, write_recorded_capture

    folder = a.cache / f"recorded_{case}"
    gt = write_recorded_capture(folder, case)
    cap_all = load_capture(folder)
    cap, held = split_views(cap_all, a.holdout_every if len(cap_all) >= 10 else 4)
    cfg = ReconstructionConfig()
    cap_none = cap  # the default reads bounds/table from the capture (none: automatic, no table)
    # the carves get the same automatic box (a voxel carve needs one) and no table

    methods = {FAST: torm_method(cfg), **{f"carve {r}^3": auto_box_hull(r) for r in a.carve_res}}
    res = run_methods(methods, cap_none, held, gt, a.repeats, set(methods))
    best = _best_carve(res)
    f = res.get(FAST, {})
    wins = bool(best and f.get("chamfer_mm") is not None and f["time_s"] <= res[best]["time_s"]
                and f["chamfer_mm"] < res[best]["chamfer_mm"] and f["volume_iou"] > res[best]["volume_iou"])
    return {"case": case, "description": RECORDED_CASES[case]["description"], "n_input_views": len(cap),
            "n_heldout_views": len(held), "image_size": list(cap.image_size), "fast_label": mode_label(cfg),
            "methods": res, "best_carve": best, "fast_wins": wins}


# ----------------------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------------------
def _best_carve(methods: dict[str, Any]) -> str | None:
    carves = [(m["chamfer_mm"], -m["volume_iou"], k) for k, m in methods.items()
              if k.startswith("carve ") and m.get("chamfer_mm") is not None]
    return min(carves)[2] if carves else None


def summarise(doc: dict[str, Any]) -> dict[str, Any]:
    wins, rows = 0, 0
    ratios_t, ratios_cd = [], []
    for s in doc["scenes"].values():
        m = s["methods"]
        best = _best_carve(m)
        f = m.get(FAST, {})
        if best is None or f.get("chamfer_mm") is None:
            continue
        c = m[best]
        s["best_carve"] = best
        s["fast_wins"] = bool(f["time_s"] <= c["time_s"] and f["chamfer_mm"] < c["chamfer_mm"]
                              and f["volume_iou"] > c["volume_iou"])
        wins += s["fast_wins"]
        rows += 1
        ratios_t.append(f["time_s"] / c["time_s"])
        ratios_cd.append(f["chamfer_mm"] / c["chamfer_mm"])
    return {"scenes": rows, "fast_wins": wins, "time_ratio_mean": float(np.mean(ratios_t)) if ratios_t else None,
            "time_ratio_max": float(np.max(ratios_t)) if ratios_t else None,
            "chamfer_ratio_mean": float(np.mean(ratios_cd)) if ratios_cd else None}


def _mean(xs: list[Any]) -> float | None:
    v = [float(x) for x in xs if x is not None]
    return float(np.mean(v)) if v else None


def report(doc: dict[str, Any], path_md: Path) -> None:
    summ = doc.get("summary", {})
    ctx = doc["context"]
    md = ["# Reconstruction vs voxel carving (issue #13)\n",
          "Generated by `benchmarks/recon_vs_carve.py`; JSON twin `recon_vs_carve.json`. Same GT masks, cameras "
          "and box for every method, in one process. Input views: all but every "
          f"{ctx['args']['holdout_every']}th view, which are held out and only scored. Chamfer: "
          f"{bc.CHAMFER_POINTS} samples per side (union of objects vs GT outer shells). Volume IoU: 1 mm voxels. "
          "Held-out IoU: the union of the objects rendered in the held-out views at the capture resolution vs the "
          "GT masks. Time: minimum over the timed runs after a warm-up, methods interleaved; TORM-fast's time is "
          "the whole `reconstruct()` (objects, checks, point clouds), a carve's is masks -> mesh. Best carve: the "
          "numpy carve resolution with the lowest Chamfer on the scene. numpy's BLAS and OpenMP run one thread "
          "(OPENBLAS_NUM_THREADS=OMP_NUM_THREADS=1) for every method; torch uses `threads` below.\n",
          bc.context_md(ctx)]
    if doc.get("scenes"):
        first = next(iter(doc["scenes"].values()))
        md.append(f"\n## Sim scenes: {first['fast_label']} vs the best carve\n\n"
                  f"TORM-fast wins {summ.get('fast_wins')}/{summ.get('scenes')} scenes (time <= best carve's, lower "
                  f"Chamfer, higher volume IoU); time ratio TORM-fast / best carve: mean "
                  f"{bc.fmt(summ.get('time_ratio_mean'), 2)}, max {bc.fmt(summ.get('time_ratio_max'), 2)}; Chamfer "
                  f"ratio mean {bc.fmt(summ.get('chamfer_ratio_mean'), 3)}.\n")
        rows = []
        for key, s in doc["scenes"].items():
            m, best = s["methods"], s.get("best_carve")
            f = m.get(FAST, {})
            c = m.get(best, {}) if best else {}
            rows.append([key, f.get("chamfer_mm"), f.get("volume_iou"), f.get("heldout_iou_mean"), f.get("time_s"),
                         best, c.get("chamfer_mm"), c.get("volume_iou"), c.get("heldout_iou_mean"), c.get("time_s"),
                         (f["time_s"] / c["time_s"]) if c and "time_s" in f else None,
                         "yes" if s.get("fast_wins") else "**no**", s.get("load_avg_1min")])
        md.append(bc.md_table(["scene", "TORM-fast Chamfer mm", "vol IoU", "held-out IoU", "time s", "best carve",
                               "carve Chamfer mm", "vol IoU", "held-out IoU", "time s", "time ratio", "win", "load"],
                              rows))
        prow = []
        for key, s in doc["scenes"].items():
            p, best = s["methods"].get(PAPER), s.get("best_carve")
            if p is None:
                continue
            c = s["methods"].get(best, {}) if best else {}
            f = s["methods"].get(FAST, {})
            prow.append([key, p.get("error", "")[:60] or p.get("chamfer_mm"), p.get("volume_iou"),
                         p.get("heldout_iou_mean"), f"{p.get('n_found', 0)}/{s['n_objects']}", p.get("time_s"),
                         f.get("chamfer_mm"), f.get("time_s"), c.get("chamfer_mm"), c.get("time_s"),
                         p.get("load_avg_1min"), _bf16_label(p.get("dmtet"))])
        if prow:
            md.append(f"\n## {PAPER} (`reconstruct(mode=\"paper\")`, default config: 5000 steps, sphere start, "
                      "no rescue) beside TORM-fast and the best carve\n\nOne untimed run per scene (its time includes "
                      "the MLP fit, the 5000 steps, the split, checks and point clouds); same input and held-out views "
                      "as the others. Run later than them (`--paper-only`), on the code and machine in `more_contexts`."
                      "\n\n" + bc.md_table(["scene", "Chamfer mm (or error)", "vol IoU", "held-out IoU", "found",
                                           "time s", "TORM-fast Chamfer mm", "TORM-fast s", "best carve Chamfer mm",
                                           "best carve s", "load", "bfloat16 (band, fit)"], prow))
        names = list(next(iter(doc["scenes"].values()))["methods"])
        for nm in {k for s in doc["scenes"].values() for k in s["methods"]} - set(names):
            names.append(nm)
        arows = []
        for nm in names:
            ms = [s["methods"][nm] for s in doc["scenes"].values() if nm in s["methods"]]
            ok = [x for x in ms if "error" not in x]
            label = first["fast_label"] if nm == FAST else nm
            arows.append([label, len(ok), _mean([x.get("chamfer_mm") for x in ok]),
                          _mean([x.get("volume_iou") for x in ok]), _mean([x.get("heldout_iou_mean") for x in ok]),
                          _mean([x.get("time_s") for x in ok]), sum(x.get("n_found", 0) for x in ok),
                          sum(s["n_objects"] for s in doc["scenes"].values() if nm in s["methods"])])
        md.append("\nEvery method, mean over the scenes:\n\n" + bc.md_table(
            ["method", "scenes", "Chamfer mm", "vol IoU", "held-out IoU", "time s", "objects found", "present"],
            arows))
        if any("ablation" in s for s in doc["scenes"].values()):
            lab = [lb for lb, _ in ABLATION]
            brows = []
            for lb in lab:
                ms = [s["ablation"][lb] for s in doc["scenes"].values() if lb in s.get("ablation", {})]
                ok = [x for x in ms if "error" not in x]
                brows.append([lb, len(ok), _mean([x.get("chamfer_mm") for x in ok]),
                              _mean([x.get("volume_iou") for x in ok]), _mean([x.get("heldout_iou_mean") for x in ok]),
                              _mean([x.get("time_s") for x in ok]),
                              _mean([x.get("timings", {}).get("narrow_band") for x in ok])])
            md.append("\n## Per-stage ablation of TORM-fast (GT masks, mean over the scenes; time of one run, "
                      "not the timed minimum)\n\n" + bc.md_table(
                          ["configuration", "scenes", "Chamfer mm", "vol IoU", "held-out IoU", "time s",
                           "narrow band s"], brows))
        if any("corrupted" in s for s in doc["scenes"].values()):
            cn = list(next(s for s in doc["scenes"].values() if "corrupted" in s)["corrupted"]["methods"])
            crows = []
            for nm in cn:
                ms = [s["corrupted"]["methods"][nm] for s in doc["scenes"].values() if "corrupted" in s]
                ok = [x for x in ms if "error" not in x]
                crows.append([nm, len(ms) - len(ok), _mean([x.get("chamfer_mm") for x in ok]),
                              _mean([x.get("volume_iou") for x in ok]), _mean([x.get("heldout_iou_mean") for x in ok]),
                              sum(x.get("n_found", 0) for x in ok),
                              sum(s["n_objects"] for s in doc["scenes"].values() if "corrupted" in s)])
            pre = next(s for s in doc["scenes"].values() if "corrupted" in s)["corrupted"]["preset"]
            md.append(f"\n## Corrupted masks (noisy segmenter, preset `{pre}`; scored against the GT)\n\n"
                      "Failed: `reconstruct()` raised or nothing survived the carve.\n\n" + bc.md_table(
                          ["method", "failed", "Chamfer mm", "vol IoU", "held-out IoU (vs GT)", "objects found",
                           "present"], crows))
        per = []
        for key, s in doc["scenes"].items():
            for nm, x in s["methods"].items():
                per.append([key, first["fast_label"] if nm == FAST else nm, x.get("chamfer_mm"), x.get("volume_iou"),
                            x.get("heldout_iou_mean"), x.get("time_s"), x.get("n_found"), x.get("error", "")[:60]])
        md.append("\nPer scene and method:\n\n" + bc.md_table(
            ["scene", "method", "Chamfer mm", "vol IoU", "held-out IoU", "time s", "found", "error"], per))
    if doc.get("recorded"):
        rrows = []
        for case, r in doc["recorded"].items():
            for nm, x in r["methods"].items():
                best = " (best carve)" if nm == r.get("best_carve") else ""
                nm = r.get("fast_label", nm) if nm == FAST else nm + best
                rrows.append([case, r["n_input_views"], r["n_heldout_views"], nm, x.get("heldout_iou_mean"),
                              x.get("heldout_iou_min"), x.get("chamfer_mm"), x.get("volume_iou"), x.get("time_s"),
                              x.get("n_found"), x.get("error", "")[:60]])
        nw = sum(bool(r.get("fast_wins")) for r in doc["recorded"].values())
        md.append("\n## Recorded-frames cases (synthetic, `torm.capture.synthetic_frames`; issue #17)\n\n"
                  f"Default settings (box and table from the capture: none, so automatic box, no table) vs numpy "
                  f"voxel hulls over the same automatic box, same input views. TORM-fast wins {nw}/"
                  f"{len(doc['recorded'])} cases (time <= best carve's, lower Chamfer, higher volume IoU).\n\n"
                  + "".join(f"- `{c}`: {r['description']}\n" for c, r in doc["recorded"].items()) + "\n"
                  + bc.md_table(["case", "input views", "held-out views", "method", "held-out IoU mean", "min",
                                 "Chamfer mm", "vol IoU", "time s", "found", "error"], rrows))
    path_md.write_text("\n".join(md))


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / "recon_vs_carve.json"
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    bc.setup(a.threads)
    doc: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    doc.setdefault("scenes", {})
    doc.setdefault("recorded", {})
    ctx = bc.context(args)
    if not a.report_only:
        if "context" in doc:
            doc.setdefault("more_contexts", []).append(ctx)
        else:
            doc["context"] = ctx
        if "sim" in a.parts:
            for name in a.scenarios:
                key = f"{name}_s{a.seed}"
                if a.paper_only:
                    row = doc["scenes"].get(key)
                    if row is None:
                        log.warning("%s: not measured yet; run it without --paper-only first", key)
                    elif PAPER not in row["methods"] or a.redo:
                        sim_scene_paper_only(a, name, row)
                        bc.write_json(path, doc)
                        p = row["methods"][PAPER]
                        log.info("%s: %s %s mm, %s s", key, PAPER, bc.fmt(p.get("chamfer_mm")), bc.fmt(p.get("time_s")))
                    continue
                if key in doc["scenes"] and not a.redo:
                    continue
                t = time.perf_counter()
                doc["scenes"][key] = sim_scene(a, name)
                doc["summary"] = summarise(doc)
                bc.write_json(path, doc)
                f = doc["scenes"][key]["methods"][FAST]
                log.info("%s done in %.0f s: TORM-fast %s mm %.2f s; best carve %s", key, time.perf_counter() - t,
                         bc.fmt(f.get("chamfer_mm")), f.get("time_s", np.nan), doc["scenes"][key].get("best_carve"))
        if "recorded" in a.parts:
            from torm.capture.synthetic_frames import RECORDED_CASES

            for case in a.cases or RECORDED_CASES:
                if case in doc["recorded"] and not a.redo:
                    continue
                doc["recorded"][case] = recorded_case(a, case)
                bc.write_json(path, doc)
    doc["summary"] = summarise(doc)
    bc.write_json(path, doc)
    report(doc, a.out / "recon_vs_carve.md")
    log.info("wrote %s", a.out / "recon_vs_carve.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
