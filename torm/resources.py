"""Memory estimates that bound sizes before any work starts.

A size typed by mistake (``capture.n_views=1e9``, ``capture.scale=50``, ``--workers 10000``) must be refused
with a message, not found out by the kernel's out-of-memory killer after minutes of work. The estimates are
deliberately on the safe side and measured, not guessed:

- a trial process (Python, torch, MuJoCo, the scene) peaks at 0.77 GB resident with the default 50 views
  at 640x360 (``/usr/bin/time -v torm trial --scenario rw1``, 2026-12-05), so :data:`TRIAL_BASE_BYTES` is 1 GiB;
- each captured pixel costs about 21 bytes through the pipeline (200 views at 640x360 peak 1.64 GB against
  0.77 GB with 20 views: 4.8 MB per view): RGB (3), ideal and sensor depth (4 + 4), the instance mask (4),
  the segmenter's masks and the reconstruction's per-view silhouettes and distance maps; the estimate
  uses :data:`CAPTURE_BYTES_PER_PIXEL` = 32.

:func:`check_fits` compares an estimate with the memory the machine has free (``MemAvailable`` of
``/proc/meminfo``; physical memory where that is missing) and raises :class:`~torm.errors.ConfigError`
naming the size, the estimate, what is free and the fix.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from torm.errors import ConfigError

log = logging.getLogger(__name__)

#: Resident memory of a trial process before its capture (bytes; measured 0.77 GB, rounded up).
TRIAL_BASE_BYTES = 1 << 30
#: Memory per captured pixel through capture, segmentation and reconstruction (bytes; measured ~21).
CAPTURE_BYTES_PER_PIXEL = 32
#: Peak memory of the antipodal grasp planner per (object x contact sample x approach angle x depth) (bytes):
#: tracemalloc peaks of 670-1230 B (the upper end at the default sizes, where a fixed ~16 MB dominates), two
#: 2,048-32,768-point cylinders, 256-2,048 samples, 16-64 angles, 4 depths, 2026-12-07.
GRASP_BYTES_PER_CANDIDATE = 1280
#: Peak memory of the voxel carve per voxel of its grid (bytes): tracemalloc peaks of 95 B at 64^3-192^3, 8 views
#: of 160 x 120, 2026-12-07 (the surviving voxels' indices and centres, the first view's projection).
CARVE_BYTES_PER_VOXEL = 96
#: Grounding DINO + SAM on onnxruntime's CPU provider, measured by ``benchmarks/gsam_cpu.py`` (2026-12-07, every
#: combination of Grounding DINO or learned boxes, SAM ViT-B or SAM 2.1 Hiera-Tiny, memory arena on or off; the views
#: in a fresh process; ``benchmarks/results/{gsam,sam2_gdino,sam_learned,sam2_learned}_cpu*.md``): the process before
#: loading 0.36 GB (bytes below, GB = 1e9).
GSAM_BASE_BYTES = 0.5e9
#: Loading the sessions adds 1.2-2.0x the ONNX files' bytes (initialisers plus onnxruntime's pre-packed copies).
ONNX_LOADED_BYTES_PER_FILE_BYTE = 2.1
#: Grounding DINO's input size at which :data:`GDINO_WORK_BYTES` was measured (the official 16:9 resize, px).
GDINO_REFERENCE_PX = 800 * 1333
#: Working memory of segmenting views, by memory arena (True = onnxruntime's default): Grounding DINO at
#: :data:`GDINO_REFERENCE_PX` (scaled with its input's pixels) and each SAM's image encoder at 1024 px. With the arena
#: each session keeps its largest need, so the parts add; without it the tensors are freed and the larger part bounds
#: the peak.
#: Measured with / without the arena: Grounding DINO 3.74-3.84 / 1.91 GB, SAM ViT-B 6.86 / 3.53, SAM 2.1 Hiera-Tiny
#: 1.66 / 1.02; the constants add about 5 % (the estimate stays above every measured peak: tests/test_resources.py).
GDINO_WORK_BYTES = {True: 4.0e9, False: 2.0e9}
SAM_WORK_BYTES = {("sam", True): 7.2e9, ("sam2", True): 1.8e9, ("sam", False): 3.7e9, ("sam2", False): 1.1e9}
#: Full-resolution image size of the simulated camera (pixels, width x height); ``capture.scale`` scales both.
CAMERA_FULL_SIZE = (1280, 720)


def available_memory_bytes() -> int | None:
    """Memory free for new work (bytes): ``MemAvailable`` from ``/proc/meminfo``, else the physical memory
    (``os.sysconf``), else None (unknown: no check is possible)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def capture_bytes(n_views: int, width_px: int, height_px: int) -> int:
    """Estimated peak memory (bytes) of ``n_views`` views of ``width_px`` x ``height_px`` through the pipeline."""
    return int(n_views) * int(width_px) * int(height_px) * CAPTURE_BYTES_PER_PIXEL


