"""``torm trial``: one closed-loop trial (capture -> silhouettes -> reconstruction -> grasps -> picks).

Runs capture, silhouettes, reconstruction, grasp planning and a pick of every object, judged by the paper's
25 cm lift / 20 cm translation test. On a terminal it prints a short summary (what ran, k/n picked, each
object's outcome, the slowest stages); with ``--json``, or when stdout is a pipe or a file, it prints the full
record as JSON: a ``summary`` first, then what produced it (``context``), timings, perception metrics,
per-object outcomes, and the resolved ``config`` last. ``--out FILE`` always writes the JSON.
Progress (each stage with its time) goes to stderr; ``torm -q trial ...`` silences it.

Examples::

    torm trial --scenario rw3 --seed 0
    torm trial --scenario rw7 --method depth --out runs/rw7_depth.json
    torm trial --scenario rw3 --segmenter noisy --preset severe --record rw3.rrd
    torm trial --scenario syn5 --set reconstruction.grid_res=64 --set capture.n_views=30
    torm trial --backend real --robot-config inovo_2f85 --hardware-config hw.yaml --arm-robot

``torm config show trial`` prints every config key with its default.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from torm.commands._common import (
    add_overrides,
    add_parser,
    add_record,
    add_robot,
    check_output_file,
    count_arg,
    print_json,
    seed_arg,
    write_json_file,
)

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from torm.vocabulary import DEPTH_MODELS, METHODS, REALISM_PROFILES, RENDERERS, SEGMENTERS

    p = add_parser(sub, "trial", __doc__, help="run one closed-loop grasp trial and print its JSON result")
    p.add_argument("--scenario", default=None, help="scenario name (torm scenes list); default rw3")
    p.add_argument("--seed", type=seed_arg, default=None, help="layout / noise seed (default 0)")
    p.add_argument("--method", default=None, metavar="METHOD",
                   help=f"perception: a built-in ({', '.join(METHODS)}: torm = reconstruction, depth = single-view "
                   "depth with symmetric completion, depth_fusion = TSDF fusion of every view's depth, oracle = true "
                   "meshes), a registered plug-in (torm methods list) or package.module:callable (default torm)")
    p.add_argument("--segmenter", choices=SEGMENTERS, default=None,
                   help="silhouette source for --method torm (default gt)")
    p.add_argument("--renderer", choices=RENDERERS, default=None, help="simulated RGB renderer (default mujoco)")
    p.add_argument("--depth-model", choices=DEPTH_MODELS, default=None,
                   help="simulated depth camera model (default ideal)")
    p.add_argument("--realism", choices=REALISM_PROFILES, default=None,
                   help="realism profile of the simulated world (default ideal for one trial)")
    p.add_argument("--preset", default=None, help="error-model preset for --segmenter noisy (default paper)")
    p.add_argument("--views", type=count_arg, default=None, help="number of views (default 50)")
    p.add_argument("--backend", choices=("sim", "real"), default=None, help="sim (default) or real hardware")
    add_robot(p, None)
    p.add_argument("--hardware-config", default=None, metavar="FILE",
                   help="hardware YAML for --backend real (rosbridge host, gripper serial port, hand-eye file)")
    p.add_argument("--arm-robot", action="store_true",
                   help="allow the real arm to move (without it --backend real refuses every motion)")
    p.add_argument("--re-perceive", action="store_true", help="capture and reconstruct again before every pick")
    add_record(p, "the trial (images, masks, meshes, grasps, motion, outcomes)")
    p.add_argument("--out", default=None, help="also write the JSON result to this file")
    p.add_argument("--json", action="store_true",
                   help="print the full JSON record on stdout (the default when stdout is not a terminal; on a "
                        "terminal a short summary is printed)")
    add_overrides(p, example="reconstruction.grid_res=64", target="trial")
    p.set_defaults(func=run)


def trial_config_from_args(args: argparse.Namespace):
    """Build a TrialConfig from --config, the named flags and --set overrides (later wins)."""
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig

    flags = {
        "scenario": args.scenario, "seed": args.seed, "method": args.method, "backend": args.backend,
        "robot": args.robot_config, "segmentation.segmenter": args.segmenter, "segmentation.preset": args.preset,
        "capture.n_views": args.views, "hardware_config": getattr(args, "hardware_config", None),
        "capture.renderer": getattr(args, "renderer", None), "capture.depth_model": getattr(args, "depth_model", None),
        "world.realism": getattr(args, "realism", None),
    }
    overrides = [f"{k}={v}" for k, v in flags.items() if v is not None]
    if getattr(args, "re_perceive", False):
        overrides.append("re_perceive=true")
    if getattr(args, "arm_robot", False):
        overrides.append("arm_robot=true")
    data = cfgmod.load_yaml(args.config) if args.config else {}
    return cfgmod.from_dict(TrialConfig, data, overrides + list(args.overrides), where=args.config or "TrialConfig")


def format_summary(result: dict, out: str | None = None) -> str:
    """A trial record as a few lines for a terminal: what ran, k/n picked, each object's outcome, phantom
    attempts, the slowest stages, and where the full record is."""
    summ = result.get("summary") or {}
    ctx = result.get("context") or {}
    lines = [f"trial {summ.get('scenario')} seed {summ.get('seed')} method {summ.get('method')}: "
             f"{summ.get('success')} objects picked"
             + (f", {summ.get('phantom_attempts')} phantom attempt(s)" if summ.get("phantom_attempts") else "")
             + (f", failure {summ.get('failure')}" if summ.get("failure") else "")]
    what = [f"{k} {ctx[k]}" for k in ("realism", "segmenter", "renderer", "depth_model", "table") if ctx.get(k)]
    if what:
        lines.append("  ran: " + ", ".join(what))
    for name, outcome in (summ.get("outcomes") or {}).items():
        lines.append(f"  {name:<28} {outcome}")
    timings = {k: v for k, v in (result.get("timings") or {}).items() if k != "total" and isinstance(v, float)}
    slow = sorted(timings.items(), key=lambda kv: -kv[1])[:3]
    total = (result.get("timings") or {}).get("total")
    if total is not None:
        lines.append(f"  total {total:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in slow) + ")")
    lines.append(f"  full record: {out}" if out else "  full record: torm trial ... --json (or --out FILE)")
    return "\n".join(lines)


def _on_sigterm(signum: int, frame: Any) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # once: the backend's stop path must not be cut short
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    from torm.errors import OutputError
    from torm.pipeline import run_trial

    cfg = trial_config_from_args(args)
    out = check_output_file(args.out, "--out") if args.out else None  # before the trial, not after it
    if args.record:
        check_output_file(args.record, "--record")
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None  # clean-up on SIGTERM too
    try:
        result = run_trial(cfg, record=args.record)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    if args.json or not sys.stdout.isatty():
        print_json(result)  # first: the result is on stdout even if writing the file fails
    else:
        sys.stdout.write(format_summary(result, args.out) + "\n")
    if out is not None:
        try:
            write_json_file(out, result, "--out")
        except OutputError as exc:
            raise OutputError(f"{exc}; the result was printed on stdout") from exc
    return 0
