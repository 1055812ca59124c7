"""``torm bench``: run the closed-loop benchmark grid (scenario x trial x method) into a run folder.

Examples::

    torm bench --suite rw --trials 10 --method torm --method depth --workers 2 --out runs/rw-night
    torm bench --suite rw --scenario rw1 --scenario rw3 --trials 3 --record failures --out runs/rw13
    torm bench --suite syn --trials 1 --set reconstruction.grid_res=64 --timeout 900 --out runs/syn-g64

Re-running the same command resumes: finished trials (by key ``suite/scenario/trial/method``) are
skipped; ``--retry failed`` also runs again the trials whose row is crashed, timeout or error (the old
rows stay in results.jsonl as history). A changed run identity (the fully resolved trial config and
the files it names, suite, timeout, trial function, base seed, the git commit / uncommitted changes
and dependency versions) is refused with the differences listed unless ``--fresh``, which moves the
old files into ``old-<time>/``. One bench per folder: a second one is refused (naming the holder).
Each trial runs in its own process with a time limit; timeouts, crashes and exceptions become
failure rows. Ctrl-C / SIGTERM stop the workers with SIGTERM (a real backend cancels the motion and
disables the arm) and ``--stop-grace`` seconds before SIGKILL. Prints a JSON summary on stdout
(including the repairs made to the folder); then ``torm report OUT`` makes the tables and plots.
"""

from __future__ import annotations

import argparse
import signal
from typing import Any

from torm.commands._common import add_parser, add_robot, count_arg, positive_float, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    from torm.bench.spec import DEFAULT_TRIAL_FN, ENGINES, METHODS, RECORD_MODES, START_METHODS

    p = add_parser(subparsers, "bench", __doc__,
                   help="run the closed-loop benchmark grid into a run folder (resumable)")
    from torm.vocabulary import DEPTH_MODELS, REALISM_PROFILES, RENDERERS, SEGMENTERS
    from torm.vocabulary import suite_names as list_suites

    p.add_argument("--suite", default="rw", help=f"scenario suite ({', '.join(list_suites())}; default rw)")
    p.add_argument("--scenario", action="append", default=[], metavar="NAME",
                   help="only these scenarios of the suite (repeatable or comma-separated; default all)")
    p.add_argument("--trials", type=count_arg, default=1, help="trials per scenario and method (default 1)")
    p.add_argument("--method", action="append", default=[], metavar="METHOD",
                   help=f"perception method(s) {', '.join(METHODS)}, an installed plug-in (torm methods list) or "
                        "package.module:callable (repeatable or comma-separated; default torm)")
    p.add_argument("--workers", type=count_arg, default=1, help="trials at the same time (default 1)")
    p.add_argument("--out", required=True, help="run folder (created; resumed when it exists)")
    p.add_argument("--engine", choices=ENGINES, default="pool", help="pool: local processes (default); ray: Ray tasks")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--timeout", type=positive_float, default=1800.0,
                   help="seconds per trial before it is killed (default 1800)")
    p.add_argument("--record", choices=RECORD_MODES, default="none",
                   help="rerun recordings per trial: none (default), failures (kept for failed trials), all")
    p.add_argument("--fresh", action="store_true", help="move existing results aside and start over")
    p.add_argument("--retry", choices=("failed",), default=None,
                   help="failed: also run again trials whose row is crashed, timeout or error (old rows kept)")
    p.add_argument("--stop-grace", type=positive_float, default=10.0, metavar="S",
                   help="seconds a stopping worker gets between SIGTERM and SIGKILL (default 10)")
    p.add_argument("--start-method", choices=START_METHODS, default="forkserver",
                   help="how each trial's process starts (pool engine): forkserver (default: a fork of a server that "
                        "imported the libraries once) or spawn (a fresh interpreter per trial)")
    p.add_argument("--threads", type=int, default=0, help="threads per trial (default: free cores / workers)")
    p.add_argument("--base-seed", type=int, default=0, help="mixed into every trial seed (default 0)")
    p.add_argument("--trial-fn", default=DEFAULT_TRIAL_FN,
                   help=f"module:function run per trial (default {DEFAULT_TRIAL_FN})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a trial config value, e.g. --set capture.n_views=20 (repeatable)")
    p.add_argument("--segmenter", choices=SEGMENTERS, default=None,
                   help="silhouette source of --method torm (= --set segmentation.segmenter=...; default gt)")
    p.add_argument("--renderer", choices=RENDERERS, default=None,
                   help="image renderer (= --set capture.renderer=...; default mujoco)")
    p.add_argument("--depth-model", choices=DEPTH_MODELS, default=None,
                   help="sensor-depth model (= --set capture.depth_model=...; default ideal)")
    p.add_argument("--realism", choices=REALISM_PROFILES, default=None,
                   help="realism profile (= --set world.realism=...; benchmarks default to measured)")
    p.add_argument("--views", type=count_arg, default=None, help="views per capture (= --set capture.n_views=...)")
    p.add_argument("--backend", choices=("sim", "real"), default=None, help="sim (default) or real hardware")
    add_robot(p, None)
    p.add_argument("--hardware-config", default=None, metavar="FILE", help="hardware YAML for --backend real")
    p.add_argument("--arm-robot", action="store_true", help="allow the real arm to move (--backend real)")
    p.set_defaults(func=run)


def trial_overrides(args: argparse.Namespace) -> tuple[str, ...]:
    """--set overrides plus the backend/robot flags, as ``key=value`` strings (the flags come first)."""
    flags = {"backend": args.backend, "robot": args.robot_config, "hardware_config": args.hardware_config,
             "segmentation.segmenter": getattr(args, "segmenter", None),
             "capture.renderer": getattr(args, "renderer", None),
             "capture.depth_model": getattr(args, "depth_model", None),
             "world.realism": getattr(args, "realism", None), "capture.n_views": getattr(args, "views", None)}
    out = [f"{k}={v}" for k, v in flags.items() if v is not None]
    if args.arm_robot:
        out.append("arm_robot=true")
    return (*out, *args.overrides)


def _on_sigterm(signum: int, frame: Any) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # once: the workers' stop path must not be cut short
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    from torm.bench.runner import run_benchmark
    from torm.bench.spec import BenchConfig, parse_list

    config = BenchConfig(
        suite=args.suite, scenarios=parse_list(args.scenario), trials=args.trials,
        methods=parse_list(args.method) or ("torm",), workers=args.workers, engine=args.engine,
        ray_address=args.ray_address, timeout_s=args.timeout, record=args.record, overrides=trial_overrides(args),
        trial_fn=args.trial_fn, base_seed=args.base_seed, threads=args.threads, stop_grace_s=args.stop_grace,
        start_method=args.start_method,
    )
    previous = signal.signal(signal.SIGTERM, _on_sigterm)  # SIGTERM stops the workers like Ctrl-C
    try:
        summary = run_benchmark(config, args.out, fresh=args.fresh, progress=not args.no_progress, retry=args.retry)
    finally:
        signal.signal(signal.SIGTERM, previous)
    print_json(summary)
    return 0
