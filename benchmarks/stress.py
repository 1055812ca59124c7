"""Margins, not tuning: success curves as each realism factor group is pushed beyond its sourced range.

For each factor group of the ``measured`` profile (``sim/realism.py``: contact, grip force, objects, calibration,
execution), the rw suite runs with that group alone at the ``stress`` profile's levels (``world.realism=stress``,
``world.stress=k``: every parameter of the group at the worst end of its sourced range, pushed k times further;
k = 1 is the worst *sourced* value, k = 2 and 4 are **stress, not realism**), beside the ideal world (k = 0 in the
plots). The curves show how much margin each factor has and where slip, displacement or pruning begins. Nothing is
fitted to the paper: the sourced ``measured`` profile stays the default of every benchmark.

Grip force: the 2F-85 cannot grip below 20 N (its force register's floor, HARDWARE.md; the simulated gripper's
``gripper_force_range``), so a level whose pad force lies below the floor would be clipped to 20 N and test nothing
beyond x1: such levels are not run, and the report says why.

What the loop sees is the default trial's (simulator masks, MuJoCo renders, ideal depth) unless ``--set KEY=VALUE``
(repeatable; e.g. ``segmentation.segmenter=learned``, ``capture.renderer=pbr``) changes it for every run; the
report's header names what produced the rows from their context records.

Written: ``benchmarks/results/stress[_<tag>].json``, ``.md`` and ``.png``. Run folders under ``runs/stress[_<tag>]/``
are resumable. Run: ``MUJOCO_GL=egl nice -n 15 python benchmarks/stress.py [--trials 5] [--levels 1,2,4]
[--workers 2] [--set KEY=VALUE] [--tag NAME]``; ``--report-only`` rewrites the report from the run folders.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import check_tag  # noqa: E402
from benchmarks.fidelity import FAILURE_MODES  # noqa: E402
from torm.bench import BenchConfig, run_benchmark  # noqa: E402
from torm.bench.report import load_run  # noqa: E402
from torm.bench.results import git_revision, package_versions  # noqa: E402
from torm.bench.spec import DEFAULT_TRIAL_FN  # noqa: E402
from torm.bench.stats import wilson_interval  # noqa: E402
from torm.errors import BenchmarkError  # noqa: E402
from torm.pipeline import REALISM_FACTORS as FACTORS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RUNS = ROOT / "runs"
#: the context keys that say what produced a row (the report's header)
WHAT_RAN = ("segmenter", "segmenter_model", "segmenter_postprocess", "renderer", "render_spp", "render_scale",
            "depth_model", "reconstruction_mode", "table")


def grip_floor_n() -> float:
    """The simulated 2F-85's lowest pad force (N): commands below it are clipped to it."""
    from sim.backend import SimBackendConfig

    return float(SimBackendConfig().gripper_force_range[0])


def below_floor(group: str, level: float) -> bool:
    """True when ``group`` at ``level`` asks for a pad force the gripper cannot command (the level tests nothing)."""
    from sim.realism import MEASURED

    return group == "grip_force" and MEASURED.stressed(level).grip_force.lo < grip_floor_n() - 1e-9


def what_ran(contexts: list[str]) -> str:
    """``key value`` pairs of :data:`WHAT_RAN` over the rows' context records (several values joined by " / ")."""
    ctx = [json.loads(c) for c in contexts if c and c != "null"]
    parts = []
    for k in WHAT_RAN:
        vals = sorted({str(c.get(k)) for c in ctx if c.get(k) is not None})
        if vals:
            parts.append(f"{k} {' / '.join(vals)}")
    return ", ".join(parts) or "unknown (no context in the rows)"


def _rate(k: int, n: int) -> dict[str, Any]:
    lo, hi = wilson_interval(k, n)
    return {"k": k, "n": n, "rate": k / n if n else None, "wilson95": [lo, hi]}


def _kind(outcome: str) -> str:
    return next((key for key, _, outcomes in FAILURE_MODES if outcome in outcomes), "other")


