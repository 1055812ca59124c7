"""Benchmark the closed-loop harness end to end: trials per hour and where a trial's time goes.

Runs a small fixed budget of the default closed-loop suite through the benchmark runner (each trial
an isolated worker process, exactly as ``torm bench`` runs them): by default the ``rw`` suite, one
trial per scenario, method ``torm``, 2 workers, default trial config. Writes
``benchmarks/results/throughput.json`` and ``benchmarks/results/throughput.md``: trials per hour
(from the runner session's timestamps), mean seconds per pipeline stage and per trial, object
success, failure categories, machine load and versions. The run folder (``runs/bench_throughput``
by default) is started fresh every time (old results are moved aside into ``old-<time>/``) and can be
opened with ``torm report``.

Run: ``MUJOCO_GL=egl python benchmarks/bench_throughput.py [--suite rw] [--scenario rw1 ...]
[--trials 1] [--method torm] [--workers 2] [--timeout 1800] [--set capture.n_views=20] [--baseline]``.
``--baseline`` runs the same grid again right after with only ``--baseline-set`` overrides (none: the simulator-mask
grid) and writes the wall-time ratio of the two grids (one run, same machine state).
``contended`` is true when the 1-minute load before the run was above half the cores (the numbers
are then pessimistic). Benchmark trials default to the ``measured`` realism profile (``--set
world.realism=ideal`` for the ideal world); ``--name throughput_measured`` writes ``throughput_measured.{json,md}``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torm.bench import BenchConfig, run_benchmark  # noqa: E402
from torm.bench.report import (  # noqa: E402
    load_run,
    methods_of,
    overall_throughput,
    stages_of,
    success_counts,
    timing_means,
)
from torm.bench.results import cpu_model, package_versions  # noqa: E402
from torm.bench.spec import DEFAULT_TRIAL_FN, START_METHODS, parse_list  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RUN_DIR = ROOT / "runs" / "bench_throughput"


def _r(v: float | None, digits: int = 3) -> float | None:
    return None if v is None else round(v, digits)


def summarise(run_dir: Path, config: BenchConfig, wall_s: float, load_before: tuple[float, ...],
              load_after: tuple[float, ...]) -> dict:
    """The result dict written to throughput.json (numbers from the run folder's rows and manifest)."""
    run = load_run(run_dir)
    cores = os.cpu_count() or 1
    stages = stages_of(run.rows)
    per_method = {}
    for m in methods_of(run.rows, run.manifest):
        t = timing_means(run.rows, m)
        k, n = success_counts(run.rows, None, m)
        per_method[m] = {
            "trials": sum(r["method"] == m for r in run.rows),
            "stage_mean_s": {s: _r(t[s]) for s in stages},
            "trial_total_mean_s": _r(t["total"]),
            "worker_wall_mean_s": _r(t["wall"]),
            "objects_success": k, "objects": n,
        }
    failures: dict[str, int] = {}
    for r in run.rows:
        if r.get("failure"):
            failures[r["failure"]] = failures.get(r["failure"], 0) + 1
    tph = overall_throughput(run)
    if tph is None and wall_s > 0:  # no session timestamps: the measured wall time (includes start-up)
        tph = len(run.rows) / wall_s * 3600
    return {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "config": config.as_dict(),
        "run_dir": str(run_dir),
        "trials": len(run.rows),
        "wall_s": round(wall_s, 1),
        "trials_per_hour": _r(tph, 1),
        "realism": sorted({str((r.get("context") or {}).get("realism")) for r in run.rows}),
        "what_ran": sorted({what_ran(r.get("context") or {}) for r in run.rows}),
        "per_method": per_method,
        "failure_categories": failures,
        "machine": {"cpu": cpu_model(), "cores": cores, "platform": platform.platform(),
                    "loadavg_before": [round(x, 2) for x in load_before],
                    "loadavg_after": [round(x, 2) for x in load_after]},
        "contended": bool(load_before[0] > 0.5 * cores),
        "versions": package_versions(),
        "git": (run.manifest or {}).get("git"),
    }


#: trial-context keys named in a result's "what ran" line (torm.pipeline.trial_context)
WHAT_RAN_KEYS = ("method", "segmenter", "segmenter_model", "segmenter_postprocess", "segmenter_input_px", "renderer",
                 "render_spp", "render_scale", "depth_model", "realism")


def what_ran(ctx: dict) -> str:
    """A trial context as one line: ``key value`` for each of :data:`WHAT_RAN_KEYS` that it has."""
    return ", ".join(f"{k} {ctx[k]}" for k in WHAT_RAN_KEYS if ctx.get(k) is not None)


def write_markdown(result: dict, path: Path) -> None:
    c = result["config"]
    lines = [
        "# Closed-loop benchmark throughput",
        "",
        f"Suite `{c['suite']}` ({', '.join(c['scenarios']) or 'all scenarios'}), {c['trials']} trial(s) per scenario, "
        f"methods {', '.join(c['methods'])}, {c['workers']} worker(s) on the `{c['engine']}` engine, "
        f"overrides: {', '.join(f'`{o}`' for o in c['overrides']) or 'none'}. Date {result['date']}, machine: "
        f"{result['machine']['cpu']} ({result['machine']['cores']} cores). Load average before the run: "
        f"{result['machine']['loadavg_before']}; contended: **{str(result['contended']).lower()}**. Realism profile "
        f"of the trials: {', '.join(result.get('realism') or ['?'])}.",
        "",
        "What ran (from the trials' contexts): " + "; ".join(f"`{w}`" for w in result.get("what_ran", [])) + ".",
        "",
        f"**{result['trials_per_hour']} trials/hour** ({result['trials']} trials in {result['wall_s']} s wall time, "
        f"each trial an isolated worker process, started by `{c.get('start_method', 'spawn')}`).",
        "",
    ]
    base = result.get("baseline")
    if base:
        lines += [f"**Baseline grid in the same run** (the same grid with overrides "
                  f"{', '.join(f'`{o}`' for o in base['overrides']) or 'none'}, run right after; what ran: "
                  + "; ".join(f"`{w}`" for w in base.get("what_ran", [])) + f"): {base['trials_per_hour']} "
                  f"trials/hour, {base['wall_s']} s wall time, objects {base['objects_success']}/{base['objects']}. "
                  f"**This grid took {result['wall_ratio_vs_baseline']:.2f}x the baseline's wall time.**", ""]
    methods = list(result["per_method"].values())
    stages = list(methods[0]["stage_mean_s"]) if methods else []  # the same stages for every method
    lines.append("Mean seconds per stage of a trial (trials that returned); `worker` = mean wall time of the "
                 "trial's process including interpreter start and imports.")
    lines.append("")
    lines.append("| method | trials | " + " | ".join(stages) + " | total | worker | object success |")
    lines.append("|---|---|" + "---|" * (len(stages) + 3))
    for m, v in result["per_method"].items():
        cells = ["–" if v["stage_mean_s"].get(s) is None else f"{v['stage_mean_s'][s]:.2f}" for s in stages]
        tot = "–" if v["trial_total_mean_s"] is None else f"{v['trial_total_mean_s']:.2f}"
        wall = "–" if v["worker_wall_mean_s"] is None else f"{v['worker_wall_mean_s']:.2f}"
        lines.append(f"| {m} | {v['trials']} | " + " | ".join(cells) + f" | {tot} | {wall} | "
                     f"{v['objects_success']}/{v['objects']} |")
    lines.append("")
    if result["failure_categories"]:
        lines.append("Trial failures: " + ", ".join(f"{k} {n}" for k, n in sorted(result["failure_categories"].items()))
                     + ".")
        lines.append("")
    v = result["versions"]
    lines.append("Versions: " + ", ".join(f"{k} {val}" for k, val in v.items() if val) + ".")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="rw")
    ap.add_argument("--scenario", action="append", default=[], help="subset of the suite (default all)")
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--method", action="append", default=[], help="default torm")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per trial")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--trial-fn", default=DEFAULT_TRIAL_FN)
    ap.add_argument("--start-method", choices=START_METHODS, default="forkserver",
                    help="how each trial's process starts (default forkserver, as torm bench)")
    ap.add_argument("--run-dir", default=str(RUN_DIR), help=f"run folder (default {RUN_DIR})")
    ap.add_argument("--results-dir", default=str(RESULTS), help=f"where the result files go (default {RESULTS})")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--name", default="throughput", help="result file stem (default throughput)")
    ap.add_argument("--baseline", action="store_true",
                    help="run the same grid again right after with --baseline-set overrides only (default none: the "
                         "simulator-mask grid) and report the wall-time ratio")
    ap.add_argument("--baseline-set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")
    config = BenchConfig(suite=args.suite, scenarios=parse_list(args.scenario), trials=args.trials,
                         methods=parse_list(args.method) or ("torm",), workers=args.workers, timeout_s=args.timeout,
                         overrides=tuple(args.overrides), trial_fn=args.trial_fn,
                         start_method=args.start_method)
    run_dir = Path(args.run_dir)
    load_before = os.getloadavg()
    t0 = time.monotonic()
    run_benchmark(config, run_dir, fresh=True, progress=not args.no_progress)
    wall = time.monotonic() - t0
    result = summarise(run_dir, config, wall, load_before, os.getloadavg())
    if args.baseline:
        import dataclasses

        b_config = dataclasses.replace(config, overrides=tuple(args.baseline_set))
        b_dir = run_dir.with_name(run_dir.name + "_baseline")
        b_load = os.getloadavg()
        t0 = time.monotonic()
        run_benchmark(b_config, b_dir, fresh=True, progress=not args.no_progress)
        b_wall = time.monotonic() - t0
        b = summarise(b_dir, b_config, b_wall, b_load, os.getloadavg())
        result["baseline"] = {"overrides": list(args.baseline_set), "run_dir": str(b_dir), "wall_s": b["wall_s"],
                              "trials_per_hour": b["trials_per_hour"], "what_ran": b["what_ran"],
                              "objects_success": sum(v["objects_success"] for v in b["per_method"].values()),
                              "objects": sum(v["objects"] for v in b["per_method"].values()),
                              "per_method": b["per_method"], "loadavg_before": b["machine"]["loadavg_before"]}
        result["wall_ratio_vs_baseline"] = round(wall / b_wall, 3) if b_wall > 0 else None
    out = Path(args.results_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    write_markdown(result, out / f"{args.name}.md")
    print(json.dumps({"trials_per_hour": result["trials_per_hour"], "trials": result["trials"],
                      "json": str(out / f"{args.name}.json"), "md": str(out / f"{args.name}.md")}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
