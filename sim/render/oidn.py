"""Intel Open Image Denoise (OIDN) on a path-traced view's linear radiance (``capture.pbr.denoise=oidn*``).

OIDN's ``RT`` filter is a convolutional network trained on path-traced images at low sample counts; given the
noisy HDR colour of a view it returns an estimate of the converged image. It runs on the CPU through the
``pyoidn`` bindings (MIT), whose wheel ships OIDN 2.x's libraries (Apache-2.0): ``pip install 'torm-glass[denoise]'``.
Only the colour is passed (no albedo or normal images): glass has no meaningful albedo at its first hit, and the
auxiliary passes would cost rays of their own.

Qualities (OIDN's names): ``high`` (the largest network), ``balanced``, ``fast``. The renderer names them as
denoisers (:data:`torm.capture.render_settings.DENOISERS`): ``oidn`` = high, ``oidn_fast`` = fast (``balanced``
measured as slow as ``high`` on a CPU here, so the renderer does not offer it).
One CPU device and one filter per (thread count, quality, image size) are kept for the process's lifetime.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from sim.render.base import RenderError

#: OIDN quality names -> the ``OIDN_QUALITY_*`` constant's attribute in ``pyoidn``.
QUALITIES = {"high": "OIDN_QUALITY_HIGH", "balanced": "OIDN_QUALITY_BALANCED", "fast": "OIDN_QUALITY_FAST"}
INSTALL_HINT = "pip install 'torm-glass[denoise]' (or: pip install pyoidn)"

_lock = threading.Lock()
_devices: dict[int, Any] = {}
_filters: dict[tuple[int, str, tuple[int, int]], tuple[Any, np.ndarray, np.ndarray]] = {}


class OidnUnavailableError(RenderError):
    """OIDN was asked for but its Python bindings (``pyoidn``) are not installed."""


def _pyoidn() -> Any:
    try:
        import pyoidn
    except ImportError as exc:  # the optional extra is missing
        raise OidnUnavailableError(f"capture.pbr.denoise=oidn needs Intel Open Image Denoise's bindings: "
                                   f"{INSTALL_HINT}; or pick another capture.pbr.denoise") from exc
    return pyoidn


def _check(device: Any, what: str) -> None:
    msg = device.get_error()
    if msg is not None:
        raise RenderError(f"OIDN {what} failed: {msg}")


def oidn_denoise(linear_hxwx3: np.ndarray, *, quality: str = "high", threads: int = 1) -> np.ndarray:
    """Denoise a view's linear radiance with OIDN's ``RT`` filter in HDR mode.

    Args:
        linear_hxwx3: (H, W, 3) linear radiance (any non-negative scale; NaN / inf are read as 0).
        quality: one of :data:`QUALITIES` (``high``, ``balanced``, ``fast``).
        threads: CPU threads OIDN may use (>= 1; a trial's worker passes its share of the cores).

    Returns:
        (H, W, 3) float32 linear radiance, same scale as the input.

    Raises:
        OidnUnavailableError: ``pyoidn`` is not installed (the message names the install command).
        RenderError: an unknown ``quality``, a wrong shape, or OIDN reported an error.
    """
    if quality not in QUALITIES:
        raise RenderError(f"OIDN quality {quality!r} is not one of {sorted(QUALITIES)}")
    lin = np.asarray(linear_hxwx3)
    if lin.ndim != 3 or lin.shape[2] != 3 or lin.shape[0] < 1 or lin.shape[1] < 1:
        raise RenderError(f"OIDN needs an (H, W, 3) image, got shape {lin.shape}")
    threads = max(1, int(threads))
    oidn = _pyoidn()
    key = (threads, quality, (int(lin.shape[0]), int(lin.shape[1])))
    with _lock:
        if threads not in _devices:
            dev = oidn.Device(oidn.OIDN_DEVICE_TYPE_CPU)
            dev.set_int("numThreads", threads)
            dev.set_bool("setAffinity", False)  # leave thread placement to the worker's scheduler
            dev.commit()
            _check(dev, "device setup")
            _devices[threads] = dev
        dev = _devices[threads]
        if key not in _filters:
            colour = np.zeros((*key[2], 3), np.float32)
            out = np.zeros_like(colour)
            flt = oidn.Filter(dev, oidn.OIDN_FILTER_TYPE_RT)
            flt.set_image(oidn.OIDN_IMAGE_COLOR, colour, oidn.OIDN_FORMAT_FLOAT3)
            flt.set_image(oidn.OIDN_IMAGE_OUTPUT, out, oidn.OIDN_FORMAT_FLOAT3)
            flt.set_bool("hdr", True)
            flt.set_quality(getattr(oidn, QUALITIES[quality]))
            flt.commit()
            _check(dev, "filter setup")
            _filters[key] = (flt, colour, out)
        flt, colour, out = _filters[key]
        colour[...] = np.nan_to_num(lin, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
        flt.execute()
        _check(dev, "denoising")
        return out.copy()


__all__ = ["QUALITIES", "INSTALL_HINT", "OidnUnavailableError", "oidn_denoise"]
