"""A fork server for trial workers: one process imports the heavy libraries once, every trial is a fork of it.

A fresh interpreter per trial (``start_method="spawn"``, :mod:`torm.bench.isolate`) pays the interpreter
start and the trial's imports every time: about 2.4 s on a 2-core machine (torch alone 1.3 s), a tenth
of a realistic closed-loop trial. ``start_method="forkserver"`` keeps the isolation and pays the imports
once: a server process (``python -m torm.bench.forkserver``) imports :data:`PRELOAD` and the trial
function's module, **checks that it is still single-threaded** (a fork copies only the calling thread, so
a thread pool, an EGL context or a renderer started before the fork would be broken in the child), and
then forks one child per trial. The child starts its own session (process group), sends its output to
the trial's log, takes the trial's environment and runs :func:`torm.bench.worker.main` exactly as a
spawned worker would: same SIGTERM handling, same parent watchdog (its parent is the server), same result
file, ``os._exit`` at the end. Nothing the trial does touches the server: threads, GL contexts, torch's
thread pool and renderers all start in the child.

What differs from ``spawn`` (stated, not hidden): the children share the server's Python hash seed (set
iteration order of strings is the same in every trial), and the libraries' import-time state is the
server's. NumPy's legacy global generator is reseeded from the OS in every child, as in a fresh
interpreter; ``random`` reseeds itself at fork.

Protocol (JSON lines): the runner writes ``{"id", "job", "log", "env"}`` to the server's stdin; the
server answers ``{"id", "pid"}`` (or ``{"id", "error"}``) and, when a child ends, ``{"exit": pid, "rc"}``
with ``rc`` as :attr:`subprocess.Popen.returncode` gives it (negative: killed by that signal). When the
runner goes away (EOF on stdin) the server exits; its children notice (their parent changed) and stop
themselves the way a spawned worker does when its runner dies.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

log = logging.getLogger(__name__)

PRELOAD: tuple[str, ...] = (
    "numpy", "scipy.spatial", "scipy.ndimage", "torch", "trimesh", "mujoco", "cv2",
    "torm.pipeline", "torm.bench.worker", "torm.metrics", "torm.methods.builtin_methods", "torm.segmentation.gt",
    "torm.segmentation.learned", "sim.world", "sim.backend", "sim.judge", "sim.cameras.rig", "sim.cameras.occlusion",
    "sim.depth.ideal", "sim.depth.statistical", "sim.scenes.scenario",
)
"""Modules the server imports before it forks (each optional: one that fails to import is logged and left
to the trial). The trial function's module is added to them. Not here because they start threads at import
(measured: onnxruntime, mitsuba / drjit and so ``sim.render``): the trial imports those itself (0.3-0.4 s)."""

READY_TIMEOUT_S = 300.0
"""How long the runner waits for the server's imports before it gives up (a stuck import)."""


class ForkServerError(RuntimeError):
    """The fork server could not start, is not safe to fork from, or died."""


