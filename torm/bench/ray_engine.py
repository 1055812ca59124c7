"""The Ray engine: the same isolated trials as Ray remote tasks (``pip install "torm-glass[distributed]"``).

Each task runs :func:`torm.bench.isolate.run_isolated` on whichever node Ray picks, so a trial is a
fresh worker process there exactly as with the local pool, and the row is built the same way (only
``run.engine``/``run.worker`` differ). The task enforces ``timeout_s`` itself; as a backstop the
driver cancels (``ray.cancel(force=True)``) a task still running ``timeout_s + grace_s`` after it was
submitted and records ``timeout``; a task whose Ray worker died is recorded as ``crashed``. At most
``workers`` tasks are in flight, so submission time is start time. Tasks are never retried
(``max_retries=0``): a crash is a result, not something to hide.

Paths: recordings and kept logs are written on the node that ran the trial, at the run folder's
path; on a multi-node cluster that folder should be on a shared file system (rows come back to the
driver regardless). Every node needs torm installed in the same environment. A task cancelled by
the driver's backstop is force-killed; its trial process dies with it (Ray reaps a killed worker's
children) or, left behind, notices that its parent died and stops itself through the same SIGTERM path
(the trial's clean-up runs). A killed trial may leave its small scratch folder (``torm-trial-*``). When the
driver stops (Ctrl-C, SIGTERM, an error), running tasks are cancelled without force, so each stops its trial
with SIGTERM and the grace period like the local pool.

Stop guarantees with a real arm, the same as the pool's: the driver keeps torm's SIGTERM handling (``ray.init``
installs its own; it is put back), so SIGTERM stops the bench like Ctrl-C (exit 130). When a Ray worker
dies (SIGKILL, out of memory), the driver itself runs the stop prepared by the trial module's ``safe_stop``
hook (:func:`torm.bench.isolate.driver_stop`: a real arm is cancelled and disabled over a new connection,
within :data:`torm.hardware.remote_stop.STOP_TIMEOUT_S` of noticing); a trial process that dies under a live
Ray worker is stopped by that worker the same way. When the driver stops, each task first runs its trial's
own stop path (cancel, then disable, at once); ``stop_grace_s`` + :data:`CANCEL_DELIVERY_S` after the cancel,
when every trial process is gone, the driver stops every real arm that was in flight once more, as a backstop. A cluster
address that does not answer within :data:`CONNECT_TIMEOUT_S` is refused with a message instead of Ray's
retries.
"""

from __future__ import annotations

import logging
import signal
import socket
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

from torm.bench.isolate import TrialJob, driver_stop, prepare_driver_stop, run_isolated, timeout_message
from torm.bench.rows import failure_row
from torm.bench.spec import TrialSpec
from torm.errors import BenchmarkError

log = logging.getLogger(__name__)

#: How long the driver waits for a Ray cluster address to accept a connection (s).
CONNECT_TIMEOUT_S = 10.0

#: Allowance (s) for a cancel to reach a running task: Ray delivers it asynchronously (raylet -> worker -> a
#: KeyboardInterrupt in the task), seconds late on a loaded machine, and the trial's SIGTERM -> SIGKILL grace
#: starts only then. The driver's backstop stop waits ``stop_grace_s`` + this after its cancel.
CANCEL_DELIVERY_S = 5.0


def _ray_trial(spec: TrialSpec, job: TrialJob) -> dict[str, Any]:
    import ray

    row = run_isolated(spec, job)
    try:
        row["run"]["node"] = ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001 - metadata only
        row["run"]["node"] = None
    return row


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise BenchmarkError("engine 'ray' needs Ray: pip install 'torm[distributed]' (ray==2.60.0)") from exc
    return ray


