"""Run a benchmark grid into a run folder, resumably.

``run_benchmark(config, out_dir)``:

1. builds the grid (:func:`torm.bench.spec.build_grid`) and lets the trial module check the overrides;
2. opens the run folder: a new folder gets a manifest; an existing one is resumed when its config
   identity (:data:`torm.bench.spec.IDENTITY_FIELDS`) is unchanged, refused with the differences
   listed otherwise, or moved aside first with ``fresh=True`` (nothing is deleted);
3. cuts an interrupted last line off ``results.jsonl`` (saved aside) and skips every trial whose key
   already has a row, so re-running the same command continues where it stopped and never
   duplicates a trial;
4. runs the remaining trials on the engine (``pool``: local isolated processes, ``ray``: Ray tasks),
   appending each row as soon as it finishes, with a tqdm bar (trials done, object success rate so
   far, ETA) on stderr;
5. records the invocation as a "session" in the manifest (start, end, trials run, engine, git).

Folder layout: ``manifest.json``, ``results.jsonl``, ``logs/<key>.log`` (worker logs of failed
trials), ``recordings/<key>.rrd`` (with ``record`` on), ``old-<time>/`` (what ``fresh`` moved aside).
"""

from __future__ import annotations

import logging
import os
import platform
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from torm.bench.isolate import TrialJob
from torm.bench.results import (
    MANIFEST_NAME,
    RESULTS_NAME,
    append_row,
    diff_dicts,
    git_revision,
    move_aside,
    package_versions,
    read_manifest,
    read_results,
    repair_tail,
    utc_now,
    write_json_atomic,
)
from torm.bench.rows import trial_failed
from torm.bench.spec import BenchConfig, TrialSpec, build_grid, config_hash, identity, validate_for_trial_fn
from torm.errors import BenchmarkError
from torm.runtime import free_cores

log = logging.getLogger(__name__)

MANIFEST_FORMAT = "torm-bench/1"


