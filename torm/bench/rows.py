"""Result rows: a trial function's record wrapped with the grid cell, or a failure row for a trial
that never returned.

Row format (one ``results.jsonl`` line)::

    {"key": "rw/rw3/0/torm", "suite": "rw", "scenario": "rw3", "trial": 0, "method": "torm",
     "seed": 1234567, "status": "ok" | "error" | "timeout" | "crashed",
     "failure": null | "<category>", "message": "...",
     ... every other field of the trial record (run_trial: config, versions, backend, timings {stage: s},
         perception {...}, objects [{object_id, name, outcome, message, pick}], spurious_objects) ...
     "n_objects": 3, "n_success": 2, "success_rate": 0.667,
     "run": {"engine", "worker", "started", "finished", "wall_s", "threads", "session", "log", "recording"}}

``status`` says whether the trial function returned (``ok``) or not; ``failure`` is the trial's own
failure category (e.g. ``physics_error`` from run_trial) or the runner's (``timeout``, ``crashed``,
``error``, ``physics_error``, ``reconstruction_failed``, ``config_error``, ``out_of_memory``,
``terminated``: the worker got SIGTERM or SIGINT from outside the runner). A trial that never returned gets one
object entry per scenario object with ``outcome`` = the category, so per-object success counts stay
honest (a timed-out trial counts its objects as failed). A row written by ``--retry failed`` carries
``attempt`` (2, 3, ...) and ``retry_of`` (the replaced row's status, failure and session).
``run`` is the only part that depends on how the trial ran (engine, worker, times); comparisons
ignore it (:func:`torm.bench.results.comparable`).
"""

from __future__ import annotations

from typing import Any

from torm.bench.spec import TrialSpec

SPEC_KEYS = ("key", "suite", "scenario", "trial", "method", "seed")
RUNNER_CATEGORIES = ("timeout", "crashed", "error", "physics_error", "reconstruction_failed", "config_error",
                     "out_of_memory", "terminated")
#: Row statuses ``torm bench --retry failed`` runs again: the trial function never returned a record.
RETRY_STATUSES = ("crashed", "timeout", "error")


def _head(spec: TrialSpec) -> dict[str, Any]:
    return {"key": spec.key, "suite": spec.suite, "scenario": spec.scenario, "trial": spec.trial,
            "method": spec.method, "seed": spec.seed}


def ok_row(spec: TrialSpec, record: dict[str, Any]) -> dict[str, Any]:
    """Wrap a trial function's record; the grid cell's fields win over the record's own copies."""
    row = _head(spec)
    row["status"] = "ok"
    row["failure"] = None
    for k, v in record.items():
        if k not in SPEC_KEYS and k not in ("status", "run"):
            row[k] = v
    objs = row.get("objects") or []
    row["objects"] = objs
    row.setdefault("n_objects", len(objs))
    row.setdefault("n_success", sum(1 for o in objs if o.get("outcome") == "success"))
    row.setdefault("success_rate", row["n_success"] / row["n_objects"] if row["n_objects"] else 0.0)
    row.setdefault("timings", {})
    return row


def failure_row(spec: TrialSpec, status: str, category: str, message: str) -> dict[str, Any]:
    """A row for a trial that did not return a record (timeout, crash, exception)."""
    row = _head(spec)
    row.update({
        "status": status, "failure": category, "message": message, "timings": {},
        "objects": [{"object_id": i + 1, "name": name, "outcome": category, "message": message}
                    for i, name in enumerate(spec.objects)],
        "n_objects": len(spec.objects), "n_success": 0, "success_rate": 0.0,
    })
    return row


def trial_failed(row: dict[str, Any]) -> bool:
    """True unless the trial returned and every object was picked successfully."""
    return (row.get("status") != "ok" or bool(row.get("failure")) or not row.get("n_objects")
            or row.get("n_success", 0) < row.get("n_objects", 0))


__all__ = ["RETRY_STATUSES", "RUNNER_CATEGORIES", "SPEC_KEYS", "failure_row", "ok_row", "trial_failed"]
