"""Shared helpers of the reconstruction and segmentation benchmarks.

- :func:`get_scene`: a scenario's capture (rendered once, saved under ``runs/bench_captures/`` with
  :func:`torm.capture.io.save_capture` and reloaded afterwards, never re-rendered) and its GT object
  meshes (outer shells only, world frame, metres).
- :func:`evaluate_meshes`: objects found, silhouette IoU vs GT masks over all views at the capture size,
  dense Chamfer (mm), volume IoU/ratio and, optionally, the paper's Table II depth metrics.
- :func:`context`: versions, threads, machine, date and whether the machine was contended.
- :func:`write_json` / :func:`md_table`: result files.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torm.capture.io import load_capture, save_capture  # noqa: E402
from torm.mesh.sample import sample_surface  # noqa: E402
from torm.metrics import chamfer_distance_mm, depth_metrics, match_meshes, volume_iou  # noqa: E402
from torm.reconstruction.raster import render_depth  # noqa: E402
from torm.runtime import configure_threads  # noqa: E402
from torm.types import Capture, TriMesh  # noqa: E402

log = logging.getLogger("bench")

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CAPTURE_CACHE = ROOT / "runs" / "bench_captures"
#: surface samples per side for the dense Chamfer distance (sampling noise << 0.1 mm at this density)
CHAMFER_POINTS = 40_000
THREADS = 2


def setup(threads: int = THREADS, verbose: bool = True) -> int:
    """Logging to stderr and ``threads`` torch threads (the machine has 2 cores); returns the thread count."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("torm").setLevel(logging.WARNING)
    os.environ["TORM_THREADS"] = str(threads)  # reconstruct() calls configure_threads() itself
    return configure_threads(threads)


def cpu_busy_s() -> float:
    """CPU seconds all processes have been busy since boot (``/proc/stat``; 0 where it does not exist)."""
    try:
        fields = [float(x) for x in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
    except OSError:
        return 0.0
    return (sum(fields) - fields[3] - (fields[4] if len(fields) > 4 else 0.0)) / os.sysconf("SC_CLK_TCK")


def own_cpu_s(children: bool = False) -> float:
    """CPU seconds of this process (and of its waited-for children with ``children``)."""
    t = os.times()
    return t.user + t.system + ((t.children_user + t.children_system) if children else 0.0)


def cpu_info() -> dict[str, Any]:
    """CPU model and the vector extensions that change torch's speed here (from /proc/cpuinfo; empty elsewhere).

    Measured: TORM-paper on syn5 ran 205 s on a 2-core AVX-512 + bf16 machine and 501 s on a 2-core AVX2-only
    one (2026-12-03), so a timing without the ISA cannot be compared.
    """
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), "")
    flags = set(next((ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags")), []))
    isa = [f for f in ("avx2", "avx512f", "avx512_bf16", "amx_bf16") if f in flags]
    return {"cpu_model": model, "isa": isa, "torch_bf16_native": _bf16_native()}


def _bf16_native() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def context(args: dict[str, Any]) -> dict[str, Any]:
    """Run context: arguments, versions, threads, cores, date and load (``contended`` = 1-min load > 1.5)."""
    import mujoco
    import scipy
    import trimesh

    import torm

    load1 = os.getloadavg()[0]
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10).stdout.strip()
    except Exception:  # informational only
        rev = ""
    return {
        "args": args,
        "date_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "versions": {"python": platform.python_version(), "torm": getattr(torm, "__version__", ""),
                     "torch": torch.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
                     "mujoco": mujoco.__version__, "trimesh": trimesh.__version__, "git": rev},
        "threads": torch.get_num_threads(),
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), **cpu_info()},
        "load_avg_start": list(os.getloadavg()),
        "contended": bool(load1 > 1.5),
    }


@dataclass
class Scene:
    """A benchmark scene: the capture (GT masks, ideal depth) and the GT object meshes (outer shells)."""

    name: str
    seed: int
    capture: Capture
    gt_meshes: list[TriMesh]


def get_scene(scenario: str, seed: int, n_views: int, scale: float, cache: Path = CAPTURE_CACHE) -> Scene:
    """Build the world (for GT meshes) and load the cached capture, rendering and saving it on first use."""
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world

    world = build_world(scenario, seed)
    gt = list(world.object_outer_surfaces().values())
    cfg = CameraRigConfig(n_views=n_views, scale=scale)
    folder = Path(cache) / f"{scenario}_s{seed}_v{n_views}_{cfg.image_width}x{cfg.image_height}"
    if (folder / "transforms.json").exists():
        cap = load_capture(folder)
        log.info("%s: capture loaded from %s", scenario, folder)
    else:
        t = time.perf_counter()
        rig = SimCameraRig.from_world(world, cfg)
        try:
            cap = rig.capture()
        finally:
            rig.close()
        save_capture(cap, folder)
        log.info("%s: rendered %d views in %.1f s, saved to %s", scenario, n_views, time.perf_counter() - t, folder)
    return Scene(scenario, seed, cap, gt)


def concat(meshes: list[TriMesh]) -> TriMesh:
    """One mesh holding all of ``meshes``."""
    if not meshes:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    offs = np.cumsum([0] + [len(m.verts_vx3) for m in meshes])[:-1]
    return TriMesh(np.concatenate([m.verts_vx3 for m in meshes]),
                   np.concatenate([m.faces_fx3 + o for m, o in zip(meshes, offs, strict=True)]))