def capture_size(scale: float) -> tuple[int, int]:
    """Image size (width, height in pixels) of the simulated camera at image scale ``scale``."""
    w, h = CAMERA_FULL_SIZE
    return max(1, round(w * scale)), max(1, round(h * scale))


def trial_bytes(n_views: int, scale: float) -> int:
    """Estimated peak memory (bytes) of one trial process capturing ``n_views`` views at image scale ``scale``."""
    w, h = capture_size(scale)
    return TRIAL_BASE_BYTES + capture_bytes(n_views, w, h)


def grasp_bytes(n_objects: int, n_samples: int, n_angles: int, n_depths: int) -> int:
    """Estimated peak memory (bytes) of planning grasps for ``n_objects`` objects with ``n_samples`` contacts,
    ``n_angles`` approach angles and ``n_depths`` depths each (:data:`GRASP_BYTES_PER_CANDIDATE`)."""
    return int(n_objects) * int(n_samples) * int(n_angles) * int(n_depths) * GRASP_BYTES_PER_CANDIDATE


def grounded_sam_bytes(file_bytes: int, gdino_px: int, sam_kind: str, sam_image_size: int = 1024,
                       memory_arena: bool = False) -> float:
    """Estimated peak memory (bytes) of the ``grounded_sam`` segmenter: :data:`GSAM_BASE_BYTES`, the loaded ONNX
    files (``file_bytes`` on disk), and the working memory of Grounding DINO at ``gdino_px`` input pixels (0: boxes
    from the learned segmenter) and of the SAM encoder (``sam_kind`` ``sam`` | ``sam2``) at ``sam_image_size`` px
    (scaled by (size / 1024)^2 below 1024 and ^4 above: ViT-B's global attention is quadratic in its tokens)."""
    if sam_kind not in ("sam", "sam2"):
        raise ConfigError(f"sam_kind {sam_kind!r}; valid choices: sam, sam2")
    work_g = GDINO_WORK_BYTES[memory_arena] * gdino_px / GDINO_REFERENCE_PX
    r = sam_image_size / 1024
    work_s = SAM_WORK_BYTES[(sam_kind, memory_arena)] * (r ** 4 if r > 1 else r ** 2)
    work = work_g + work_s if memory_arena else max(work_g, work_s)
    return GSAM_BASE_BYTES + ONNX_LOADED_BYTES_PER_FILE_BYTE * file_bytes + work


def gib(n_bytes: float) -> str:
    """``n_bytes`` as a short human-readable size (``'1.5 GiB'``, ``'2.3e+06 GiB'``)."""
    g = n_bytes / (1 << 30)
    return f"{g:.3g} GiB" if g < 1e5 else f"{g:.2g} GiB"


def check_fits(need_bytes: float, what: str, fix: str, available: int | None = None) -> None:
    """Refuse work whose estimated memory ``need_bytes`` exceeds what is free.

    Args:
        need_bytes: the estimate (bytes).
        what: the size that causes it, as the user wrote it (e.g. ``"capture.n_views=1000000000 at scale 0.5"``).
        fix: what to change (e.g. ``"use fewer views or a smaller capture.scale"``).
        available: free memory in bytes (default :func:`available_memory_bytes`; None = unknown, no check).

    Raises:
        ConfigError: naming the size, the estimate, the free memory and ``fix``.
    """
    free = available_memory_bytes() if available is None else available
    if free is None:
        log.debug("free memory unknown; %s (%s) not checked", what, gib(need_bytes))
        return
    if need_bytes > free:
        raise ConfigError(f"{what} needs about {gib(need_bytes)} of memory but {gib(free)} is free; {fix}")


def check_trial_fits(n_views: int, scale: float, available: int | None = None) -> None:
    """:func:`check_fits` for one trial's capture (``capture.n_views`` views at ``capture.scale``)."""
    w, h = capture_size(scale)
    check_fits(trial_bytes(n_views, scale), f"capture.n_views={n_views} at capture.scale={scale} ({w}x{h} px)",
               "use fewer views (paper: 50) or a smaller capture.scale (default 0.5)", available)


__all__ = ["CAMERA_FULL_SIZE", "CAPTURE_BYTES_PER_PIXEL", "CARVE_BYTES_PER_VOXEL", "GDINO_REFERENCE_PX",
           "GDINO_WORK_BYTES", "GRASP_BYTES_PER_CANDIDATE", "GSAM_BASE_BYTES", "ONNX_LOADED_BYTES_PER_FILE_BYTE",
           "SAM_WORK_BYTES", "TRIAL_BASE_BYTES", "available_memory_bytes", "capture_bytes", "capture_size",
           "check_fits", "check_trial_fits", "gib", "grasp_bytes", "grounded_sam_bytes", "trial_bytes"]