def thread_count() -> int:
    """Threads of this process, native ones included (``/proc/self/task``); 0 where that cannot be read (no
    ``/proc``: Python's own thread count would miss native threads), which the server treats as not safe."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


# ---------------------------------------------------------------------------------------------------- server


def _preload(modules: Sequence[str]) -> dict[str, str]:
    failed: dict[str, str] = {}
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - a module the trial may not need; the trial imports it again
            failed[name] = f"{type(exc).__name__}: {exc}"
    return failed


def _child(req: dict[str, Any], keep_fds: Sequence[int]) -> None:
    """In the forked child: become a trial worker. Never returns."""
    code = 1
    try:
        os.setsid()
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
            signal.signal(sig, signal.SIG_DFL)
        for fd in keep_fds:  # the server's protocol and signal pipes (all > 2)
            with contextlib.suppress(OSError):
                os.close(fd)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)  # the server's request pipe is not the trial's stdin
        out = os.open(req["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(out, 1)
        os.dup2(out, 2)
        for fd in {null, out} - {0, 1, 2}:
            os.close(fd)
        os.environ.clear()
        os.environ.update(req["env"])
        if "numpy" in sys.modules:
            sys.modules["numpy"].random.seed()  # as a fresh interpreter would have it
        from torm.bench import worker

        code = worker.main([req["job"]])
    except BaseException:  # noqa: BLE001 - the child must never return into the server's loop
        import traceback

        with contextlib.suppress(Exception):
            traceback.print_exc()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def _returncode(status: int) -> int:
    if os.WIFSIGNALED(status):
        return -os.WTERMSIG(status)
    return os.WEXITSTATUS(status) if os.WIFEXITED(status) else 1


def serve(modules: Sequence[str]) -> int:
    """The server's loop (``python -m torm.bench.forkserver MODULE ...``): preload, report, fork on request."""
    proto = os.dup(1)  # protocol lines go here; fd 1 itself goes to stderr so no import's print corrupts them
    os.dup2(2, 1)
    failed = _preload(list(PRELOAD) + [m for m in modules if m not in PRELOAD])
    threads = thread_count()
    gc.collect()
    gc.freeze()  # the preloaded objects leave the collector's view: a child's collections do not touch (copy) them

    def send(msg: dict[str, Any]) -> None:
        os.write(proto, (json.dumps(msg) + "\n").encode())

    send({"ready": os.getpid(), "threads": threads, "failed": failed})
    if threads != 1:
        return 3  # the runner refuses it (see Forkserver.start); forking now could hang a child
    rfd, wfd = os.pipe()
    os.set_blocking(rfd, False)
    os.set_blocking(wfd, False)
    signal.set_wakeup_fd(wfd)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the runner stops the trials; a terminal's Ctrl-C is not for us
    stdin = sys.stdin.buffer.raw if hasattr(sys.stdin.buffer, "raw") else sys.stdin.buffer
    pending = b""
    children: set[int] = set()
    while True:
        try:
            ready, _, _ = select.select([stdin, rfd], [], [])
        except InterruptedError:
            ready = [rfd]
        if rfd in ready:
            with contextlib.suppress(BlockingIOError):
                os.read(rfd, 4096)
        while children:  # reap every child that ended (one SIGCHLD may stand for several)
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            children.discard(pid)
            send({"exit": pid, "rc": _returncode(status)})
        if stdin in ready:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                return 0  # the runner is gone: leave; the children's watchdogs stop them
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                req = json.loads(line)
                if thread_count() != 1:  # something started a thread since: refuse rather than fork
                    send({"id": req["id"], "error": f"fork server has {thread_count()} threads; not safe to fork"})
                    continue
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _child(req, (proto, rfd, wfd))
                children.add(pid)
                send({"id": req["id"], "pid": pid})


# ---------------------------------------------------------------------------------------------------- client


