"""Process-level runtime settings: thread counts and headless rendering defaults."""

from __future__ import annotations

import atexit
import logging
import os
import sys
import weakref

log = logging.getLogger(__name__)


def free_cores() -> int:
    """Cores this process may use (respects CPU affinity and ``TORM_THREADS``)."""
    env = os.environ.get("TORM_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def default_threads() -> tuple[int, str]:
    """(torch threads to use, why): ``TORM_THREADS`` when set, else the free cores minus the busy ones.

    "Busy" is the 1-minute load average: on a 2-core machine with load 1.3 this gives 1 thread, with load
    0.2 two. Oversubscription (more threads than idle cores) made DMTet steps up to 20x slower here
    (RECONSTRUCTION.md; issue #17: 56.7 s at all threads vs 6.6 s with one under the same load).
    """
    env = os.environ.get("TORM_THREADS")
    if env:
        return max(1, int(env)), "TORM_THREADS"
    cores = free_cores()
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover - no load average on this platform
        return cores, f"{cores} free cores"
    n = max(1, min(cores, int(cores - load + 0.5)))
    return n, f"{cores} free cores, 1-min load {load:.1f}; set TORM_THREADS to choose"


_logged: set[int] = set()


def configure_threads(n: int | None = None) -> int:
    """Set torch's intra-op threads to ``n`` (default: :func:`default_threads`) and return it; the choice is
    logged once per value.

    Oversubscription (more threads than free cores) made reconstruction steps 20x slower on a
    2-core machine, so every entry point calls this once.
    """
    import torch

    why = "requested"
    if not n:
        n, why = default_threads()
    if n not in _logged:
        _logged.add(n)
        log.info("using %d torch thread(s) (%s)", n, why)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def ensure_headless_gl() -> None:
    """Default ``MUJOCO_GL`` to ``egl`` (headless) unless the user chose a backend."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"] if os.environ["MUJOCO_GL"] != "glfw" else "")


_CLOSE_AT_EXIT: weakref.WeakSet = weakref.WeakSet()
_EXIT_HOOK_REGISTERED = False


def close_at_exit(obj: object) -> None:
    """Call ``obj.close()`` at interpreter exit if it is still alive then (an env the user never closed).

    MuJoCo's EGL backend registers ``eglTerminate`` at exit when it makes its display (with the first GL context),
    and exit handlers run last-registered first; torm's hook is registered on the first call made after that display
    exists, so it closes the contexts while the display is still there (without it, the renderers' ``__del__``
    fails on a terminated display and prints EGL tracebacks). Call it after ``obj`` may have made GL contexts
    (after a reset, a render). ``obj`` is held weakly; closing twice must be harmless.
    """
    global _EXIT_HOOK_REGISTERED
    _CLOSE_AT_EXIT.add(obj)
    if _EXIT_HOOK_REGISTERED:
        return
    egl = sys.modules.get("mujoco.egl")
    if egl is not None and getattr(egl, "EGL_DISPLAY", None) is None:
        return  # no display yet: registering now would run after its eglTerminate; the next call registers
    atexit.register(_close_all)
    _EXIT_HOOK_REGISTERED = True


def _close_all() -> None:
    for obj in list(_CLOSE_AT_EXIT):
        try:
            obj.close()
        except Exception as exc:  # at exit nothing can be done about it
            log.debug("closing %r at exit failed: %s", obj, exc)
