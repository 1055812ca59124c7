"""Import Mitsuba 3 with a working variant: ``llvm_ad_rgb`` (vectorised, needs libLLVM >= 16) or ``scalar_rgb``.

Dr.Jit's LLVM backend loads libLLVM at run time from ``DRJIT_LIBLLVM_PATH``. Debian 12's default LLVM 15
crashes it (``Cannot select ... fminimum``, measured here); Debian's ``libllvm19`` package works. When
``DRJIT_LIBLLVM_PATH`` is unset, :func:`find_libllvm` looks for libLLVM 16..19 in the system library folders
and sets it before Mitsuba is imported. Mitsuba's variant is process-global: the first call fixes it, a later
call asking for another variant raises.
"""

from __future__ import annotations

import glob
import logging
import os
from typing import Any

from sim.render.base import RenderError

log = logging.getLogger(__name__)

#: LLVM major versions known to work with Dr.Jit (>= 16); newest first.
LLVM_VERSIONS = (19, 18, 17, 16)
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib", "/usr/local/lib", "/usr/lib64")
INSTALL_HINT = ("install Debian's libLLVM 19 (`apt-get install libllvm19`) or point DRJIT_LIBLLVM_PATH at a "
                "libLLVM >= 16 .so; or set capture.pbr.variant=scalar_rgb (the scalar fallback, ~10x slower)")

_state: dict[str, Any] = {"variant": None, "mi": None}


def find_libllvm() -> str | None:
    """Path of a libLLVM >= 16 shared library (``DRJIT_LIBLLVM_PATH`` first if it exists), or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        return env
    for v in LLVM_VERSIONS:
        for d in _LIB_DIRS:
            for pat in (f"libLLVM-{v}.so", f"libLLVM-{v}.so.1", f"libLLVM.so.{v}*", f"llvm-{v}/lib/libLLVM*.so*"):
                hits = sorted(glob.glob(os.path.join(d, pat)))
                if hits:
                    return hits[0]
    return None


def resolve_variant(requested: str) -> str:
    """The Mitsuba variant ``requested`` ("auto" | "llvm_ad_rgb" | "scalar_rgb") resolves to on this machine.

    ``auto`` picks ``llvm_ad_rgb`` when libLLVM is found (warning and ``scalar_rgb`` otherwise); an explicit
    ``llvm_ad_rgb`` without libLLVM raises :class:`RenderError` naming ``apt-get install libllvm19``.
    """
    if _state["variant"] is not None and requested == "auto":
        return str(_state["variant"])
    if requested == "scalar_rgb":
        return requested
    lib = find_libllvm()
    if lib is None:
        if requested == "llvm_ad_rgb":
            raise RenderError(f"Mitsuba variant llvm_ad_rgb needs libLLVM >= 16, none found; {INSTALL_HINT}")
        log.warning("no libLLVM >= 16 found: the PBR renderer falls back to Mitsuba's scalar_rgb variant, ~10x "
                    "slower and a different look (Mitsuba's plain path integrator, not the glass_path one the "
                    "learned segmenter was trained on: expect lower silhouette IoU); %s", INSTALL_HINT)
        return "scalar_rgb"
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)
    return "llvm_ad_rgb"


def load_mitsuba(requested: str = "auto", threads: int = 0) -> tuple[Any, str]:
    """``(mitsuba module, variant)`` with the variant set; ``threads`` > 0 sets Dr.Jit's thread pool size."""
    variant = resolve_variant(requested)
    if _state["variant"] is not None and _state["variant"] != variant:
        raise RenderError(f"Mitsuba already runs variant {_state['variant']} in this process; it cannot switch to "
                          f"{variant} (the variant is process-global): use one capture.pbr.variant per process")
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - mitsuba is a dependency
        raise RenderError(f"the PBR renderer needs Mitsuba 3 (`pip install mitsuba`): {exc}") from exc
    if _state["variant"] is None:
        try:
            mi.set_variant(variant)
        except Exception as exc:
            raise RenderError(f"Mitsuba cannot start variant {variant} ({exc}); {INSTALL_HINT}") from exc
        _state["variant"], _state["mi"] = variant, mi
        log.info("Mitsuba %s variant %s%s", mi.__version__, variant,
                 f" (libLLVM {os.environ.get('DRJIT_LIBLLVM_PATH')})" if variant.startswith("llvm") else "")
    if threads > 0 and hasattr(dr, "set_thread_count") and dr.thread_count() != threads:
        dr.set_thread_count(threads)
    return mi, variant
