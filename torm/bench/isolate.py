"""Run one trial in its own fresh Python process with a wall-clock limit and turn whatever happens
into a result row.

Why a fresh interpreter per trial (``subprocess`` running ``python -m torm.bench.worker``, the
equivalent of multiprocessing's "spawn" context): MuJoCo's EGL contexts and torch's thread pools do
not survive ``fork`` after threads, a segfault or a leaked GL context must not take the runner or the
next trial with it, and a hung trial can only be stopped reliably by killing its process. The worker
runs in its own session (process group). A worker that must stop (its timeout, Ctrl-C or SIGTERM of
the runner, an error in the runner) first gets SIGTERM, which the worker turns into an exception in
the trial so its ``finally`` blocks run (a real backend's ``close`` cancels the arm's motion and
disables it), and ``stop_grace_s`` to exit before the whole group is SIGKILLed.

Costs one interpreter start per trial plus the trial's own imports: about 2.4 s on a 2-core machine
(torch 1.3 s), a tenth of a realistic closed-loop trial. ``TrialJob.start_method="forkserver"`` pays the
imports once: each worker is then a fork of a server that imported them and never started a thread
(:mod:`torm.bench.forkserver`); its own session, log, SIGTERM handling and result file are the same.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torm.bench.results import utc_now
from torm.bench.rows import failure_row, ok_row, trial_failed
from torm.bench.spec import TrialSpec
from torm.vocabulary import START_METHODS

log = logging.getLogger(__name__)

LOG_TAIL_CHARS = 2000
THREAD_ENV = ("TORM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


@dataclass(frozen=True)
class TrialJob:
    """How to run one trial (everything but the spec). Times in s.

    Attributes:
        trial_fn: ``module:function`` of the trial function.
        overrides: ``a.b=c`` trial config overrides.
        timeout_s: wall-clock limit; the process group is killed after it.
        threads: torch/BLAS threads of the worker (exported as TORM_THREADS, OMP_NUM_THREADS, ...).
        record: ``none`` | ``failures`` | ``all``.
        recordings_dir: where ``<key>.rrd`` recordings go (when ``record`` is not ``none``).
        logs_dir: where the worker's log is kept for failed trials (None: not kept).
        engine: recorded in the row's ``run`` metadata.
        session: the runner session id, recorded in ``run``.
        stop_grace_s: SIGTERM -> SIGKILL grace of a worker that must stop (timeout, cancel).
        start_method: ``spawn`` (a fresh interpreter per trial) or ``forkserver`` (a fork of a server that
            imported the libraries once; falls back to ``spawn``, with a warning, where the server cannot start).
    """

    trial_fn: str
    overrides: tuple[str, ...] = ()
    timeout_s: float = 1800.0
    threads: int = 1
    record: str = "none"
    recordings_dir: str | None = None
    logs_dir: str | None = None
    engine: str = "pool"
    session: int = 0
    stop_grace_s: float = 10.0
    start_method: str = "spawn"

    def __post_init__(self) -> None:
        if self.start_method not in START_METHODS:
            from torm.errors import UnknownNameError

            raise UnknownNameError("start_method", self.start_method, START_METHODS)


@dataclass
class Canceller:
    """Lets the runner stop every running worker (Ctrl-C, SIGTERM, an error in the runner)."""

    stop: threading.Event = field(default_factory=threading.Event)
    running: set[subprocess.Popen] = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)
    grace_s: float = 10.0

    def cancel(self) -> None:
        """SIGTERM every running worker at once, wait up to ``grace_s`` for all, SIGKILL the rest.

        A second Ctrl-C while waiting skips the rest of the grace period (SIGKILL now).
        """
        self.stop.set()
        with self.lock:
            procs = list(self.running)
        stop_groups(procs, self.grace_s)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(sig)


def stop_groups(procs: list[subprocess.Popen], grace_s: float) -> None:
    """SIGTERM the process groups of ``procs``, give them ``grace_s`` s to exit, then SIGKILL what is left."""
    for p in procs:
        if p.poll() is None:
            _signal_group(p, signal.SIGTERM)
    deadline = time.monotonic() + max(0.0, grace_s)
    try:
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
    finally:  # also when a second Ctrl-C cuts the grace period short
        for p in procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)  # the group: grandchildren too
            with contextlib.suppress(ProcessLookupError):
                p.kill()
            p.wait()


def safe_name(key: str) -> str:
    """A file name for a trial key (``rw/rw3/0/torm`` -> ``rw__rw3__0__torm``)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in key.replace("/", "__"))


