"""``torm capture``: render a simulated multi-view capture of a scenario and save it as a capture folder.

Examples::

    torm capture --scenario rw3 --seed 0 --views 50 --scale 0.5 --out runs/rw3_s0
    torm capture --scenario rw3 --scale 0.5 --renderer pbr --spp 16 --out runs/rw3_pbr
    torm capture --scenario rw7 --views 30 --depth-model statistical --set radius=0.6 --out runs/rw7 --record rw7.rrd
    torm capture --scenario rw3 --scale 0.5 --empty --out runs/rw3_empty   # a reference pass as its own capture

``--empty`` renders the workspace with the objects hidden: what a robot records over the empty table before the
objects are placed, for ``torm segment --reference DIR`` and a trial's ``capture.reference_dir=DIR``.

``--backend real`` flies the real arm's wrist camera over the capture poses a trial uses and saves what it sees (the
arm moves only with ``--arm-robot``; it is stopped and disabled on any fault and on exit): run it over the table
cleared by hand, with ``--empty`` to say so, to record the reference pass of a real cell::

    torm capture --backend real --hardware-config hw.yaml --arm-robot --views 50 --empty --out runs/cell_empty

Prints a JSON summary (folder, image size, intrinsics, objects, occlusion ratio, timings) on stdout.
The rig config (``sim.cameras.rig.CameraRigConfig``; ``torm config show capture`` lists its keys) can be
given as YAML with ``--config`` and ``--set key=value`` overrides; ``--views/--width/--height/--scale``
override it.
"""

from __future__ import annotations

import argparse
import time

from torm.commands._common import (
    add_overrides,
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
    p = add_parser(subparsers, "capture", __doc__,
                   help="render a simulated multi-view capture of a scenario to a folder")
    p.add_argument("--scenario", default=None, help="scenario name (see `torm scenes list`); simulation only")
    p.add_argument("--seed", type=seed_arg, default=0, help="layout seed (default 0)")
    p.add_argument("--views", type=count_arg, default=None, help="number of views (default: the rig config's, 50)")
    p.add_argument("--width", type=pixels_arg, default=None, help="image width in pixels (default 1280)")
    p.add_argument("--height", type=pixels_arg, default=None, help="image height in pixels (default 720)")
    p.add_argument("--scale", type=positive_float, default=None, help="scale the image size (e.g. 0.5 -> 640x360)")
    p.add_argument("--out", required=True, help="output capture folder (transforms.json convention)")
    add_robot(p, "inovo_2f85", none_ok=True)
    from torm.vocabulary import DEPTH_MODELS, RENDERERS

    p.add_argument("--depth-model", default="ideal", choices=DEPTH_MODELS,
                   help="sensor-depth model (sim/depth): ideal (glass invisible), statistical, stereo (default ideal)")
    p.add_argument("--no-occlusion", action="store_true", help="skip computing the occlusion ratio")
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bar on stderr (shown by default, like torm bench)")
    p.add_argument("--progress", dest="progress", action="store_true", help=argparse.SUPPRESS)  # old opt-in, kept
    add_record(p, "the capture")
    p.add_argument("--renderer", choices=RENDERERS, default="mujoco",
                   help="who renders RGB: MuJoCo's rasteriser or the Mitsuba path tracer (depth and masks: MuJoCo)")
    p.add_argument("--spp", type=count_arg, default=None, help="PBR samples per pixel (default: PbrSettings.spp)")
    p.add_argument("--reference", action="store_true",
                   help="also render each view over the empty workspace (reference/; a robot's reference pass)")
    p.add_argument("--empty", action="store_true",
                   help="render the workspace with the objects hidden, as its own capture (a recorded reference pass); "
                   "with --backend real: the operator cleared the table (recorded in the metadata)")
    p.add_argument("--backend", choices=("sim", "real"), default="sim",
                   help="sim renders a scenario (default); real flies the real arm's wrist camera")
    p.add_argument("--hardware-config", default=None, metavar="FILE", help="hardware YAML for --backend real")
    p.add_argument("--arm-robot", action="store_true",
                   help="allow the real arm to move (without it --backend real refuses every motion)")
    add_overrides(p, example="radius=0.6", target="capture")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.backend == "real":
        return run_real(args)
    if args.scenario is None:
        from torm.errors import ConfigError

        raise ConfigError("--scenario is required in simulation (see `torm scenes list`)")
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()
    from sim.cameras.occlusion import occlusion_ratio
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world
    from torm import config as cfgmod
    from torm.capture.io import save_capture
    from torm.resources import TRIAL_BASE_BYTES, capture_bytes, check_fits

    overrides = list(args.overrides)
    for flag, key in ((args.views, "n_views"), (args.width, "width"), (args.height, "height"), (args.scale, "scale")):
        if flag is not None:
            overrides.append(f"{key}={flag}")
    rig_cfg = cfgmod.load(CameraRigConfig, args.config, overrides)
    if args.empty and args.reference:
        from torm.errors import ConfigError

        raise ConfigError("--empty renders the empty workspace itself; --reference adds one to a capture with the "
                          "objects: give one of them")
    out_dir = check_output_dir(args.out)  # before any work: a bad --out is refused now, not after the capture
    w, h = round(rig_cfg.width * rig_cfg.scale), round(rig_cfg.height * rig_cfg.scale)
    check_fits(TRIAL_BASE_BYTES + capture_bytes(rig_cfg.n_views, w, h), f"{rig_cfg.n_views} views of {w}x{h} px",
               "use fewer views (--views) or a smaller --scale")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    world = build_world(args.scenario, args.seed, robot=None if args.robot_config == "none" else args.robot_config)
    timings["build_world_s"] = time.perf_counter() - t0
    from sim.depth import make_depth_model

    rgb_renderer = None
    if args.renderer == "pbr":
        from sim.cameras.renderers import make_renderer
        from torm.capture.render_settings import PbrSettings

        rgb_renderer = make_renderer("pbr", world, PbrSettings() if args.spp is None else PbrSettings(spp=args.spp))
    with SimCameraRig.from_world(world, rig_cfg, rgb_renderer=rgb_renderer,
                                 depth_model=make_depth_model(args.depth_model), depth_seed=args.seed) as rig:
        t0 = time.perf_counter()
        if args.empty:
            from datetime import datetime, timezone

            from sim.cameras.reference_pass import objects_hidden

            with objects_hidden(world):
                cap = rig.capture(progress=args.progress)
            cap.metadata.update(source="empty workspace (torm capture --empty)",
                                date=datetime.now(timezone.utc).isoformat(timespec="seconds"))
        else:
            cap = rig.capture(progress=args.progress, reference=args.reference)
        timings["render_s"] = time.perf_counter() - t0
        occ = None
        if not args.no_occlusion and not args.empty:
            t0 = time.perf_counter()
            occ = occlusion_ratio(rig, cap)
            timings["occlusion_s"] = time.perf_counter() - t0
    if occ is not None:
        cap.metadata["occlusion"] = occ.summary()
        cap.metadata["occlusion"]["view_flags"] = occ.view_flags.astype(int).tolist()
    t0 = time.perf_counter()
    path = save_capture(cap, out_dir)
    timings["save_s"] = time.perf_counter() - t0
    if args.record:
        import rerun as rr

        from torm.viz import log_capture

        rec = rr.RecordingStream("torm")
        rec.save(args.record)
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
        "record": args.record,
        "timings": timings,
    })
    return 0