class ForkedWorker:
    """The runner's handle of a forked trial worker: the part of :class:`subprocess.Popen` the runner uses
    (``pid``, ``returncode``, ``poll``, ``wait``, ``send_signal``, ``terminate``, ``kill``)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._done = threading.Event()

    def _finish(self, rc: int) -> None:
        self.returncode = rc
        self._done.set()

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise subprocess.TimeoutExpired(f"forked worker {self.pid}", timeout or 0.0)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class Forkserver:
    """A running fork server (see the module docstring). Thread-safe: pool threads call :meth:`start_worker`.

    Args:
        env: the environment of the server and of every child (thread counts, ``MUJOCO_GL``: libraries read
            some of them at import, so the server must have them before it imports).
        modules: extra modules to preload (the trial function's module).
    """

    def __init__(self, env: Mapping[str, str], modules: Sequence[str] = ()) -> None:
        self.env = dict(env)
        self._next = 0
        self._replies: dict[int, dict[str, Any]] = {}
        self._workers: dict[int, ForkedWorker] = {}
        self._early_exits: dict[int, int] = {}
        self._cond = threading.Condition()
        self._dead: str | None = None
        self.proc = subprocess.Popen([sys.executable, "-m", "torm.bench.forkserver", *modules],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=self.env,
                                     start_new_session=True)
        hello = self._read_ready()
        self.pid = int(hello["ready"])
        self.failed_imports: dict[str, str] = hello.get("failed") or {}
        if int(hello.get("threads", 0)) != 1:
            self.close()
            why = ("cannot count its threads (no /proc)" if not hello.get("threads") else
                   f"has {hello.get('threads')} threads after its imports (a module starts a thread at import)")
            raise ForkServerError(f"the fork server {why}: forking from it is not safe; use start_method='spawn'")
        for name, why in self.failed_imports.items():
            log.info("fork server: %s not preloaded (%s); trials import it themselves", name, why)
        self._reader = threading.Thread(target=self._read_loop, name="forkserver-reader", daemon=True)
        self._reader.start()

    def _read_ready(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], READY_TIMEOUT_S)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            self.close()
            raise ForkServerError(f"the fork server did not start within {READY_TIMEOUT_S:g} s (exit code "
                                  f"{self.proc.poll()}); run `python -m torm.bench.forkserver` to see why, or use "
                                  "start_method='spawn'")
        return json.loads(line)

    def _read_loop(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            msg = json.loads(line)
            with self._cond:
                if "exit" in msg:
                    pid, rc = int(msg["exit"]), int(msg["rc"])
                    worker = self._workers.pop(pid, None)
                    if worker is None:
                        self._early_exits[pid] = rc  # ended before its pid reply was handled
                    else:
                        worker._finish(rc)
                else:
                    self._replies[int(msg["id"])] = msg
                    self._cond.notify_all()
        with self._cond:  # the server died: its children are orphans now and stop themselves
            self._dead = f"fork server (pid {self.proc.pid}) exited with code {self.proc.wait()}"
            self._cond.notify_all()
            workers, self._workers = list(self._workers.values()), {}
        for worker in workers:
            threading.Thread(target=_wait_gone, args=(worker,), daemon=True).start()

    def start_worker(self, job_path: str, log_path: str, env: Mapping[str, str]) -> ForkedWorker:
        """Fork a worker for ``job_path`` whose output goes to ``log_path``; raises ForkServerError if the server
        is gone or refused."""
        with self._cond:
            if self._dead:
                raise ForkServerError(self._dead)
            self._next += 1
            rid = self._next
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.write((json.dumps({"id": rid, "job": job_path, "log": log_path, "env": dict(env)})
                                       + "\n").encode())
                self.proc.stdin.flush()
            except OSError as exc:  # the server died between two trials
                raise ForkServerError(f"fork server (pid {self.proc.pid}) is gone: {exc}") from exc
            while rid not in self._replies and not self._dead:
                self._cond.wait()
            reply = self._replies.pop(rid, None)
            if reply is None:
                raise ForkServerError(self._dead or "fork server gave no reply")
            if "error" in reply:
                raise ForkServerError(reply["error"])
            worker = ForkedWorker(int(reply["pid"]))
            if worker.pid in self._early_exits:
                worker._finish(self._early_exits.pop(worker.pid))
            else:
                self._workers[worker.pid] = worker
            return worker

    def close(self) -> None:
        """Stop the server (its running children are not touched: the runner stops those)."""
        with contextlib.suppress(Exception):
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _wait_gone(worker: ForkedWorker, poll_s: float = 0.1) -> None:
    """A worker whose server died: wait until its pid is gone; its exit status is lost (recorded as 1)."""
    while True:
        try:
            os.kill(worker.pid, 0)
        except ProcessLookupError:
            break
        except PermissionError:
            pass
        time.sleep(poll_s)
    worker._finish(1)


_SERVERS: dict[tuple[tuple[str, str], ...], Forkserver] = {}
_SERVERS_LOCK = threading.Lock()
_REFUSED: dict[tuple[tuple[str, str], ...], str] = {}


def get_forkserver(env: Mapping[str, str], modules: Sequence[str] = ()) -> Forkserver:
    """The fork server for this environment and these preloads (started on first use, shared by threads).
    A server that was refused is not started again (until :func:`close_forkservers`): ForkServerError at once,
    after one warning."""
    key = tuple(sorted(env.items())) + tuple(("module", m) for m in modules)
    with _SERVERS_LOCK:
        if key in _REFUSED:  # not tried again for every trial: a start costs the imports it would save
            raise ForkServerError(_REFUSED[key])
        server = _SERVERS.get(key)
        if server is None or server._dead:
            try:
                server = _SERVERS[key] = Forkserver(env, modules)
            except ForkServerError as exc:
                _REFUSED[key] = str(exc)
                log.warning("start_method forkserver unavailable (%s); trials start as fresh interpreters (spawn)",
                            exc)
                raise
        return server


def close_forkservers() -> None:
    """Stop every fork server this process started (the pool calls it when a benchmark ends); forget refusals."""
    with _SERVERS_LOCK:
        servers = list(_SERVERS.values())
        _SERVERS.clear()
        _REFUSED.clear()
    for server in servers:
        server.close()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    return serve(args)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["PRELOAD", "ForkServerError", "ForkedWorker", "Forkserver", "close_forkservers", "get_forkserver",
           "thread_count"]
