"""``torm capture``: render a simulated multi-view capture of a scenario and save it as a capture folder.

Example::

    torm capture --scenario rw3 --seed 0 --views 50 --width 640 --height 360 --out runs/rw3_s0 [--rrd rw3.rrd]
    torm capture --scenario rw3 --scale 0.5 --renderer pbr --spp 16 --out runs/rw3_pbr   # path-traced RGB

Prints a JSON summary (folder, image size, intrinsics, objects, occlusion ratio, timings) on stdout.
The rig config (``sim.camera_rig.CameraRigConfig``) can be given as YAML with ``--config`` and
``--set key=value`` overrides; ``--views/--width/--height/--scale`` override it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from torm.commands._common import add_overrides, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("capture", help="render a simulated multi-view capture of a scenario to a folder",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", required=True, help="scenario name (see `torm scenes list`)")
    p.add_argument("--seed", type=int, default=0, help="layout seed (default 0)")
    p.add_argument("--views", type=int, default=None, help="number of views (default: the rig config's, 50)")
    p.add_argument("--width", type=int, default=None, help="image width in pixels (default 1280)")
    p.add_argument("--height", type=int, default=None, help="image height in pixels (default 720)")
    p.add_argument("--scale", type=float, default=None, help="scale the image size (e.g. 0.5 -> 640x360)")
    p.add_argument("--out", required=True, help="output capture folder (transforms.json convention)")
    p.add_argument("--robot", default="inovo_2f85", help="robot attached to the scene (hidden in renders), or 'none'")
    p.add_argument("--no-occlusion", action="store_true", help="skip computing the occlusion ratio")
    p.add_argument("--progress", action="store_true", help="show a progress bar on stderr")
    p.add_argument("--rrd", default=None, help="also write a rerun recording of the capture to this file")
    p.add_argument("--renderer", choices=("mujoco", "pbr"), default="mujoco",
                   help="who renders RGB: MuJoCo's rasteriser or the Mitsuba path tracer (depth and masks: MuJoCo)")
    p.add_argument("--spp", type=int, default=None, help="PBR samples per pixel (default: PbrSettings.spp)")
    add_overrides(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()
    from sim.camera_rig import CameraRigConfig, SimCameraRig
    from sim.occlusion import occlusion_ratio
    from sim.world import build_world
    from torm import config as cfgmod
    from torm.capture.io import save_capture

    overrides = list(args.overrides)
    for flag, key in ((args.views, "n_views"), (args.width, "width"), (args.height, "height"), (args.scale, "scale")):
        if flag is not None:
            overrides.append(f"{key}={flag}")
    rig_cfg = cfgmod.load(CameraRigConfig, args.config, overrides)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    world = build_world(args.scenario, args.seed, robot=None if args.robot == "none" else args.robot)
    timings["build_world_s"] = time.perf_counter() - t0
    rgb_renderer = None
    if args.renderer == "pbr":
        from sim.render import make_renderer
        from torm.capture.render_settings import PbrSettings

        rgb_renderer = make_renderer("pbr", world, PbrSettings() if args.spp is None else PbrSettings(spp=args.spp))
    with SimCameraRig.from_world(world, rig_cfg, rgb_renderer=rgb_renderer) as rig:
        t0 = time.perf_counter()
        cap = rig.capture(progress=args.progress)
        timings["render_s"] = time.perf_counter() - t0
        occ = None
        if not args.no_occlusion:
            t0 = time.perf_counter()
            occ = occlusion_ratio(rig, cap)
            timings["occlusion_s"] = time.perf_counter() - t0
    if occ is not None:
        cap.metadata["occlusion"] = occ.summary()
        cap.metadata["occlusion"]["view_flags"] = occ.view_flags.astype(int).tolist()
    t0 = time.perf_counter()
    path = save_capture(cap, Path(args.out))
    timings["save_s"] = time.perf_counter() - t0
    if args.rrd:
        import rerun as rr

        from torm.viz import log_capture

        rec = rr.RecordingStream("torm")
        rec.save(args.rrd)
        log_capture(rec, cap)
        rec.flush()
    H, W = cap.image_size
    print_json({
        "out": str(path.parent),
        "transforms": str(path),
        "scenario": cap.scenario,
        "seed": cap.seed,
        "views": len(cap),
        "width": W,
        "height": H,
        "K": cap.views[0].K,
        "object_ids": list(cap.object_ids),
        "object_names": list(cap.object_names),
        "occlusion_ratio": None if occ is None else occ.ratio,
        "occluded_views": None if occ is None else int(occ.view_flags.sum()),
        "views_per_s": len(cap) / max(timings["render_s"], 1e-9),
        "rrd": args.rrd,
        "timings": timings,
    })
    return 0
