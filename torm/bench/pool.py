"""The local engine: up to ``workers`` isolated trial processes at a time on this machine.

Each trial is its own process (:func:`torm.bench.isolate.run_isolated`: a fork of a server that imported the
libraries once, :mod:`torm.bench.forkserver`, or with ``spawn`` a fresh ``python -m torm.bench.worker``);
a thread per slot waits on it, so the runner's main thread only collects rows.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import Any

from torm.bench.forkserver import close_forkservers
from torm.bench.isolate import Canceller, TrialJob, run_isolated
from torm.bench.spec import TrialSpec


def pool_rows(specs: Sequence[TrialSpec], job: TrialJob, workers: int) -> Iterator[dict[str, Any]]:
    """Yield one row per spec as trials finish (completion order). Closing the generator (or an
    exception in the consumer) stops every running worker (SIGTERM, ``job.stop_grace_s``, SIGKILL)."""
    canceller = Canceller(grace_s=job.stop_grace_s)
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="trial")
    todo = list(specs)
    running: set[Future] = set()
    try:
        while todo or running:
            while todo and len(running) < workers:
                running.add(pool.submit(run_isolated, todo.pop(0), job, canceller))
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                yield fut.result()
    finally:
        canceller.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
        close_forkservers()


__all__ = ["pool_rows"]
