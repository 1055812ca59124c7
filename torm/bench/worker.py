"""The child side of an isolated trial: ``python -m torm.bench.worker JOB.json``.

JOB.json holds ``{"spec": TrialSpec dict, "overrides": [...], "trial_fn": "module:function",
"record_path": str or null, "result_path": str, "parent_pid": int}``. The worker calls
``trial_fn(spec, overrides, record_path)`` and writes ``{"status": "ok", "record": {...}}`` or, when the
function raises, ``{"status": "error", "failure": category, "message": ..., "traceback": ...}`` to
``result_path`` (atomically), then leaves with ``os._exit(0)`` so no library teardown can hang it.
Anything that kills the process before that (segfault, ``os._exit``, the OOM killer) leaves no result
file: the parent records ``crashed``.

Stopping: SIGTERM raises :class:`TrialTerminated` in the trial (once; later SIGTERMs are ignored so the
clean-up is not cut short), so every ``finally`` runs: ``run_trial`` closes its backend, and the real
backend's ``close`` cancels the arm's motion and disables it. The runner sends SIGTERM on a timeout, on
Ctrl-C / SIGTERM of the bench and when the runner fails, and SIGKILLs after its grace period. A
watchdog thread notices when the parent died (a SIGKILLed runner) and stops the worker the same way
(SIGTERM to itself, SIGKILL-equivalent ``os._exit`` after ``stop_grace_s``), so no orphan computes (or
moves an arm) for nobody.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any

log = logging.getLogger("torm.bench.worker")


class TrialTerminated(BaseException):  # noqa: N818 - like KeyboardInterrupt, a request to stop, not an error
    """Raised in the trial by SIGTERM: a BaseException, so ``except Exception`` in a trial does not swallow it."""


def install_sigterm_handler() -> None:
    """SIGTERM raises :class:`TrialTerminated` in the main thread, the first time only."""

    def handler(signum: int, frame: Any) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the clean-up must not be interrupted again
        raise TrialTerminated(f"worker {os.getpid()} received SIGTERM")

    signal.signal(signal.SIGTERM, handler)


def failure_category(exc: BaseException) -> str:
    """The recorded category of an exception that escaped a trial function."""
    names = {c.__name__ for c in type(exc).__mro__}
    if "PhysicsError" in names or isinstance(exc, FloatingPointError):
        return "physics_error"
    if "ReconstructionError" in names:
        return "reconstruction_failed"
    if "ConfigError" in names or "UnknownNameError" in names:
        return "config_error"
    if isinstance(exc, MemoryError):
        return "out_of_memory"
    return "error"


ORPHANED = threading.Event()


def _watch_parent(parent: int, scratch: Path | None = None, interval_s: float = 1.0, grace_s: float = 10.0) -> None:
    """Once ``parent`` is gone: SIGTERM this process (the trial's clean-up runs), and after ``grace_s``
    remove the job's scratch folder (which the dead parent cannot) and exit.

    ``parent`` is the pid the runner wrote into the job, so a parent that died before this thread
    started is noticed too (``os.getppid()`` would already name the reaper).
    """

    def loop() -> None:
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent:
                ORPHANED.set()
                log.error("the benchmark runner (pid %d) is gone; stopping the trial", parent)
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(grace_s)
                if scratch is not None:
                    shutil.rmtree(scratch, ignore_errors=True)
                os._exit(137)

    threading.Thread(target=loop, name="parent-watchdog", daemon=True).start()


def _write_atomic(path: Path, data: dict[str, Any]) -> None:
    from torm.bench.results import _clean

    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(_clean(data), f, allow_nan=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def run_job(job: dict[str, Any]) -> dict[str, Any]:
    """Run the job's trial function in this process; returns the result dict (never raises)."""
    from torm.bench.spec import TrialSpec, load_trial_fn

    spec = TrialSpec.from_dict(job["spec"])
    try:
        fn = load_trial_fn(job["trial_fn"])
        record = fn(spec, tuple(job.get("overrides", ())), job.get("record_path"))
        if not isinstance(record, dict):
            raise TypeError(f"trial function {job['trial_fn']} returned {type(record).__name__}, not a dict")
        return {"status": "ok", "record": record}
    except (TrialTerminated, KeyboardInterrupt) as exc:  # a request to stop from outside, not a failure of the trial
        how = "SIGTERM" if isinstance(exc, TrialTerminated) else "SIGINT"
        log.error("trial %s stopped by %s: %s", spec.key, how, exc)
        return {"status": "error", "failure": "terminated", "message": f"stopped by {how}" + (f" ({exc})" if str(exc)
                                                                                                else ""),
                "traceback": traceback.format_exc()[-4000:]}
    except Exception as exc:  # noqa: BLE001 - every failure becomes a recorded category
        tb = traceback.format_exc()
        log.error("trial %s failed: %s", spec.key, tb)
        return {"status": "error", "failure": failure_category(exc),
                "message": f"{type(exc).__name__}: {exc}", "traceback": tb[-4000:]}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        sys.stderr.write("usage: python -m torm.bench.worker JOB.json\n")
        return 2
    install_sigterm_handler()
    # SIGINT stops the trial like SIGTERM does (recorded as ``terminated``), also when the worker was started with
    # SIGINT ignored (a background job inherits SIG_IGN, and Python then installs no handler); the worker runs in its
    # own session, so a terminal's Ctrl-C never reaches it: only a deliberate signal does.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    job_path = Path(args[0])
    job = json.loads(job_path.read_text())
    scratch = job_path.parent if job_path.parent.name.startswith("torm-trial-") else None
    logging.basicConfig(level=os.environ.get("TORM_BENCH_LOG_LEVEL", "INFO"), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    _watch_parent(int(job.get("parent_pid") or os.getppid()), scratch, grace_s=float(job.get("stop_grace_s", 10.0)))
    result = run_job(job)
    if ORPHANED.is_set():  # nobody reads the result: clean up and leave
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        return 137
    with contextlib.suppress(TrialTerminated):  # a SIGTERM now: the runner decides the row without a result
        _write_atomic(Path(job["result_path"]), result)
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
