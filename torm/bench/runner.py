"""Run a benchmark grid into a run folder, resumably, one bench per folder at a time.

``run_benchmark(config, out_dir)``:

1. builds the grid (:func:`torm.bench.spec.build_grid`) and lets the trial module resolve the overrides
   into the full base trial config (:func:`torm.bench.spec.validate_for_trial_fn`);
2. checks the folder can be written and takes its lock (:class:`torm.bench.lock.RunLock`): a second
   bench on the same folder is refused with the holder's pid, host and command; a stale lock of a dead
   bench is taken over;
3. opens the run folder: a new folder gets a manifest; an existing one is resumed when its run identity
   (:mod:`torm.bench.identity`: the resolved trial config, the files it names, the benchmark fields and
   the code version: git commit, uncommitted changes, dependency versions) is unchanged, refused with
   the differences listed otherwise, or moved aside first with ``fresh=True`` (nothing is deleted);
   sessions a killed bench left ``running`` are marked ``killed``;
4. cuts an interrupted last line off ``results.jsonl`` (saved aside) and skips every trial whose key
   already has a row; with ``retry="failed"`` it also runs again every trial whose row is ``crashed``,
   ``timeout`` or ``error`` (the new row is the next ``attempt``; the old one stays in the file as history);
5. runs the remaining trials on the engine (``pool``: local isolated processes, ``ray``: Ray tasks),
   appending each row as soon as it finishes, with a tqdm bar (trials done, object success rate so
   far, ETA) on stderr;
6. records the invocation as a "session" in the manifest (start, end, status, trials run, engine, pid).

The summary lists every repair made to the folder (``repairs``): a cut-off last line, skipped corrupted
or duplicated lines, a stale lock, sessions marked killed (each is also logged once, where it is made).

Folder layout: ``manifest.json``, ``results.jsonl``, ``.lock``, ``logs/<key>.log`` (worker logs of failed
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

from torm.bench.identity import grid_hash, identity_hash, run_identity
from torm.bench.isolate import TrialJob
from torm.bench.lock import RunLock
from torm.bench.results import (
    MANIFEST_NAME,
    RESULTS_NAME,
    append_row,
    attempt,
    diff_dicts,
    move_aside,
    read_manifest,
    read_results,
    remove_corrupt_lines,
    repair_tail,
    utc_now,
    write_json_atomic,
)
from torm.bench.rows import RETRY_STATUSES, trial_failed
from torm.bench.spec import BenchConfig, TrialSpec, build_grid, identity, validate_for_trial_fn
from torm.errors import BenchmarkError, ConfigError
from torm.resources import available_memory_bytes, check_fits, gib, trial_bytes
from torm.runtime import free_cores

log = logging.getLogger(__name__)

MANIFEST_FORMAT = "torm-bench/2"
RETRY_MODES = ("failed",)
#: Most Ray tasks kept in flight at once (``workers`` with ``engine="ray"``).
MAX_RAY_WORKERS = 1024


def threads_per_trial(config: BenchConfig) -> int:
    """Threads each trial may use: ``config.threads``, or the free cores shared by the workers (>= 1)."""
    return config.threads or max(1, free_cores() // config.workers)


def bench_identity(config: BenchConfig, resolved: dict[str, Any] | None) -> dict[str, Any]:
    """The benchmark part of the run identity: :data:`torm.bench.spec.IDENTITY_FIELDS`, without the ``--set``
    strings when the trial module resolved them into ``resolved`` (equal configs spelt differently match)."""
    ident = identity(config)
    if resolved is not None:
        ident.pop("overrides", None)
    return ident


def prepare_folder(out_dir: Path) -> None:
    """Create the run folder; BenchmarkError naming the folder when that or writing in it fails."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BenchmarkError(f"cannot create the run folder {out_dir} ({exc.strerror}); choose another --out") from exc
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise BenchmarkError(f"the run folder {out_dir} is not writable; choose another --out or fix its permissions")


