"""Reconstruction from captures degraded the way real recorded captures are (issue 38), defaults vs voxel hulls.

A user's real capture (COLMAP cameras, SIMPLE_RADIAL k1 = 0.0325, hand-made masks, 2048x1534, 8 input views) gave
held-out silhouette IoU 0.922 with torm's defaults against 0.943 for a plain 128^3 voxel hull. This benchmark
rebuilds that situation on synthetic objects whose truth is known: the geometry of the recorded-frames cases
(:mod:`torm.capture.synthetic_frames`: ``glass10``, a capsule on a stand; ``bottles20``, three objects side by side;
``ring8``, a torus half below z = 0 and a box cut by the border), cameras on the same spiral at high resolution,
and these degradations (:mod:`torm.capture.degrade`), alone and together:

- ``pose``: each input camera's pose perturbed so that the scene's surface points move by 0.3-1.0 px RMS (uniform
  per view): the mean reprojection error COLMAP reports for such captures (the range the issue gives);
- ``lens``: the images recorded through SIMPLE_RADIAL k1 = 0.0325 (the real capture's COLMAP solve), declared in
  transforms.json, so the loader undoes it (what a user with a COLMAP import gets);
- ``masks``: hand-drawn polygon masks (outline simplified at ``--simplify-px`` and each vertex off by
  ``--vertex-sigma-px``, anti-aliased soft edges). No measured source for annotators' vertex error was found; the
  defaults (2 px, 1 px at 2048 px width) are an assumption stated here, and the input-mask IoU they cause is in
  every row;
- ``views``: 8, 10 or 12 input views (10 in the single-degradation cases); ``exact50``: 50 exact views;
- stress cases, beyond those ranges and outside the targets (:data:`STRESS`): twice the pose error, a hand twice as
  coarse, and masks drawn ``--bias-px`` (1.5 px at 2048 px) outside (``halo``) or inside (``shrink``) the edge, the
  systematic error of a soft mask thresholded too low or too high.

Scored on held-out views with the **exact** cameras and masks (truth, not the degraded inputs): silhouette IoU at
the capture resolution, Chamfer (mm) and volume IoU against the true meshes. Methods: ``default``
(``ReconstructionConfig()``), a grid of tuned settings (``TUNED``), a plain numpy voxel hull at 128^3 over the
automatic box (what a user would write) and Open3D's ``VoxelGrid.carve_silhouette`` at 128^3 over the same box.

Targets (issue 38): in every degraded case the defaults >= the 128^3 voxel hull on held-out IoU, and >= 0.95 of
the best tuned setting.

Resumable: the JSON is rewritten after every case; finished cases are skipped (``--redo`` reruns them).
Run: ``python benchmarks/recon_degraded.py [--quick] [--shapes glass10] [--cases real10 pose10]``.
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

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as bc  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from recon_vs_carve import auto_box, auto_box_hull, open3d_method, score, torm_method  # noqa: E402

from torm.capture.degrade import hand_drawn_mask, perturb_poses  # noqa: E402
from torm.capture.io import load_capture  # noqa: E402
from torm.capture.lens import Lens  # noqa: E402
from torm.capture.synthetic_frames import RECORDED_CASES, case_cameras, case_meshes  # noqa: E402
from torm.errors import ReconstructionError  # noqa: E402
from torm.geometry import cv_to_gl  # noqa: E402
from torm.mesh.sample import sample_surface  # noqa: E402
from torm.reconstruction import ReconstructionConfig  # noqa: E402
from torm.reconstruction.raster import render_mask_fast  # noqa: E402
from torm.types import CameraView, Capture, TriMesh  # noqa: E402

log = logging.getLogger("recon_degraded")
NAME = "recon_degraded"
#: the real capture's lens (issue 38: its COLMAP solve)
REAL_LENS = Lens("SIMPLE_RADIAL", (("k1", 0.0325),))
#: COLMAP's usual mean reprojection error on object captures (px), issue 38
POSE_PX = (0.3, 1.0)
#: case -> (input views, degradations)
CASES: dict[str, tuple[int, tuple[str, ...]]] = {
    "exact50": (50, ()), "exact10": (10, ()), "pose10": (10, ("pose",)), "lens10": (10, ("lens",)),
    "masks10": (10, ("masks",)), "real8": (8, ("pose", "lens", "masks")), "real10": (10, ("pose", "lens", "masks")),
    "real12": (12, ("pose", "lens", "masks")),
    # stress: beyond the ranges above, to see where the defaults start to lose (not part of the targets)
    "pose_x2_10": (10, ("pose_x2",)), "masks_x2_10": (10, ("masks_x2",)), "halo10": (10, ("masks", "halo")),
    "shrink10": (10, ("masks", "shrink")), "stress10": (10, ("pose_x2", "lens", "masks_x2")),
}
#: degradations beyond the issue's ranges: twice the pose error, a hand twice as coarse, masks drawn
#: ``--bias-px`` outside (halo) or inside (shrink) the true edge
STRESS = ("pose_x2", "masks_x2", "halo", "shrink")
#: tuned settings tried beside the defaults (ReconstructionConfig overrides)
TUNED: dict[str, dict[str, Any]] = {
    "strict band (fine_vote_views=0)": {"fine_vote_views": 0},
    "band tolerates 1 view": {"fine_vote_views": 1},
    "band tolerates 2 views": {"fine_vote_views": 2},
    "consensus tolerates 1 view": {"vote_views": 1},
    "coarser cells (cell_px=3)": {"cell_px": 3.0},
    "no facet rule (facet_frac=0)": {"facet_frac": 0.0},
    "facet_frac=0.6": {"facet_frac": 0.6},
    "min_band_res=48": {"min_band_res": 48},
    "cut views skipped": {"skip_cut_views": True},
}
HULL = "voxel hull 128^3"
OPEN3D = "open3d carve 128^3"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tests: glass10, exact10 + real10, 480x360, 3 tuned")
    p.add_argument("--shapes", nargs="+", default=["glass10", "bottles20", "ring8"], choices=sorted(RECORDED_CASES))
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--hw", nargs=2, type=int, default=[1536, 2048], metavar=("H", "W"))
    p.add_argument("--heldout", type=int, default=6, help="held-out views per case (exact cameras and masks)")
    p.add_argument("--simplify-px", type=float, default=2.0, help="hand-drawn masks: polygon tolerance at 2048 px")
    p.add_argument("--vertex-sigma-px", type=float, default=1.0, help="hand-drawn masks: vertex error at 2048 px")
    p.add_argument("--bias-px", type=float, default=1.5, help="halo / shrink stress: edge offset at 2048 px")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=bc.THREADS)
    p.add_argument("--out", type=Path, default=bc.RESULTS)
    p.add_argument("--cache", type=Path, default=bc.ROOT / "runs" / "recon_degraded")
    p.add_argument("--name", default=NAME)
    p.add_argument("--redo", action="store_true")
    p.add_argument("--report-only", action="store_true")
    a = p.parse_args(argv)
    if a.quick:
        a.shapes, a.cases, a.hw, a.heldout = ["glass10"], ["exact10", "real10"], [360, 480], 3
    return a


# ----------------------------------------------------------------------------------------------------------
# Captures
# ----------------------------------------------------------------------------------------------------------
def _spiral(shape: str, n_in: int, n_held: int, hw: tuple[int, int]) -> tuple[np.ndarray, list, list]:
    """K and (input poses, held-out poses): one spiral of n_in + n_held views, every k-th held out."""
    K, poses = case_cameras(shape, n_in + n_held, hw)
    step = (n_in + n_held) / n_held
    held_idx = {int(step * j + step / 2) for j in range(n_held)}
    return K, [p for i, p in enumerate(poses) if i not in held_idx], [p for i, p in enumerate(poses) if i in held_idx]


def _silhouette(meshes: list[TriMesh], K: np.ndarray, T: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    H, W = hw
    T_cw = np.linalg.inv(T)
    out = np.zeros((H, W), bool)
    for m in meshes:
        out |= render_mask_fast(m.verts_vx3, m.faces_fx3, K, T_cw, H, W)
    return out


def build_case(a: argparse.Namespace, shape: str, case: str) -> tuple[Capture, Capture, list[TriMesh], dict]:
    """(degraded input capture as loaded from its folder, exact held-out capture, true meshes, what was done)."""
    n_in, degs = CASES[case]
    hw = (int(a.hw[0]), int(a.hw[1]))
    rng = np.random.default_rng([a.seed, list(RECORDED_CASES).index(shape), list(CASES).index(case)])
    meshes = case_meshes(shape)
    K, poses, held_poses = _spiral(shape, n_in, a.heldout, hw)
    info: dict[str, Any] = {"n_input_views": n_in, "degradations": list(degs), "image_hw": list(hw)}
    masks = [_silhouette(meshes, K, T, hw) for T in poses]  # what each true camera sees
    scale = hw[1] / 2048.0
    soft = [m.astype(np.float32) for m in masks]
    drawn = masks
    if "halo" in degs or "shrink" in degs:  # a systematic edge offset: the mask drawn outside / inside the edge
        bias = a.bias_px * scale
        if "halo" in degs:
            drawn = [cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 5) <= bias for m in masks]
        else:
            drawn = [cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 5) > bias for m in masks]
        info["edge_bias_px"] = bias if "halo" in degs else -bias
    if "masks" in degs or "masks_x2" in degs:
        k = 2.0 if "masks_x2" in degs else 1.0
        soft = [hand_drawn_mask(m, rng, k * a.simplify_px * scale, k * a.vertex_sigma_px * scale) for m in drawn]
        info["input_mask_iou_mean"] = float(np.mean([((s >= 0.5) & m).sum() / max(((s >= 0.5) | m).sum(), 1)
                                                      for s, m in zip(soft, masks, strict=True)]))
    if "lens" in degs:
        from torm.capture.degrade import distort_image

        soft = [distort_image(s, K, REAL_LENS) for s in soft]
        info["lens"] = REAL_LENS.to_json()
    used = np.asarray(poses)
    if "pose" in degs or "pose_x2" in degs:
        pts = sample_surface(bc.concat(meshes), 2000, np.random.default_rng(0)).points_nx3
        k = 2.0 if "pose_x2" in degs else 1.0
        target = rng.uniform(k * POSE_PX[0], k * POSE_PX[1], size=len(poses))
        used, errs = perturb_poses(np.asarray(poses), np.repeat(K[None], len(poses), 0), pts, target, rng)
        info["pose_error"] = {"reprojection_px_mean": float(np.mean([e.reprojection_rms_px for e in errs])),
                              "rotation_mrad_mean": 1e3 * float(np.mean([e.rotation_rad for e in errs])),
                              "translation_mm_mean": 1e3 * float(np.mean([e.translation_m for e in errs]))}
    folder = a.cache / f"{shape}_{case}_{hw[1]}x{hw[0]}_s{a.seed}"
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (s, T) in enumerate(zip(soft, used, strict=True)):
        cv2.imwrite(str(folder / "masks" / f"{i:03d}.png"), np.round(255 * np.clip(s, 0, 1)).astype(np.uint8))
        frames.append({"file_path": f"masks/{i:03d}.png", "mask_path": f"masks/{i:03d}.png",
                       "transform_matrix": cv_to_gl(np.asarray(T)).tolist()})
    doc: dict[str, Any] = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": hw[1], "h": hw[0],
                           "frames": frames}
    if "lens" in degs:
        doc.update(REAL_LENS.to_json())
    (folder / "transforms.json").write_text(json.dumps(doc))
    cap = load_capture(folder)
    held = Capture(views=tuple(CameraView(K, T, mask=_silhouette(meshes, K, T, hw).astype(np.int32))
                               for T in held_poses))
    return cap, held, meshes, info


# ----------------------------------------------------------------------------------------------------------
# Methods
# ----------------------------------------------------------------------------------------------------------
def methods(quick: bool) -> dict[str, Callable]:
    tuned = dict(list(TUNED.items())[:3]) if quick else TUNED
    out: dict[str, Callable] = {"default": torm_method(ReconstructionConfig())}
    out |= {k: torm_method(ReconstructionConfig(**kw)) for k, kw in tuned.items()}
    out[HULL] = auto_box_hull(128)
    o3 = open3d_method(128, auto_box)
    if o3 is not None:
        out[OPEN3D] = o3
    return out


def run_case(a: argparse.Namespace, shape: str, case: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    cap, held, meshes, info = build_case(a, shape, case)
    res: dict[str, Any] = {}
    for name, fn in methods(a.quick).items():
        t = time.perf_counter()
        try:
            objs, extra = fn(cap)
        except ReconstructionError as exc:
            res[name] = {"error": str(exc), "heldout_iou_mean": 0.0}
            continue
        res[name] = {"time_s": time.perf_counter() - t, **score(objs, meshes, held),
                     **{k: v for k, v in extra.items() if k in ("band_levels", "vote_views", "open3d")}}
    torm_rows = {k: v for k, v in res.items() if k not in (HULL, OPEN3D)}
    best = max(torm_rows, key=lambda k: torm_rows[k].get("heldout_iou_mean", 0.0))
    d, h, b = (res[k].get("heldout_iou_mean", 0.0) for k in ("default", HULL, best))
    return {"shape": shape, "case": case, **info, "stress": bool(set(CASES[case][1]) & set(STRESS)),
            "methods": res, "best_tuned": best,
            "default_vs_hull": d - h, "default_over_best": d / b if b else None,
            "meets_hull": bool(d >= h), "meets_best": bool(b and d >= 0.95 * b),
            "load_avg_1min": os.getloadavg()[0], "case_s": time.perf_counter() - t0}  # "ran" added by main()


# ----------------------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------------------
def report(doc: dict[str, Any], path_md: Path) -> None:
    ctx = doc["context"]
    rows, extra = [], []
    for key, r in doc["rows"].items():
        m = r["methods"]
        deg = r.get("pose_error", {})
        rows.append([key, r["n_input_views"], ", ".join(r["degradations"]) or "none",
                     deg.get("reprojection_px_mean"), r.get("input_mask_iou_mean"),
                     m["default"].get("heldout_iou_mean"), m.get(HULL, {}).get("heldout_iou_mean"),
                     m.get(OPEN3D, {}).get("heldout_iou_mean"), r["best_tuned"],
                     m[r["best_tuned"]].get("heldout_iou_mean"),
                     "yes" if r["meets_hull"] else "**no**", "yes" if r["meets_best"] else "**no**"])
        ran = r.get("ran", {})
        extra.append([key, m["default"].get("chamfer_mm"), m.get(HULL, {}).get("chamfer_mm"),
                      m["default"].get("volume_iou"), m.get(HULL, {}).get("volume_iou"),
                      m["default"].get("time_s"), m.get(HULL, {}).get("time_s"),
                      f"{ran.get('git', doc['context']['versions']['git'])} {ran.get('date_utc', '')[:16]}"])
    degraded = [r for r in doc["rows"].values() if r["degradations"] and not r.get("stress")]
    stress = [r for r in doc["rows"].values() if r.get("stress")]
    n_hull = sum(r["meets_hull"] for r in degraded)
    n_best = sum(r["meets_best"] for r in degraded)
    tuned_names = sorted({k for r in doc["rows"].values() for k in r["methods"] if k not in (HULL, OPEN3D)})
    per_setting = []
    for k in tuned_names:
        v = [r["methods"][k].get("heldout_iou_mean", 0.0) for r in degraded if k in r["methods"]]
        per_setting.append([k, len(v), float(np.mean(v)) if v else None, float(np.min(v)) if v else None])
    md = ["# Reconstruction from degraded captures (issue 38)\n",
          "Generated by `benchmarks/recon_degraded.py` (the module docstring says how each case is built); JSON "
          f"twin `{path_md.stem}.json`. Held-out views use the exact cameras and masks (truth). Pose error: mean RMS "
          "reprojection error (px) of the input views; input mask IoU: hand-drawn vs exact, mean over input views.\n",
          bc.context_md(ctx),
          f"\n**Degraded cases: defaults >= the 128^3 voxel hull in {n_hull}/{len(degraded)}, >= 0.95 of the best "
          f"tuned setting in {n_best}/{len(degraded)}.**"
          + (f" Stress cases (beyond those ranges: twice the pose error, a hand twice as coarse, masks drawn "
             f"{doc['context']['args'].get('bias_px')} px outside or inside the edge): >= the hull in "
             f"{sum(r['meets_hull'] for r in stress)}/{len(stress)}, >= 0.95 of the best in "
             f"{sum(r['meets_best'] for r in stress)}/{len(stress)}." if stress else "") + "\n",
          "\n## Held-out silhouette IoU\n",
          bc.md_table(["shape / case", "views", "degradations", "pose err px", "input mask IoU", "default",
                       HULL, OPEN3D, "best tuned", "its IoU", "default >= hull", "default >= 0.95 best"], rows),
          "\n## Mean held-out IoU per setting over the degraded cases\n",
          bc.md_table(["setting", "cases", "mean", "min"], per_setting),
          "\n## Chamfer, volume IoU and time (default vs voxel hull)\n",
          bc.md_table(["shape / case", "default Chamfer mm", "hull Chamfer mm", "default vol IoU", "hull vol IoU",
                       "default s", "hull s", "ran (git, UTC)"], extra)]
    path_md.write_text("\n".join(md) + "\n")


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    bc.setup(a.threads)
    path = a.out / f"{a.name}.json"
    doc = json.loads(path.read_text()) if path.exists() else {"rows": {}}
    if not a.report_only:
        for r in doc["rows"].values():  # rows of an earlier run keep that run's identity
            if "ran" not in r and "context" in doc:
                r["ran"] = {"git": doc["context"]["versions"]["git"], "date_utc": doc["context"]["date_utc"],
                            "load_avg_start": r.pop("load_avg_1min", None)}
        doc["context"] = bc.context({k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()})
        for shape in a.shapes:
            for case in a.cases:
                key = f"{shape}/{case}"
                if key in doc["rows"] and not a.redo:
                    continue
                log.info("%s ...", key)
                doc["rows"][key] = r = run_case(a, shape, case)
                r["ran"] = {"git": doc["context"]["versions"]["git"], "date_utc": doc["context"]["date_utc"],
                            "load_avg_start": r.pop("load_avg_1min")}
                log.info("%s: default %.3f, hull %.3f, best %s %.3f (%.0f s)", key,
                         r["methods"]["default"].get("heldout_iou_mean", 0), r["methods"][HULL]["heldout_iou_mean"],
                         r["best_tuned"], r["methods"][r["best_tuned"]]["heldout_iou_mean"], r["case_s"])
                bc.write_json(path, doc)
    bc.write_json(path, doc)
    report(doc, path.with_suffix(".md"))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    raise SystemExit(main())
