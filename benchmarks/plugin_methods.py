"""A plug-in perception method beside TORM and the built-in depth baseline, in the same benchmark (issue 40).

Runs ``torm bench`` on the ``--suite`` (default rw) with the methods ``--methods`` (default: ``torm``, ``depth``
and the example plug-in ``torm_plane_fill:PlaneFill`` loaded by ``module:callable`` from
``examples/torm_plane_fill/src``), the ``measured`` realism profile and the ``statistical`` depth camera (glass
depth mostly missing, as a D455 reports it), TORM with the simulator's masks; then writes per method the objects
picked k/n with Wilson 95 % intervals, per scenario, and what ran (method name, version, source, options hash from
the rows). Resumable: the run folder is ``runs/bench_plugin_<suite>``.

Writes ``benchmarks/results/plugin_methods.{json,md}``.
Run: ``MUJOCO_GL=egl python benchmarks/plugin_methods.py [--trials 2] [--workers 1]`` (tens of seconds per trial).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import RESULTS, ROOT, context, context_md, md_table, setup, write_json  # noqa: E402

EXAMPLE_SRC = ROOT / "examples" / "torm_plane_fill" / "src"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="rw")
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--methods", default="torm,depth,torm_plane_fill:PlaneFill")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    setup()
    os.environ["PYTHONPATH"] = os.pathsep.join([str(EXAMPLE_SRC), str(ROOT), os.environ.get("PYTHONPATH", "")])
    sys.path.insert(0, str(EXAMPLE_SRC))
    from torm.bench import BenchConfig, run_benchmark
    from torm.bench.results import read_results
    from torm.bench.stats import wilson_interval

    methods = tuple(m for m in args.methods.split(",") if m)
    overrides = ("world.realism=measured", "capture.depth_model=statistical", *args.overrides)
    cfg = BenchConfig(suite=args.suite, trials=args.trials, methods=methods, workers=args.workers,
                      overrides=overrides, timeout_s=900.0)
    run_dir = ROOT / "runs" / f"bench_plugin_{args.suite}"
    run_benchmark(cfg, run_dir, progress=True)
    rows = read_results(run_dir / "results.jsonl").rows
    per: dict[str, dict[str, Any]] = {}
    for m in methods:
        rs = [r for r in rows if r.get("method") == m]
        k = sum(int(r.get("n_success") or 0) for r in rs if r.get("status") == "ok")
        n = sum(int(r.get("n_objects") or 0) for r in rs if r.get("status") == "ok")
        lo, hi = wilson_interval(k, n) if n else (float("nan"), float("nan"))
        ctx = next((r.get("context", {}) for r in rs if r.get("context")), {})
        per[m] = {"k": k, "n": n, "rate": k / n if n else None, "wilson95": [lo, hi], "trials": len(rs),
                  "errors": sum(r.get("status") != "ok" for r in rs),
                  "what_ran": {key: ctx.get(key) for key in ("method", "method_name", "method_version",
                                                             "method_source", "method_options_sha", "segmenter",
                                                             "renderer", "depth_model", "realism")},
                  "by_scenario": {sc: [sum(int(r.get("n_success") or 0) for r in rs if r["scenario"] == sc),
                                       sum(int(r.get("n_objects") or 0) for r in rs if r["scenario"] == sc)]
                                  for sc in sorted({r["scenario"] for r in rs})}}
    doc = {"context": context(vars(args)), "run_dir": str(run_dir), "overrides": list(overrides), "methods": per}
    write_json(RESULTS / "plugin_methods.json", doc)
    scen = sorted({sc for p in per.values() for sc in p["by_scenario"]})
    head = ["method", "what ran", "objects picked", "rate [95 % CI]", *scen]
    body = []
    for m, p in per.items():
        w = p["what_ran"]
        ran = (f"{w.get('method_name') or m} {w.get('method_version') or ''} ({w.get('method_source') or 'builtin'})"
               .strip())
        rate = "-" if p["rate"] is None else f"{p['rate']:.2f} [{p['wilson95'][0]:.2f}, {p['wilson95'][1]:.2f}]"
        body.append([f"`{m}`", ran, f"{p['k']}/{p['n']}", rate,
                     *(f"{p['by_scenario'].get(sc, [0, 0])[0]}/{p['by_scenario'].get(sc, [0, 0])[1]}" for sc in scen)])
    L = ["# A plug-in method beside the built-ins (issue 40)", "", context_md(doc["context"]), "",
         f"`torm bench` on `{args.suite}`, {args.trials} trial(s) per scenario and method, the same layouts for every "
         f"method; overrides {', '.join(f'`{o}`' for o in overrides)}. TORM reads the simulator's masks; the depth "
         "baseline and the plug-in read one top-down view's sensor depth inside those masks. `plane_fill` is the "
         "example plug-in (`examples/torm_plane_fill`), loaded by `module:callable` like any third-party method.", "",
         md_table(head, body), ""]
    (RESULTS / "plugin_methods.md").write_text("\n".join(L) + "\n")
    print("\n".join(str(b) for b in body))
    return 0


if __name__ == "__main__":
    sys.exit(main())
