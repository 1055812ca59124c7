"""``torm scenes``: list, check and look at the simulated scenarios.

- ``torm scenes list``: JSON with every scenario (objects, spacing, suite) and library object.
- ``torm scenes check``: build, settle and step every scene; JSON report; exit status 1 when any scene fails.
- ``torm scenes show``: render a few views to PNGs (RGB, instance mask, depth, sensor depth) and optionally a
  rerun recording of the capture.

Examples::

    torm scenes list --suite rw
    torm scenes check --suite rw --seeds 0 1
    torm scenes check --scenario rw3 --scenario syn5
    torm scenes show --scenario rw3 --views 6 --out runs/rw3_views --record rw3.rrd
"""

from __future__ import annotations

import argparse
import time
import traceback
from typing import Any

from torm.commands._common import (
    add_parser,
    add_record,
    add_robot,
    check_output_dir,
    count_arg,
    pixels_arg,
    positive_float,
    print_json,
    seed_arg,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "scenes", __doc__, help="list, check and render the simulated scenarios")
    sub = p.add_subparsers(dest="scenes_command", metavar="ACTION", required=True)

    pl = sub.add_parser("list", help="JSON list of scenarios and library objects")
    pl.add_argument("--suite", default=None, help="only this suite (e.g. rw, syn)")
    pl.set_defaults(func=run_list)

    pc = sub.add_parser("check", help="compile, settle and step every scene; exit 1 on any failure")
    pc.add_argument("--suite", default=None, help="only this suite")
    pc.add_argument("--scenario", action="append", default=[], help="only these scenarios (repeatable)")
    pc.add_argument("--seeds", type=seed_arg, nargs="+", default=[0], help="layout seeds to build (default 0)")
    add_robot(pc, "inovo_2f85", none_ok=True)
    pc.add_argument("--seconds", type=positive_float, default=1.0, help="simulated seconds per scene (default 1)")
    pc.set_defaults(func=run_check)

    ps = sub.add_parser("show", help="render a few views of a scenario to PNGs (and a rerun .rrd)")
    ps.add_argument("--scenario", required=True, help="scenario name")
    ps.add_argument("--seed", type=seed_arg, default=0, help="layout seed (default 0)")
    ps.add_argument("--views", type=count_arg, default=6, help="number of views (default 6)")
    ps.add_argument("--width", type=pixels_arg, default=640, help="image width (default 640)")
    ps.add_argument("--height", type=pixels_arg, default=360, help="image height (default 360)")
    ps.add_argument("--out", required=True, help="folder for the PNGs")
    add_record(ps, "the capture")
    add_robot(ps, "inovo_2f85", none_ok=True)
    ps.set_defaults(func=run_show)


def _robot(name: str) -> str | None:
    return None if name == "none" else name


def run_list(args: argparse.Namespace) -> int:
    from sim.scenes.objects import get_object, list_objects
    from sim.scenes.scenario import get_scenario, list_scenarios

    scenarios = []
    for name in list_scenarios(args.suite):
        sc = get_scenario(name)
        scenarios.append({"name": sc.name, "suite": sc.suite, "objects": list(sc.objects), "spacing": sc.spacing,
                          "fixed_poses": sc.poses is not None, "description": sc.description})
    objects = []
    for name in list_objects():
        a = get_object(name)
        objects.append({"name": a.name, "material": a.material, "transparent": a.transparent,
                        "height_m": a.height, "width_m": a.width, "mass_kg": a.mass, "description": a.description})
    print_json({"scenarios": scenarios, "objects": objects})
    return 0


def run_check(args: argparse.Namespace) -> int:
    from sim.scenes.scenario import get_scenario, list_scenarios
    from sim.world import build_world, check_world

    names = list(args.scenario) or list_scenarios(args.suite)
    for n in names:
        get_scenario(n)  # UnknownNameError lists the valid names
    rows: list[dict[str, Any]] = []
    for name in names:
        for seed in args.seeds:
            row: dict[str, Any] = {"scenario": name, "seed": seed}
            t0 = time.perf_counter()
            try:
                world = build_world(name, seed, robot=_robot(args.robot_config))
                row["build_s"] = time.perf_counter() - t0
                row["layout_attempts"] = world.layout_attempts
                row["ngeom"] = int(world.model.ngeom)
                row.update(check_world(world, seconds=args.seconds))
                row["ok"] = True
            except Exception as exc:  # report every failure, keep checking the other scenes
                row["ok"] = False
                row["error"] = f"{type(exc).__name__}: {exc}"
                row["traceback"] = traceback.format_exc(limit=3)
            rows.append(row)
    failed = [f"{r['scenario']}/{r['seed']}" for r in rows if not r["ok"]]
    print_json({"ok": not failed, "checked": len(rows), "failed": failed, "scenes": rows})
    return 1 if failed else 0


def run_show(args: argparse.Namespace) -> int:
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()
    import cv2
    import numpy as np

    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world
    from torm.resources import TRIAL_BASE_BYTES, capture_bytes, check_fits
    from torm.viz import instance_colors

    check_fits(TRIAL_BASE_BYTES + capture_bytes(args.views, args.width, args.height),
               f"--views {args.views} of {args.width}x{args.height} px", "give fewer --views or a smaller image")
    out = check_output_dir(args.out)
    world = build_world(args.scenario, args.seed, robot=_robot(args.robot_config))
    cfg = CameraRigConfig(n_views=args.views, width=args.width, height=args.height)
    with SimCameraRig.from_world(world, cfg) as rig:
        cap = rig.capture()
    colors = instance_colors(max(cap.object_ids, default=0))
    files: list[str] = []

    def depth_png(d: np.ndarray) -> np.ndarray:
        # near = bright; the range spans the closest surface to 1.2 m (the table around the objects)
        valid = d > 0
        lo = float(d[valid].min()) if valid.any() else 0.0
        hi = max(lo + 1e-3, min(1.2, float(d[valid].max()) if valid.any() else 1.0))
        g = np.zeros(d.shape, np.uint8)
        g[valid] = np.clip(255 * (hi - d[valid]) / (hi - lo), 0, 255).astype(np.uint8)
        return cv2.applyColorMap(g, cv2.COLORMAP_VIRIDIS)

    for i, v in enumerate(cap.views):
        panels = {
            "rgb": cv2.cvtColor(v.rgb, cv2.COLOR_RGB2BGR),
            "mask": cv2.cvtColor(colors[np.clip(v.mask, 0, len(colors) - 1)], cv2.COLOR_RGB2BGR),
            "depth": depth_png(v.depth),
            "sensor_depth": depth_png(v.sensor_depth),
        }
        for kind, img in panels.items():
            f = out / f"view_{i:03d}_{kind}.png"
            cv2.imwrite(str(f), img)
            files.append(str(f))
    summary: dict[str, Any] = {"scenario": cap.scenario, "seed": cap.seed, "views": len(cap),
                               "object_ids": list(cap.object_ids), "object_names": list(cap.object_names),
                               "out": str(out), "files": files}
    if args.record:
        import rerun as rr

        from torm.viz import log_capture, log_mesh

        rec = rr.RecordingStream("torm")
        rec.save(args.record)
        log_capture(rec, cap)
        for o, mesh in zip(world.objects, world.object_meshes_world(), strict=True):
            log_mesh(rec, f"world/objects/{o.instance_id}_{o.name}", mesh,
                     color=[*(int(c) for c in colors[o.instance_id]), 255])
        rec.flush()
        summary["record"] = str(args.record)
    print_json(summary)
    return 0