def open_run(config: BenchConfig, out_dir: Path, ident: dict[str, Any], fresh: bool = False,
             repairs: list[str] | None = None) -> dict[str, Any]:
    """Create or resume the run folder's manifest for run identity ``ident`` (module docstring); returns it
    (not yet saved). The caller holds the folder's lock. Repairs made are appended to ``repairs``."""
    repairs = repairs if repairs is not None else []
    if fresh:
        moved = move_aside(out_dir)
        if moved is not None:
            repairs.append(f"--fresh: the previous results were moved to {moved}")
    manifest = read_manifest(out_dir)
    results = out_dir / RESULTS_NAME
    digest = identity_hash(ident)
    if manifest is None:
        if results.exists() and results.stat().st_size > 0:
            raise BenchmarkError(f"{results} exists but {out_dir / MANIFEST_NAME} does not, so its config is "
                                 "unknown; choose another --out or pass --fresh to move the old files aside")
        return {"format": MANIFEST_FORMAT, "created": utc_now(), "config": config.as_dict(),
                "identity_hash": digest, "identity": ident, "sessions": []}
    if manifest.get("format") != MANIFEST_FORMAT:
        raise BenchmarkError(f"{out_dir} was written by an older torm bench ({manifest.get('format')!r}, without a "
                             "run identity), so its rows cannot be matched to this config and code; use another "
                             "--out, or pass --fresh (moves the old results aside into old-<time>/)")
    if manifest.get("identity_hash") != digest:
        from torm.bench.results import _clean

        lines = diff_dicts(manifest.get("identity") or {}, _clean(ident)) or ["(the stored identity hash differs)"]
        raise BenchmarkError(
            f"{out_dir} holds results of a different run (trial config, benchmark settings or code); changed:\n  "
            + "\n  ".join(lines)
            + "\nrun with the original config and code to resume, use another --out, or pass --fresh "
              "(moves the old results aside into old-<time>/)")
    grid_diff = diff_dicts({k: manifest["config"].get(k) for k in ("scenarios", "trials", "methods")},
                           {k: config.as_dict()[k] for k in ("scenarios", "trials", "methods")})
    if grid_diff:
        log.info("resuming %s with a changed grid (allowed): %s", out_dir, "; ".join(grid_diff))
    for sess in manifest.get("sessions", []):
        if sess.get("status") == "running":  # we hold the lock: whoever ran it is gone
            sess["status"] = "killed"
            sess["ended"] = sess.get("last_row") or manifest.get("updated") or sess.get("started")
            repairs.append(f"session {sess.get('id')} (pid {sess.get('pid')} on {sess.get('host')}, started "
                           f"{sess.get('started')}) was killed mid-run; marked 'killed' (its last row: "
                           f"{sess.get('last_row') or 'none'})")
            log.warning("%s: %s", out_dir, repairs[-1])
    manifest["config"] = config.as_dict()
    return manifest


