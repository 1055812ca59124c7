"""Process-level runtime settings: thread counts and headless rendering defaults."""

from __future__ import annotations

import logging
import os

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


def configure_threads(n: int | None = None) -> int:
    """Set torch's intra-op threads to ``n`` (default: the free cores) and return it.

    Oversubscription (more threads than free cores) made reconstruction steps 20x slower on a
    2-core machine, so every entry point calls this once.
    """
    import torch

    n = n or free_cores()
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def ensure_headless_gl() -> None:
    """Default ``MUJOCO_GL`` to ``egl`` (headless) unless the user chose a backend."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"] if os.environ["MUJOCO_GL"] != "glfw" else "")
