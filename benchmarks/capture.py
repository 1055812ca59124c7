"""Benchmark the simulated camera rig: views per second at 640x360 and 1280x720.

Builds one scenario world (``rw4`` by default; a small self-made table scene if ``sim.world`` is not
usable), renders ``--views`` views of the default hemisphere layout with all four channels together
(RGB + ideal depth + sensor depth + instance mask) and then one channel at a time, plus the
occlusion ratio (one solo mask render per object and view), and writes
``benchmarks/results/capture.json`` and ``benchmarks/results/capture.md``.

Run: ``MUJOCO_GL=egl python benchmarks/capture.py [--scenario rw4] [--views 50] [--repeats 1]``.
The machine's load average before the run is recorded; ``contended`` is true when other processes
were busy (1-minute load above half the cores), in which case the numbers are pessimistic.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import torm  # noqa: E402
from sim.cameras.occlusion import occlusion_ratio  # noqa: E402
from sim.cameras.rig import CHANNELS, CameraRigConfig, SimCameraRig  # noqa: E402
from torm.bench.results import cpu_model  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RESOLUTIONS = ((640, 360), (1280, 720))
CHANNEL_SETS: dict[str, tuple[str, ...]] = {
    "all": CHANNELS,
    "rgb": ("rgb",),
    "depth": ("depth",),
    "sensor_depth": ("sensor_depth",),
    "mask": ("mask",),
    "depth+mask": ("depth", "mask"),
}


def _fallback_world():
    """A table with three boxes (one glass) when sim.world cannot build the scenario."""
    s = mujoco.MjSpec()
    wb = s.worldbody
    wb.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.85, 0.9, 0.02], pos=[0.4, 0, -0.02], group=0)
    wb.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], pos=[0, 0, -0.75], group=0)
    wb.add_light(pos=[0.9, -0.6, 1.6], dir=[-0.35, 0.4, -1.0], castshadow=True)
    for x, y, grp in [(0.5, -0.1, 2), (0.6, 0.08, 4), (0.45, 0.1, 2)]:
        b = wb.add_body(pos=[x, y, 0.03])
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.025, 0.025, 0.03], group=grp,
                   rgba=[0.86, 0.93, 0.96, 0.3] if grp == 2 else [0.9, 0.9, 0.85, 1])
    m = s.compile()
    d = mujoco.MjData(m)
    g2i = np.zeros(m.ngeom, np.int32)
    g2i[2:5] = [1, 2, 3]
    return m, d, g2i


def _gl_info(rig: SimCameraRig) -> dict[str, str]:
    try:
        from OpenGL import GL

        rig._off.gl.make_current()
        return {k: GL.glGetString(v).decode() for k, v in (("gl_vendor", GL.GL_VENDOR), ("gl_renderer", GL.GL_RENDERER),
                                                            ("gl_version", GL.GL_VERSION))}
    except Exception as exc:  # informational only
        return {"gl_info_error": str(exc)}


def bench_resolution(rig_args: dict, width: int, height: int, views: int, repeats: int) -> dict:
    cfg = CameraRigConfig(n_views=views, width=width, height=height)
    rig = SimCameraRig(**rig_args, config=cfg)
    try:
        poses, K = rig.poses(), rig.K()
        rig.render_arrays(poses[0], K, CHANNELS)  # warm-up (shader compile, texture upload)
        out: dict = {"width": width, "height": height, "views": views, "per_channel": {}}
        for label, chans in CHANNEL_SETS.items():
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                for T in poses:
                    rig.render_arrays(T, K, chans)
                best = min(best, time.perf_counter() - t0)
            out["per_channel"][label] = {"seconds": best, "views_per_s": views / best,
                                         "ms_per_view": 1e3 * best / views}
        t0 = time.perf_counter()
        cap = rig.capture()
        out["capture_call_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        occ = occlusion_ratio(rig, cap)
        out["occlusion_s"] = time.perf_counter() - t0
        out["occlusion_ratio"] = occ.ratio
        out["all_channels_views_per_s"] = out["per_channel"]["all"]["views_per_s"]
        out.update(_gl_info(rig))
        return out
    finally:
        rig.close()


def write_markdown(result: dict, path: Path) -> None:
    lines = [
        "# Simulated capture benchmark",
        "",
        f"Scenario `{result['scenario']}` ({result['world']}), {result['views']} views of the default hemisphere "
        f"layout, date {result['date']}, machine: {result['machine']['cpu']} ({result['machine']['cores']} cores), "
        f"renderer: {result['resolutions'][0].get('gl_renderer', '?')}.",
        f"Load average before the run: {result['machine']['loadavg_before']}; contended: "
        f"**{str(result['contended']).lower()}**.",
        "",
        "Views per second (higher is better); `all` = RGB + ideal depth + sensor depth + instance mask per view.",
        "",
        "| resolution | " + " | ".join(CHANNEL_SETS) + " | OCC | OCC time (s) |",
        "|---|" + "---|" * len(CHANNEL_SETS) + "---|---|",
    ]
    for r in result["resolutions"]:
        cells = [f"{r['per_channel'][k]['views_per_s']:.1f}" for k in CHANNEL_SETS]
        lines.append(f"| {r['width']}x{r['height']} | " + " | ".join(cells)
                     + f" | {r['occlusion_ratio']:.2f} | {r['occlusion_s']:.2f} |")
    lines += ["", "OCC = share of views with an object partly occluded by another (sim/cameras/occlusion.py); its "
              "time is one solo mask render per object and view on top of the capture."]
    lines += ["", "Versions: " + ", ".join(f"{k} {v}" for k, v in result["versions"].items()), ""]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="rw4")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=1, help="timing repeats per channel set (best is kept)")
    ap.add_argument("--out", default=str(RESULTS), help="results folder")
    args = ap.parse_args(argv)

    load_before = os.getloadavg()
    cores = len(os.sched_getaffinity(0))
    try:
        from sim.world import build_world

        world = build_world(args.scenario, args.seed)
        rig_args = {"model": world.model, "data": world.data, "geom_to_instance": world.geom_to_instance}
        world_label = "sim.world"
    except Exception as exc:  # benchmark the rig even when the world is unavailable
        print(f"sim.world unavailable ({exc}); using the fallback scene", file=sys.stderr)
        m, d, g2i = _fallback_world()
        rig_args = {"model": m, "data": d, "geom_to_instance": g2i}
        world_label = "fallback scene"
    rows = []
    for w, h in RESOLUTIONS:
        r = bench_resolution(rig_args, w, h, args.views, args.repeats)
        print(f"{w}x{h}: " + ", ".join(f"{k} {v['views_per_s']:.1f} views/s" for k, v in r["per_channel"].items()),
              file=sys.stderr)
        rows.append(r)
    load_after = os.getloadavg()
    result = {
        "benchmark": "capture",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "scenario": args.scenario,
        "seed": args.seed,
        "world": world_label,
        "views": args.views,
        "channels": list(CHANNELS),
        "resolutions": rows,
        "threads": {"python_render_threads": 1, "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"),
                    "available_cores": cores},
        "machine": {"cpu": cpu_model(), "cores": cores, "platform": platform.platform(),
                    "loadavg_before": [round(x, 2) for x in load_before],
                    "loadavg_after": [round(x, 2) for x in load_after],
                    "MUJOCO_GL": os.environ.get("MUJOCO_GL")},
        "contended": bool(load_before[0] > 0.5 * cores),
        "versions": {"python": platform.python_version(), "mujoco": mujoco.__version__, "numpy": np.__version__,
                     "torm": torm.__version__},
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "capture.json").write_text(json.dumps(result, indent=2))
    write_markdown(result, out / "capture.md")
    print(json.dumps({"json": str(out / "capture.json"), "md": str(out / "capture.md"),
                      "all_channels_views_per_s": {f"{r['width']}x{r['height']}": r["all_channels_views_per_s"]
                                                   for r in rows}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