def run_real(args: argparse.Namespace) -> int:
    """``--backend real``: the real backend's capture (the poses a trial flies) saved as a capture folder, dated."""
    import signal
    import threading
    from datetime import datetime, timezone

    from torm import config as cfgmod
    from torm.capture.io import save_capture
    from torm.commands.trial import _on_sigterm
    from torm.errors import ConfigError
    from torm.pipeline import TrialConfig, make_backend

    sim_only = [flag for flag, on in (("--scenario", args.scenario is not None), ("--reference", args.reference),
                                      ("--renderer", args.renderer != "mujoco"), ("--spp", args.spp is not None),
                                      ("--depth-model", args.depth_model != "ideal"), ("--width", args.width),
                                      ("--height", args.height), ("--scale", args.scale), ("--config", args.config),
                                      ("--set", args.overrides), ("--record", args.record)) if on]
    if sim_only:
        raise ConfigError(f"{', '.join(sim_only)}: simulation flags; --backend real records what the camera sees "
                          "(image size and camera settings come from the hardware config)")
    if args.robot_config == "none":
        raise ConfigError("--backend real needs the robot that carries the camera: give --robot-config")
    out_dir = check_output_dir(args.out)
    overrides = ["backend=real", f"robot={args.robot_config}", f"capture.n_views={args.views or 50}"]
    overrides += [f"hardware_config={args.hardware_config}"] if args.hardware_config else []
    overrides += ["arm_robot=true"] if args.arm_robot else []
    cfg = cfgmod.from_dict(TrialConfig, {}, overrides, where="torm capture --backend real")
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None  # the stop path runs on SIGTERM
    try:
        backend = make_backend(cfg)
        try:
            t0 = time.perf_counter()
            cap = backend.capture(cfg.capture.n_views)
            render_s = time.perf_counter() - t0
        finally:
            backend.close()  # stops and disables the arm
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    cap.metadata.update(date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                        source="empty workspace (cleared by the operator; torm capture --backend real --empty)"
                        if args.empty else "real capture (torm capture --backend real)")
    path = save_capture(cap, out_dir)
    H, W = cap.image_size
    print_json({"out": str(path.parent), "transforms": str(path), "backend": "real", "views": len(cap),
                "requested_views": cfg.capture.n_views, "width": W, "height": H, "empty": bool(args.empty),
                "date": cap.metadata["date"], "timings": {"capture_s": render_s}})
    return 0