def threads_per_trial(config: BenchConfig) -> int:
    """Threads each trial may use: ``config.threads``, or the free cores shared by the workers (>= 1)."""
    return config.threads or max(1, free_cores() // config.workers)


def open_run(config: BenchConfig, out_dir: Path, grid: list[TrialSpec], fresh: bool = False) -> dict[str, Any]:
    """Create or resume the run folder's manifest (see the module docstring); returns it (not yet saved)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if fresh:
        move_aside(out_dir)
    manifest = read_manifest(out_dir)
    results = out_dir / RESULTS_NAME
    if manifest is None:
        if results.exists() and results.stat().st_size > 0:
            raise BenchmarkError(f"{results} exists but {out_dir / MANIFEST_NAME} does not, so its config is "
                                 "unknown; choose another --out or pass --fresh to move the old files aside")
        return {"format": MANIFEST_FORMAT, "created": utc_now(), "config": config.as_dict(),
                "config_hash": config_hash(config), "identity": identity(config), "sessions": []}
    old_identity = manifest.get("identity") or {}
    if manifest.get("config_hash") != config_hash(config):
        lines = diff_dicts(old_identity, identity(config)) or ["(the stored config hash differs)"]
        raise BenchmarkError(
            f"{out_dir} holds results of a different benchmark config; changed:\n  " + "\n  ".join(lines)
            + "\nrun with the original settings to resume, use another --out, or pass --fresh "
              "(moves the old results aside into old-<time>/)")
    grid_diff = diff_dicts({k: manifest["config"].get(k) for k in ("scenarios", "trials", "methods")},
                           {k: config.as_dict()[k] for k in ("scenarios", "trials", "methods")})
    if grid_diff:
        log.info("resuming %s with a changed grid (allowed): %s", out_dir, "; ".join(grid_diff))
    manifest["config"] = config.as_dict()
    return manifest


def run_benchmark(config: BenchConfig, out_dir: str | Path, fresh: bool = False, progress: bool = True,
                  validate: bool = True) -> dict[str, Any]:
    """Run (or resume) the benchmark into ``out_dir``; returns a summary dict (JSON-ready).

    Args:
        config: the benchmark.
        out_dir: the run folder.
        fresh: move existing results aside and start over instead of resuming.
        progress: show the tqdm bar on stderr.
        validate: let the trial function's module check ``config.overrides`` first.
    """
    out = Path(out_dir)
    grid = build_grid(config)
    resolved = validate_for_trial_fn(config) if validate else None
    manifest = open_run(config, out, grid, fresh)
    if resolved is not None:
        manifest["trial_config"] = resolved  # the base trial config; scenario/seed/method vary per trial
    results_path = out / RESULTS_NAME
    repair_tail(results_path)
    existing = read_results(results_path)
    for problem in existing.problems:
        log.warning("%s", problem)
    done_keys = existing.keys
    pending = [s for s in grid if s.key not in done_keys]
    threads = threads_per_trial(config)
    session: dict[str, Any] = {
        "id": len(manifest["sessions"]) + 1, "started": utc_now(), "finished": None, "status": "running",
        "engine": config.engine, "workers": config.workers, "threads": threads, "host": platform.node(),
        "cpus": os.cpu_count(), "git": git_revision(), "versions": package_versions(),
        "pending_at_start": len(pending), "trials_run": 0, "argv": sys.argv,
    }
    manifest["sessions"].append(session)
    manifest.update({"updated": utc_now(), "versions": session["versions"], "git": session["git"],
                     "grid": {"n_trials": len(grid), "scenarios": sorted({s.scenario for s in grid}),
                              "methods": list(config.methods)}})
    write_json_atomic(out / MANIFEST_NAME, manifest)
    job = TrialJob(trial_fn=config.trial_fn, overrides=config.overrides, timeout_s=config.timeout_s,
                   threads=threads, record=config.record, recordings_dir=str(out.resolve() / "recordings"),
                   logs_dir=str(out.resolve() / "logs"), engine=config.engine, session=session["id"])
    grid_keys = {s.key for s in grid}
    prior = [r for r in existing.rows if r["key"] in grid_keys]
    n_obj = sum(int(r.get("n_objects") or 0) for r in prior)
    n_ok = sum(int(r.get("n_success") or 0) for r in prior)
    failed = sum(trial_failed(r) for r in prior)
    categories: dict[str, int] = {}
    log.info("%s: %d trials in the grid, %d already done, %d to run on %s with %d worker(s), %d thread(s) each",
             out, len(grid), len(grid) - len(pending), len(pending), config.engine, config.workers, threads)
    bar = _progress_bar(len(grid), len(grid) - len(pending), progress)
    status = "interrupted"
    rows = _engine_rows(config, pending, job)
    try:
        for row in rows:
            append_row(results_path, row)
            session["trials_run"] += 1
            n_obj += int(row.get("n_objects") or 0)
            n_ok += int(row.get("n_success") or 0)
            if trial_failed(row):
                failed += 1
            if row.get("failure"):
                categories[row["failure"]] = categories.get(row["failure"], 0) + 1
            if bar is not None:
                bar.set_postfix_str(f"success {n_ok}/{n_obj} objects ({100.0 * n_ok / max(n_obj, 1):.0f}%), "
                                    f"{failed} failed trials", refresh=False)
                bar.update(1)
            session["last_row"] = utc_now()
            write_json_atomic(out / MANIFEST_NAME, manifest)
        status = "finished"
    except BaseException:
        status = "interrupted"
        raise
    finally:
        rows.close()
        if bar is not None:
            bar.close()
        session["finished"] = utc_now()
        session["status"] = status
        manifest["updated"] = session["finished"]
        write_json_atomic(out / MANIFEST_NAME, manifest)
    return {"out": str(out), "trials_in_grid": len(grid), "already_done": len(grid) - len(pending),
            "ran": session["trials_run"], "failed_trials": failed, "objects": n_obj, "objects_success": n_ok,
            "success_rate": n_ok / n_obj if n_obj else None, "failure_categories_this_session": categories,
            "problems": existing.problems, "session": session["id"]}


def _engine_rows(config: BenchConfig, pending: list[TrialSpec], job: TrialJob) -> Iterator[dict[str, Any]]:
    if config.engine == "ray":
        from torm.bench.ray_engine import ray_rows

        return ray_rows(pending, job, config.workers, config.ray_address)
    from torm.bench.pool import pool_rows

    return pool_rows(pending, job, config.workers)


def _progress_bar(total: int, initial: int, enabled: bool) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="trial", desc="bench", file=sys.stderr, dynamic_ncols=True,
                smoothing=0.1)


__all__ = ["open_run", "run_benchmark", "threads_per_trial"]
