"""One benchmark at a time per run folder: an exclusive lock on ``<run folder>/.lock``.

The lock is an ``fcntl.flock`` on the file, so the kernel releases it when the holder dies in any way
(SIGKILL, a crash, a reboot): a lock can never be left behind by a dead process. The file also holds
who took it (pid, host, start time, command line), which is what a refused second bench is told. A
holder record found in a lock that could be taken belongs to a process that died without releasing
it (a *stale* lock); it is reported as a repair. Released locks leave an empty file.

Where ``flock`` is not supported (some network file systems) the holder record decides: a live pid on
this host refuses, anything else is taken over with a warning.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import platform
import sys
from pathlib import Path
from typing import Any

from torm.bench.results import utc_now
from torm.errors import BenchmarkError

log = logging.getLogger(__name__)

LOCK_NAME = ".lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _describe(h: dict[str, Any]) -> str:
    cmd = " ".join(str(a) for a in h.get("argv") or [])
    return f"pid {h.get('pid')} on {h.get('host')}, since {h.get('started')}" + (f" ({cmd})" if cmd else "")


class RunLock:
    """Exclusive lock on a run folder; use as a context manager or :meth:`acquire` / :meth:`release`.

    Attributes:
        path: the lock file.
        stale: the record of a dead previous holder found when the lock was taken (None: none).
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / LOCK_NAME
        self.stale: dict[str, Any] | None = None
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        """Take the lock; BenchmarkError naming the holder when another bench has it."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise BenchmarkError(f"cannot create the lock file {self.path} ({exc.strerror}); is the run folder "
                                 "writable? choose another --out") from exc
        flock_ok = True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                holder = self._read(fd)
                os.close(fd)
                raise BenchmarkError(
                    f"{self.path.parent} is in use by another torm bench: {_describe(holder)}; wait for it to "
                    "finish (or stop it), or use another --out") from exc
            flock_ok = False  # e.g. ENOLCK on a network file system: fall back to the holder record
            log.warning("%s: file locking is not supported here (%s); relying on the holder's pid", self.path, exc)
        previous = self._read(fd)
        if previous.get("pid"):
            mine = previous.get("host") == platform.node()
            if not flock_ok and mine and _alive(int(previous["pid"])) and int(previous["pid"]) != os.getpid():
                os.close(fd)
                raise BenchmarkError(f"{self.path.parent} is in use by another torm bench: {_describe(previous)}; "
                                     "wait for it to finish (or stop it), or use another --out")
            self.stale = previous
            log.warning("%s: stale lock of a bench that died without releasing it (%s); taken over", self.path,
                        _describe(previous))
        record = {"pid": os.getpid(), "host": platform.node(), "started": utc_now(), "argv": list(sys.argv)}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        os.fsync(fd)
        self._fd = fd
        return self

    @staticmethod
    def _read(fd: int) -> dict[str, Any]:
        try:
            data = os.pread(fd, 65536, 0)
            rec = json.loads(data) if data.strip() else {}
            return rec if isinstance(rec, dict) else {}
        except (OSError, ValueError):
            return {}

    def release(self) -> None:
        """Clear the holder record and release the lock (idempotent)."""
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        with contextlib.suppress(OSError):
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


__all__ = ["LOCK_NAME", "RunLock"]