def _signal_name(rc: int) -> str:
    try:
        return signal.Signals(-rc).name
    except ValueError:
        return f"signal {-rc}"


def _tail(path: Path, n: int = LOG_TAIL_CHARS) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - n))
            return f.read().decode(errors="replace")
    except OSError:
        return ""


def run_isolated(spec: TrialSpec, job: TrialJob, canceller: Canceller | None = None) -> dict[str, Any]:
    """Run ``spec`` in a fresh worker process and return its result row (never raises for trial failures).

    Categories: the trial function's record (``status`` ok), ``error``/``physics_error``/... when it
    raised, ``timeout`` when it ran past ``job.timeout_s`` (then it got SIGTERM and ``job.stop_grace_s``
    before SIGKILL), ``crashed`` when the process died without a
    result (segfault, ``os._exit``, OOM kill; the message names the signal or exit code). The row's
    ``run`` holds the worker's pid, times, return code and, for failed trials, the tail of its log
    (``log_tail``) and the kept log file (``log``).
    """
    scratch = Path(tempfile.mkdtemp(prefix="torm-trial-"))
    job_path, result_path, log_path = scratch / "job.json", scratch / "result.json", scratch / "worker.log"
    record_path = None
    if job.record != "none" and job.recordings_dir:
        Path(job.recordings_dir).mkdir(parents=True, exist_ok=True)
        record_path = str(Path(job.recordings_dir) / f"{safe_name(spec.key)}.rrd")
    env = dict(os.environ)
    for name in THREAD_ENV:
        env[name] = str(job.threads)
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONUNBUFFERED"] = "1"
    server = _forkserver(job, env)
    job_path.write_text(json.dumps({
        "spec": spec.as_dict(), "overrides": list(job.overrides), "trial_fn": job.trial_fn,
        "record_path": record_path, "result_path": str(result_path),
        "parent_pid": server.pid if server is not None else os.getpid(),  # whose death orphans the worker
        "stop_grace_s": job.stop_grace_s,
    }))
    stop = prepare_driver_stop(spec, job)  # before the trial: after a SIGKILL only the stop itself is left
    started, t0 = utc_now(), time.monotonic()
    status = None
    proc = None
    try:
        if canceller is None:
            proc = _launch(server, job_path, log_path, env)
        else:
            with canceller.lock:  # cancel() sets stop before taking the lock: no worker escapes it
                if canceller.stop.is_set():
                    raise InterruptedError("benchmark cancelled before the trial started")
                proc = _launch(server, job_path, log_path, env)
                canceller.running.add(proc)
        try:
            rc = proc.wait(timeout=job.timeout_s)
        except subprocess.TimeoutExpired:
            stop_groups([proc], job.stop_grace_s)
            status = "timeout"
            rc = proc.returncode
        except BaseException:  # interrupted while waiting (e.g. a Ray task cancelled): stop the worker cleanly
            stop_groups([proc], job.stop_grace_s)
            if _stop_path_skipped(None, proc.returncode, result_path):
                driver_stop(stop, spec.key)
            raise
        finally:
            if canceller is not None:
                with canceller.lock:
                    canceller.running.discard(proc)
            if status != "timeout" and proc is not None:
                # Grandchildren (e.g. a renderer helper) must not outlive the trial either.
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, signal.SIGKILL)
        wall = time.monotonic() - t0
        stopped = driver_stop(stop, spec.key) if _stop_path_skipped(status, rc, result_path) else None
        if canceller is not None and canceller.stop.is_set():
            raise InterruptedError("benchmark cancelled while the trial ran")
        row = _row(spec, job, status, rc, result_path)
        failed = trial_failed(row)
        row["run"] = {"engine": job.engine, "worker": f"{socket.gethostname()}:{proc.pid}",
                      "start_method": "spawn" if isinstance(proc, subprocess.Popen) else "forkserver",
                      "started": started,
                      "finished": utc_now(), "wall_s": round(wall, 3), "threads": job.threads,
                      "session": job.session, "returncode": rc, "log": None, "recording": None,
                      "log_tail": _tail(log_path) if row["status"] != "ok" else None}
        if stopped is not None:
            row["run"]["driver_stop"] = stopped
        if failed and job.logs_dir:
            try:
                Path(job.logs_dir).mkdir(parents=True, exist_ok=True)
                dest = Path(job.logs_dir) / f"{safe_name(spec.key)}.log"
                shutil.copyfile(log_path, dest)
                row["run"]["log"] = str(dest)
            except OSError as exc:
                log.warning("could not keep the log of %s: %s", spec.key, exc)
        if record_path and Path(record_path).exists():
            if job.record == "failures" and not failed:
                Path(record_path).unlink()  # --record failures: recordings of successful trials are not kept
            else:
                row["run"]["recording"] = record_path
        return row
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _forkserver(job: TrialJob, env: dict[str, str]) -> Any:
    """The fork server for ``job``; None for ``spawn``, for more than one thread per trial (OpenBLAS starts its
    pool at import then, so the server would be refused) and when the server is refused (it warns once)."""
    if job.start_method != "forkserver" or job.threads != 1:
        return None
    from torm.bench.forkserver import ForkServerError, get_forkserver

    try:
        return get_forkserver(env, (job.trial_fn.partition(":")[0],))
    except ForkServerError:
        return None