def level_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Object and trial success with Wilson intervals, failures by kind, the realism values used."""
    objs = [o for r in rows for o in r.get("objects", [])]
    k = sum(o.get("outcome") == "success" for o in objs)
    kinds: dict[str, int] = defaultdict(int)
    for o in objs:
        if o.get("outcome") != "success":
            kinds[_kind(o.get("outcome", "other"))] += 1
    phantoms = sum(int(r.get("n_phantom_attempts") or 0) for r in rows)
    if phantoms:
        kinds["phantom"] += phantoms
    trials_ok = sum(bool(r.get("objects")) and all(o.get("outcome") == "success" for o in r["objects"]) for r in rows)
    grip = [((o.get("pick") or {}).get("grip_force") or {}) for o in objs]
    commanded = [g.get("commanded_n") for g in grip if g.get("commanded_n") is not None]
    requested = [g.get("requested_n") for g in grip if g.get("requested_n") is not None]
    return {"objects": _rate(k, len(objs)), "trials": _rate(trials_ok, len(rows)), "failures": dict(kinds),
            "grip_requested_n": min(requested) if requested else None,
            "grip_commanded_n": min(commanded) if commanded else None,
            "contexts": sorted({json.dumps(r.get("context"), sort_keys=True) for r in rows})}


def write_markdown(doc: dict[str, Any], path: Path) -> None:
    cfg, s = doc["config"], doc["summary"]
    levels = ["ideal"] + [f"x{lv:g}" for lv in cfg["levels"]]
    contexts = sorted({c for g in s.values() for e in g.values() if isinstance(e, dict) for c in e.get("contexts", [])})
    L = ["# Margins: success as each realism factor group is pushed beyond its sourced range", "",
         f"Suite rw, {cfg['trials']} trial(s) per scenario, method `{cfg['method']}` ({what_ran(contexts)}; "
         f"overrides: {', '.join(f'`{o}`' for o in cfg.get('overrides') or []) or 'none'}), one factor group at a "
         "time, the others ideal. Level x1 = every parameter of the group at "
         "the worst end of its sourced range (`sim/REALISM.md`); x2 and x4 push it two and four times further "
         "(`world.realism=stress`): **stress, not realism**. Cells: objects picked / attempted [Wilson 95 %]; "
         "failures by kind (slip, displaced, pruned, not seen, phantom, other). "
         f"Report {doc['date']}; the rows ran on git {', '.join(doc.get('run_git') or ['?'])} (the run folders' "
         "identity).", "",
         "| factor group | " + " | ".join(levels) + " |", "|---|" + "---|" * len(levels)]
    for group in cfg["groups"]:
        cells = []
        for lv in levels:
            e = s.get(group, {}).get(lv)
            if e and e.get("skipped"):
                cells.append(f"not run ({e['skipped']})")
                continue
            if not e:
                cells.append("–")
                continue
            o = e["objects"]
            f = ", ".join(f"{k} {v}" for k, v in sorted(e["failures"].items()))
            cells.append(f"{o['k']}/{o['n']} [{100 * o['wilson95'][0]:.0f}-{100 * o['wilson95'][1]:.0f}%]"
                         + (f"; {f}" if f else ""))
        L.append(f"| {group} | " + " | ".join(cells) + " |")
    L += ["", "Values at each level (the worst end of each sourced range times the level; "
              "`MeasuredRanges.stressed`):", ""]
    for group in cfg["groups"]:
        L.append(f"- **{group}**: " + "; ".join(f"x{lv}: {txt}" for lv, txt in doc["values"][group].items()))
    g = s.get("grip_force", {})
    clipped = [lv for lv, e in g.items() if e.get("grip_requested_n") is not None and e.get("grip_commanded_n")
               is not None and e["grip_commanded_n"] > e["grip_requested_n"] + 1e-6]
    skipped = [lv for lv, e in g.items() if e.get("skipped")]
    if clipped or skipped:
        L += ["", f"Grip force: at {', '.join(clipped + skipped)} the requested pad force lies below the 2F-85's "
                  f"{grip_floor_n():g} N floor; the gripper would command {grip_floor_n():g} N (its range), so those "
                  "levels test nothing beyond x1" + (" and were not run." if skipped else ".")]
    L += ["", f"Plot: `{Path(doc['plot']).name}`.", "",
          "Versions: " + ", ".join(f"{k} {v}" for k, v in doc["versions"].items() if v) + "."]
    path.write_text("\n".join(L) + "\n")


def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg, s = doc["config"], doc["summary"]
    xs = [0.0] + list(cfg["levels"])
    fig, ax = plt.subplots(figsize=(7, 4))
    for group in cfg["groups"]:
        pts = [(x, s[group][lv]) for x, lv in zip(xs, ["ideal"] + [f"x{v:g}" for v in cfg["levels"]], strict=True)
               if "objects" in s.get(group, {}).get(lv, {})]
        if not pts:
            continue
        r = [e["objects"]["rate"] for _, e in pts]
        lo = [e["objects"]["rate"] - e["objects"]["wilson95"][0] for _, e in pts]
        hi = [e["objects"]["wilson95"][1] - e["objects"]["rate"] for _, e in pts]
        ax.errorbar([x for x, _ in pts], r, yerr=[lo, hi], marker="o", capsize=3, label=group)
    ax.axvspan(0, 1, color="0.92", zorder=0, label="sourced range")
    ax.set_xticks(xs)
    ax.set_xticklabels(["ideal"] + [f"x{v:g}" for v in cfg["levels"]])
    ax.set_xlabel("stress level (x1 = worst end of the sourced range)")
    ax.set_ylabel("objects picked (Wilson 95 %)")
    ax.set_ylim(0, 1.05)
    ax.set_title(f"Margins per realism factor group (rw, {cfg['method']})")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def level_values(group: str, level: float) -> str:
    """The realism values a group takes at ``level`` (for the report)."""
    from sim.realism import MEASURED

    r = MEASURED.stressed(level)
    names = [row["parameter"] for row in MEASURED.table() if group in row["factor"].split(", ")]
    return ", ".join(f"{n} {getattr(r, n).lo:.4g}{(' ' + getattr(r, n).unit) if getattr(r, n).unit else ''}"
                     for n in names)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2, help="trials per scenario, level and group")
    ap.add_argument("--levels", default="1,2,4", help="stress multipliers (>= 1)")
    ap.add_argument("--groups", default=",".join(FACTORS))
    ap.add_argument("--method", default="torm")
    ap.add_argument("--scenario", action="append", default=[], help="subset of rw (default all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--trial-fn", default=DEFAULT_TRIAL_FN)
    ap.add_argument("--runs-dir", default="", help="run folders (default runs/stress[_<tag>])")
    ap.add_argument("--results-dir", default=str(RESULTS))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a trial-config override for every run (e.g. segmentation.segmenter=learned)")
    ap.add_argument("--tag", default="", help="write stress_<tag>.* and run into runs/stress_<tag>/")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--fresh", action="store_true")
    args = ap.parse_args(argv)
    stem = f"stress_{check_tag(args.tag)}" if args.tag else "stress"
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    levels = [float(v) for v in args.levels.split(",") if v]
    groups = [g for g in args.groups.split(",") if g]
    common = dict(suite="rw", scenarios=tuple(args.scenario), workers=args.workers, timeout_s=args.timeout,
                  threads=args.threads, trials=args.trials, methods=(args.method,), trial_fn=args.trial_fn)
    runs = Path(args.runs_dir) if args.runs_dir else RUNS / stem
    extra = tuple(args.overrides)
    plan: dict[tuple[str, str], tuple[BenchConfig, Path]] = {
        ("*", "ideal"): (BenchConfig(overrides=(*extra, "world.realism=ideal"), **common), runs / "ideal")}
    skipped: dict[tuple[str, str], str] = {}
    for g in groups:
        for lv in levels:
            if below_floor(g, lv):
                skipped[(g, f"x{lv:g}")] = f"below the gripper's {grip_floor_n():g} N floor"
                continue
            ov = (*extra, "world.realism=stress", f"world.stress={lv:g}", f"world.factors=[{g}]")
            plan[(g, f"x{lv:g}")] = (BenchConfig(overrides=ov, **common), runs / f"{g}_x{lv:g}")
    if not args.report_only:
        for (g, lv), (cfg, folder) in plan.items():
            logging.info("stress %s %s -> %s", g, lv, folder)
            run_benchmark(cfg, folder, fresh=args.fresh)
    summary: dict[str, dict[str, Any]] = defaultdict(dict)
    ideal = None
    run_git: set[str] = set()
    for (g, lv), (_, folder) in plan.items():
        try:
            run = load_run(folder)
        except BenchmarkError:
            logging.warning("no rows in %s yet", folder)
            continue
        rows = run.rows
        git = ((run.manifest.get("identity") or {}).get("code") or {}).get("git") or {}
        run_git.add(str(git.get("commit"))[:7] + (" (dirty)" if git.get("dirty") else ""))
        if g == "*":
            ideal = level_summary(rows)
        else:
            summary[g][lv] = level_summary(rows)
    for (g, lv), why in skipped.items():
        summary[g][lv] = {"skipped": why}
    for g in groups:
        if ideal is not None:
            summary[g] = {"ideal": ideal, **summary[g]}
    out = Path(args.results_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"config": {"trials": args.trials, "levels": levels, "groups": groups, "method": args.method,
                      "scenarios": args.scenario, "workers": args.workers, "overrides": list(extra)},
           "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
           "versions": package_versions(), "git": git_revision(), "run_git": sorted(run_git), "summary": summary,
           "values": {g: {f"{lv:g}": level_values(g, lv) for lv in levels} for g in groups},
           "run_folders": {f"{g}:{lv}": str(f) for (g, lv), (_, f) in plan.items()},
           "plot": str(out / f"{stem}.png")}
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1) + "\n")
    plot(doc, Path(doc["plot"]))
    write_markdown(doc, out / f"{stem}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