def check_workers_fit(config: BenchConfig, resolved: dict[str, Any] | None, available: int | None = None) -> None:
    """Refuse a pool of ``config.workers`` local trial processes that cannot fit in the free memory (each
    needs :func:`torm.resources.trial_bytes` of its capture); Ray tasks run where Ray places them, bounded by
    :data:`MAX_RAY_WORKERS` in flight. Raises ConfigError with the largest worker count that fits."""
    if config.engine == "ray":
        if config.workers > MAX_RAY_WORKERS:
            raise ConfigError(f"workers={config.workers}: at most {MAX_RAY_WORKERS} Ray tasks are kept in flight; "
                              f"use --workers <= {MAX_RAY_WORKERS} (Ray queues the rest of the grid anyway)")
        return
    cap = (resolved or {}).get("capture") or {}
    per = trial_bytes(int(cap.get("n_views", 50)), float(cap.get("scale", 0.5)))
    free = available_memory_bytes() if available is None else available
    fit = max(1, int(free // per)) if free else None
    check_fits(config.workers * per, f"--workers {config.workers} (each trial needs about {gib(per)})",
               f"use --workers {fit} or fewer" if fit else "use fewer workers", free)


def run_benchmark(config: BenchConfig, out_dir: str | Path, fresh: bool = False, progress: bool = True,
                  validate: bool = True, retry: str | None = None) -> dict[str, Any]:
    """Run (or resume) the benchmark into ``out_dir``; returns a summary dict (JSON-ready).

    Args:
        config: the benchmark.
        out_dir: the run folder.
        fresh: move existing results aside and start over instead of resuming.
        progress: show the tqdm bar on stderr.
        validate: let the trial function's module resolve and check ``config.overrides`` first.
        retry: ``"failed"``: also run again the trials whose row is crashed, timeout or error.
    """
    if retry is not None and retry not in RETRY_MODES:
        raise ConfigError(f"retry must be one of {list(RETRY_MODES)}, got {retry!r}")
    out = Path(out_dir)
    grid = build_grid(config)
    resolved = validate_for_trial_fn(config) if validate else None
    check_workers_fit(config, resolved)
    if config.engine == "ray" and config.ray_address:
        from torm.bench.ray_engine import check_address

        check_address(config.ray_address)  # before the run folder: a dead address is refused in seconds
    ident = run_identity(bench_identity(config, resolved), resolved)
    prepare_folder(out)
    with RunLock(out) as lock:
        repairs: list[str] = []
        if lock.stale:
            repairs.append(f"stale lock of a bench that died without releasing it (pid {lock.stale.get('pid')} on "
                           f"{lock.stale.get('host')}, since {lock.stale.get('started')}) was taken over")
        manifest = open_run(config, out, ident, fresh, repairs)
        return _run_locked(config, out, grid, manifest, resolved, retry, repairs, progress)


def _run_locked(config: BenchConfig, out: Path, grid: list[TrialSpec], manifest: dict[str, Any],
                resolved: dict[str, Any] | None, retry: str | None, repairs: list[str],
                progress: bool) -> dict[str, Any]:
    if resolved is not None:
        manifest["trial_config"] = resolved  # the base trial config; scenario/seed/method vary per trial
    results_path = out / RESULTS_NAME
    saved = repair_tail(results_path)
    if saved is not None:
        repairs.append(f"{results_path}: an incomplete last line (interrupted write) was cut off; its bytes are in "
                       f"{saved}")
    existing = read_results(results_path)
    repairs += [p for p in existing.problems if "is incomplete" not in p]  # read_results logged them once
    moved = remove_corrupt_lines(results_path, existing.bad_lines)  # reported once, then out of the file
    if moved is not None:
        repairs.append(f"{results_path}: {len(existing.bad_lines)} corrupted line(s) were moved to {moved}")
    by_key = {r["key"]: r for r in existing.rows}
    retried = [s.key for s in grid if retry == "failed" and by_key.get(s.key, {}).get("status") in RETRY_STATUSES]
    pending = [s for s in grid if s.key not in by_key or s.key in retried]
    threads = threads_per_trial(config)
    session: dict[str, Any] = {
        "id": len(manifest["sessions"]) + 1, "started": utc_now(), "finished": None, "status": "running",
        "engine": config.engine, "workers": config.workers, "threads": threads, "host": platform.node(),
        "pid": os.getpid(), "cpus": os.cpu_count(), "retry": retry, "retried": len(retried),
        "pending_at_start": len(pending), "trials_run": 0, "argv": sys.argv,
    }
    manifest["sessions"].append(session)
    code = manifest["identity"]["code"]
    manifest.update({"updated": utc_now(), "versions": code["packages"], "git": code["git"],
                     "grid": {"n_trials": len(grid), "scenarios": sorted({s.scenario for s in grid}),
                              "methods": list(config.methods), "hash": grid_hash(s.key for s in grid)}})
    write_json_atomic(out / MANIFEST_NAME, manifest)
    job = TrialJob(trial_fn=config.trial_fn, overrides=config.overrides, timeout_s=config.timeout_s,
                   threads=threads, record=config.record, recordings_dir=str(out.resolve() / "recordings"),
                   logs_dir=str(out.resolve() / "logs"), engine=config.engine, session=session["id"],
                   stop_grace_s=config.stop_grace_s,
                   start_method=config.start_method if config.engine == "pool" else "spawn")
    prior = [r for k, r in by_key.items() if k in {s.key for s in grid} and k not in retried]
    n_obj = sum(int(r.get("n_objects") or 0) for r in prior)
    n_ok = sum(int(r.get("n_success") or 0) for r in prior)
    failed = sum(trial_failed(r) for r in prior)
    categories: dict[str, int] = {}
    n_done = len(grid) - len(pending)
    log.info("%s: %d trials in the grid, %d already done, %d to run (%d retried) on %s with %d worker(s), "
             "%d thread(s) each", out, len(grid), n_done, len(pending), len(retried), config.engine, config.workers,
             threads)
    bar = _progress_bar(len(grid), n_done, progress)
    status = "interrupted"
    rows = _engine_rows(config, pending, job)
    moved_to_history = 0  # old rows a retry superseded in this session
    try:
        for row in rows:
            old = by_key.get(row["key"])
            if old is not None:  # a retry: the next attempt, the old row stays in the file as history
                moved_to_history += 1
                row["attempt"] = attempt(old) + 1
                row["retry_of"] = {"status": old.get("status"), "failure": old.get("failure"),
                                   "session": (old.get("run") or {}).get("session")}
            append_row(out / RESULTS_NAME, row)
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
    return {"out": str(out), "trials_in_grid": len(grid), "already_done": n_done, "retried": retried,
            "ran": session["trials_run"], "failed_trials": failed, "objects": n_obj, "objects_success": n_ok,
            "success_rate": n_ok / n_obj if n_obj else None, "failure_categories_this_session": categories,
            "repairs": repairs, "history_rows": len(existing.history) + moved_to_history, "session": session["id"]}


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


__all__ = ["RETRY_MODES", "bench_identity", "open_run", "prepare_folder", "run_benchmark", "threads_per_trial"]