def _launch(server: Any, job_path: Path, log_path: Path, env: dict[str, str]) -> Any:
    """Start the worker of ``job_path`` (a Popen, or a forked worker with the same methods)."""
    if server is not None:
        from torm.bench.forkserver import ForkServerError

        log_path.touch()
        try:
            return server.start_worker(str(job_path), str(log_path), env)
        except ForkServerError as exc:  # the server died or refused: this trial starts fresh
            log.warning("fork server failed (%s); %s starts as a fresh interpreter", exc, job_path)
            job = json.loads(job_path.read_text())
            job["parent_pid"] = os.getpid()
            job_path.write_text(json.dumps(job))
    cmd = [sys.executable, "-m", "torm.bench.worker", str(job_path)]
    with open(log_path, "wb") as logf:
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)


def prepare_driver_stop(spec: TrialSpec, job: TrialJob) -> Callable[[], Any] | None:
    """The trial module's optional ``safe_stop(spec, overrides)`` hook (:mod:`torm.bench.trial`), called before
    the trial starts: the driver-side stop of a trial whose process dies without its own stop path (a real arm:
    cancel, disable), ready to run. None without a hook or with nothing to stop. Never raises: a failing hook is
    logged and returns a callable that reports the error."""
    import importlib

    try:
        module = importlib.import_module(job.trial_fn.partition(":")[0])
        hook = getattr(module, "safe_stop", None)
        return hook(spec, tuple(job.overrides)) if callable(hook) else None
    except Exception as exc:  # noqa: BLE001 - reported with the row, never raised
        log.error("preparing the driver-side stop of %s failed: %s", spec.key, exc)
        message = f"{type(exc).__name__}: {exc}"
        return lambda: {"error": message}


def driver_stop(stop: Callable[[], Any] | None, key: str = "") -> Any:
    """Run a prepared driver-side stop (:func:`prepare_driver_stop`); its report, or None when there was
    nothing to stop. Never raises (a driver must go on stopping the other trials)."""
    if stop is None:
        return None
    try:
        return stop()
    except Exception as exc:  # noqa: BLE001
        log.error("driver-side stop of %s failed: %s", key, exc)
        return {"error": f"{type(exc).__name__}: {exc}"}


def _stop_path_skipped(status: str | None, rc: int | None, result_path: Path) -> bool:
    """True when the worker did not end on its own with a result (killed, crashed, timed out): its stop path
    (a real arm's cancel and disable) may not have run."""
    return status == "timeout" or not result_path.exists() or (rc is not None and rc < 0)


def timeout_message(timeout_s: float) -> str:
    """The message of a timeout row (the same for every engine)."""
    return f"trial ran longer than the {timeout_s:g} s limit and was stopped (SIGTERM, then SIGKILL after the grace)"


def _row(spec: TrialSpec, job: TrialJob, status: str | None, rc: int | None, result_path: Path) -> dict[str, Any]:
    """The row's content; deterministic for a given trial outcome (no times, no log text: those go in ``run``)."""
    if status == "timeout":
        return failure_row(spec, "timeout", "timeout", timeout_message(job.timeout_s))
    if result_path.exists():
        try:
            result = json.loads(result_path.read_text())
        except ValueError as exc:
            return failure_row(spec, "crashed", "crashed", f"unreadable worker result ({exc})")
        if result.get("status") == "ok":
            return ok_row(spec, result["record"])
        row = failure_row(spec, "error", result.get("failure") or "error", result.get("message", ""))
        row["traceback"] = result.get("traceback", "")
        return row
    how = f"killed by {_signal_name(rc)}" if rc is not None and rc < 0 else f"exited with code {rc}"
    return failure_row(spec, "crashed", "crashed", f"worker process {how} without a result (see run.log_tail)")


__all__ = ["Canceller", "TrialJob", "driver_stop", "prepare_driver_stop", "run_isolated", "safe_name"]