def evaluate_meshes(objects: list[TriMesh], scene: Scene, depth: bool = False,
                    chamfer_points: int = CHAMFER_POINTS) -> dict[str, Any]:
    """Metrics of reconstructed object meshes against the scene's ground truth.

    Silhouette IoU and depth: the union mesh rendered in every view at the capture resolution against
    the GT instance masks (> 0) and the ideal GT depth inside them. Chamfer: ``chamfer_points`` seeded
    area-uniform samples on the union of the objects and on the union of the GT shells. Volume IoU and
    ratio: union of objects vs union of GT (1 mm voxel centres, coarser when the grid gets too big).
    """
    cap = scene.capture
    gt_masks = cap.masks() > 0
    V, H, W = gt_masks.shape
    Ks, T_cw = cap.Ks(), np.linalg.inv(cap.poses())
    out: dict[str, Any] = {"n_present": len(scene.gt_meshes)}
    if not objects:
        out.update({"n_found": 0, "n_spurious": 0, "n_components": 0, "silhouette_iou_mean": 0.0,
                    "silhouette_iou_min": 0.0, "chamfer_mm": float("nan"), "volume_iou": 0.0, "volume_ratio": 0.0})
        return out
    m = match_meshes(objects, scene.gt_meshes)
    out.update({"n_found": m["n_found"], "n_spurious": m["n_spurious"], "n_components": len(objects)})
    union = concat(objects)
    depths = np.stack([render_depth(union.verts_vx3, union.faces_fx3, Ks[i], T_cw[i], H, W) for i in range(V)])
    pred = depths > 0
    inter = (pred & gt_masks).sum(axis=(1, 2))
    uni = (pred | gt_masks).sum(axis=(1, 2))
    ious = np.where(uni > 0, inter / np.maximum(uni, 1), 1.0)
    out["silhouette_iou_mean"] = float(ious.mean())
    out["silhouette_iou_min"] = float(ious.min())
    gt_union = concat(scene.gt_meshes)
    pa = sample_surface(union, chamfer_points, np.random.default_rng(1)).points_nx3
    pb = sample_surface(gt_union, chamfer_points, np.random.default_rng(2)).points_nx3
    out["chamfer_mm"] = chamfer_distance_mm(pa, pb)
    vi = volume_iou(objects, scene.gt_meshes)
    out["volume_iou"] = vi["iou"]
    out["volume_ratio"] = vi["volume_ratio"]
    out["volume_pitch_mm"] = 1e3 * vi["pitch"]
    if depth:
        gt_depth = np.stack([v.depth for v in cap.views])
        out["depth"] = depth_metrics(depths, gt_depth, gt_masks)
    return out


def check_tag(tag: str) -> str:
    """``tag`` if it can name a result file (letters, digits, '-', '_'); else SystemExit naming the rule."""
    if not tag.replace("_", "").replace("-", "").isalnum():
        raise SystemExit(f"--tag {tag!r}: letters, digits, '-' and '_' only (it names the result files)")
    return tag


def write_json(path: Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` as indented JSON (NaN -> null), atomically."""
    def clean(o: Any) -> Any:
        if isinstance(o, dict):
            return {str(k): clean(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [clean(v) for v in o]
        if isinstance(o, (np.floating, float)):
            return None if not np.isfinite(o) else float(o)
        if isinstance(o, np.integer):
            return int(o)
        if isinstance(o, np.bool_):
            return bool(o)
        if isinstance(o, Path):  # e.g. a list of folders among the arguments
            return str(o)
        return o

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(clean(doc), indent=1))
    tmp.replace(path)


def fmt(x: Any, nd: int = 3) -> str:
    """A table cell: floats with ``nd`` decimals, None/NaN as '-'."""
    if x is None:
        return "-"
    if isinstance(x, (float, np.floating)):
        return "-" if not np.isfinite(x) else f"{x:.{nd}f}"
    return str(x)


def md_table(header: list[str], rows: list[list[Any]], nd: int = 3) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(c, nd) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _isa_md(machine: dict[str, Any]) -> str:
    if "isa" not in machine:
        return ""
    return (f" ({machine.get('cpu_model') or 'CPU'}; {', '.join(machine['isa']) or 'no AVX2'}; "
            f"native bf16: {machine.get('torch_bf16_native')})")


def context_md(ctx: dict[str, Any]) -> str:
    """The context as a few Markdown lines."""
    v = ctx["versions"]
    return (f"- date (UTC): {ctx['date_utc']}; git {v.get('git', '')}; python {v['python']}, torch {v['torch']}, "
            f"numpy {v['numpy']}, mujoco {v['mujoco']}\n"
            f"- torch threads: {ctx['threads']}; CPU count: {ctx['machine']['cpu_count']}"
            f"{_isa_md(ctx['machine'])}; load average at start: "
            f"{', '.join(f'{x:.2f}' for x in ctx['load_avg_start'])}; contended (1-min load > 1.5): "
            f"{ctx['contended']}\n"
            f"- arguments: `{json.dumps(ctx['args'])}`\n" + (f"- note: {ctx['note']}\n" if ctx.get("note") else ""))