def check_address(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Refuse a Ray cluster address nothing listens on, within ``timeout_s`` (Ray itself retries for minutes).

    ``address``: ``host:port`` (the GCS of ``ray start --head``) or ``ray://host:port`` (Ray client); ``auto``
    and other forms are left to Ray. Raises BenchmarkError naming the address and the fix.
    """
    text = address.strip()
    if text == "auto" or "://" in text and not text.startswith("ray://"):
        return
    hostport = text.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise BenchmarkError(f"cannot reach the Ray cluster at {address!r} ({exc.strerror or exc}) within "
                             f"{timeout_s:g} s; start it (ray start --head) or fix --ray-address (host:port of the "
                             "head's GCS, ray://host:10001 for Ray client, or auto)") from exc


def _init_ray(ray: Any, address: str | None, workers: int) -> None:
    """``ray.init`` that keeps torm's SIGTERM handler (Ray replaces it with one that exits at once)."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    try:
        if address:
            check_address(address)
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    except BenchmarkError:
        raise
    except Exception as exc:  # the raylet or the GCS did not come up: Ray's own traceback helps nobody
        where = f"the Ray cluster at {address!r}" if address else f"a local Ray with {workers} worker(s)"
        raise BenchmarkError(
            f"Ray could not start {where} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}). "
            "Under a memory limit the object store cannot be mapped: set RAY_DEFAULT_OBJECT_STORE_MAX_MEMORY_BYTES "
            "(e.g. 200000000) or give fewer --workers; or run with --engine pool") from exc
    if main and previous is not None:
        signal.signal(signal.SIGTERM, previous)


def ray_rows(specs: Sequence[TrialSpec], job: TrialJob, workers: int, address: str | None = None,
             grace_s: float = 60.0, poll_s: float = 1.0) -> Iterator[dict[str, Any]]:
    """Yield one row per spec as Ray tasks finish.

    ``address``: a running cluster (``ray.init(address=...)``, e.g. ``auto`` or ``ray://host:10001``);
    None starts a local Ray with ``workers`` CPUs and no dashboard, shut down again at the end. An
    already initialised Ray (e.g. in tests) is used as it is and left running.
    """
    ray = _import_ray()
    started_here = False
    if not ray.is_initialized():
        _init_ray(ray, address, workers)
        started_here = True
    remote = ray.remote(num_cpus=1, max_retries=0)(_ray_trial)
    todo = list(specs)
    in_flight: dict[Any, tuple[TrialSpec, float]] = {}
    stops: dict[str, Any] = {}  # prepared driver-side stops of the trials in flight (torm.bench.isolate)
    deadline_s = job.timeout_s + grace_s
    try:
        while todo or in_flight:
            while todo and len(in_flight) < workers:
                spec = todo.pop(0)
                stops[spec.key] = prepare_driver_stop(spec, job)
                in_flight[remote.remote(spec, job)] = (spec, time.monotonic())
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=poll_s)
            for ref in ready:
                spec, t0 = in_flight.pop(ref)
                stop = stops.pop(spec.key, None)
                try:
                    yield ray.get(ref)
                except ray.exceptions.RayError as exc:  # the Ray worker died (or the task could not run)
                    log.warning("ray task of %s failed: %s", spec.key, exc)
                    row = failure_row(spec, "crashed", "crashed", f"ray task failed: {type(exc).__name__}")
                    stopped = driver_stop(stop, spec.key)  # its trial's stop path may not have run: stop from here
                    row["run"] = {"engine": "ray", "worker": None, "wall_s": round(time.monotonic() - t0, 3),
                                  "session": job.session, "log_tail": str(exc)[-2000:]}
                    if stopped is not None:
                        row["run"]["driver_stop"] = stopped
                    yield row
            now = time.monotonic()
            for ref, (spec, t0) in list(in_flight.items()):
                if now - t0 > deadline_s:
                    ray.cancel(ref, force=True)
                    in_flight.pop(ref)
                    stopped = driver_stop(stops.pop(spec.key, None), spec.key)
                    row = failure_row(spec, "timeout", "timeout", timeout_message(job.timeout_s))
                    row["run"] = {"engine": "ray", "worker": None, "wall_s": round(now - t0, 3),
                                  "session": job.session, "log_tail": "cancelled by the driver (ray.cancel)"}
                    if stopped is not None:
                        row["run"]["driver_stop"] = stopped
                    yield row
    finally:
        # KeyboardInterrupt in each task: run_isolated stops its worker with SIGTERM + grace (the stop path:
        # cancel, then disable, in the trial's own order); the driver does not rely on it: once the tasks ended,
        # or the grace ran out, it stops every trial's hardware itself (a second disable is harmless)
        for ref in in_flight:
            ray.cancel(ref, force=False)
        t_cancel = time.monotonic()
        if in_flight:
            ray.wait(list(in_flight), num_returns=len(in_flight), timeout=job.stop_grace_s + 5.0)
        pending = [(spec, stops.pop(spec.key, None)) for spec, _ in in_flight.values()]
        if any(stop is not None for _, stop in pending):
            # A cancelled ref can read as done while its worker still stops the trial, and a trial process is
            # SIGKILLed stop_grace_s after the cancel at the latest: stop the arms from here only after that, so
            # nothing a dying trial still sends can follow the driver's cancel and disable.
            time.sleep(max(0.0, t_cancel + job.stop_grace_s + CANCEL_DELIVERY_S - time.monotonic()))
            for spec, stop in pending:
                driver_stop(stop, spec.key)
        if started_here:
            ray.shutdown()


__all__ = ["CANCEL_DELIVERY_S", "CONNECT_TIMEOUT_S", "check_address", "ray_rows"]
