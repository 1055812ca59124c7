"""``torm trial``: one closed-loop trial (capture -> silhouettes -> reconstruction -> grasps -> picks)."""

from __future__ import annotations

import argparse
import logging

from torm.commands._common import add_overrides, print_json

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "trial",
        help="run one closed-loop grasp trial and print its JSON result",
        description="Run one closed-loop trial: capture, silhouettes, reconstruction, grasp planning and a pick "
        "of every object, judged by the paper's 25 cm lift / 20 cm translation test. Prints the result record.",
    )
    p.add_argument("--scenario", default=None, help="scenario name (torm scenes list); default rw3")
    p.add_argument("--seed", type=int, default=None, help="layout / noise seed (default 0)")
    p.add_argument("--method", choices=("torm", "depth", "oracle"), default=None,
                   help="perception: torm (reconstruction), depth (single-view depth baseline), oracle (true meshes)")
    p.add_argument("--segmenter", choices=("gt", "noisy", "grounded_sam", "learned"), default=None,
                   help="silhouette source for --method torm (default gt)")
    p.add_argument("--preset", default=None, help="error-model preset for --segmenter noisy (default paper)")
    p.add_argument("--views", type=int, default=None, help="number of views (default 50)")
    p.add_argument("--backend", choices=("sim", "real"), default=None, help="sim (default) or real hardware")
    p.add_argument("--robot-config", default=None, help="robot folder name or robot YAML (default inovo_2f85)")
    p.add_argument("--hardware-config", default=None, metavar="FILE",
                   help="hardware YAML for --backend real (rosbridge host, gripper serial port, hand-eye file)")
    p.add_argument("--arm-robot", action="store_true",
                   help="allow the real arm to move (without it --backend real refuses every motion)")
    p.add_argument("--re-perceive", action="store_true", help="capture and reconstruct again before every pick")
    p.add_argument("--record", default=None, metavar="FILE.rrd",
                   help="write a rerun recording (images, masks, meshes, grasps, motion)")
    p.add_argument("--out", default=None, help="also write the JSON result to this file")
    add_overrides(p)
    p.set_defaults(func=run)


def trial_config_from_args(args: argparse.Namespace):
    """Build a TrialConfig from --config, the named flags and --set overrides (later wins)."""
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig

    flags = {
        "scenario": args.scenario, "seed": args.seed, "method": args.method, "backend": args.backend,
        "robot": args.robot_config, "segmentation.segmenter": args.segmenter, "segmentation.preset": args.preset,
        "capture.n_views": args.views, "hardware_config": getattr(args, "hardware_config", None),
    }
    overrides = [f"{k}={v}" for k, v in flags.items() if v is not None]
    if getattr(args, "re_perceive", False):
        overrides.append("re_perceive=true")
    if getattr(args, "arm_robot", False):
        overrides.append("arm_robot=true")
    data = cfgmod.load_yaml(args.config) if args.config else {}
    return cfgmod.from_dict(TrialConfig, data, overrides + list(args.overrides), where=args.config or "TrialConfig")


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from torm.pipeline import run_trial

    cfg = trial_config_from_args(args)
    result = run_trial(cfg, record=args.record)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2, default=str))
    print_json(result)
    return 0
