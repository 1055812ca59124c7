"""Run one closed-loop trial from Python and read its record: the API a script or another project uses.

    python examples/python_api_trial.py --scenario rw1 --views 12

The same trial as ``torm trial``; see docs/api.md for the functions and docs/harness.md for the record's fields.
"""

from __future__ import annotations

import argparse
import logging

from torm import config
from torm.pipeline import TrialConfig, run_trial


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="rw1", help="scenario name (torm scenes list)")
    ap.add_argument("--method", default="oracle", choices=("torm", "depth", "depth_fusion", "oracle"))
    ap.add_argument("--views", type=int, default=12, help="capture views (the paper: 50)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    trial = config.from_dict(TrialConfig, {"scenario": args.scenario, "method": args.method},
                             overrides=[f"capture.n_views={args.views}", "capture.scale=0.25"])
    record = run_trial(trial)
    s = record["summary"]
    print(f"{s['scenario']} ({s['method']}): {s['success']} objects picked")  # noqa: T201 - an example's output
    for name, outcome in s["outcomes"].items():
        print(f"  {name}: {outcome}")  # noqa: T201
    return record


if __name__ == "__main__":
    main()
