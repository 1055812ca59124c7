"""Settings of the physically based renderer (``capture.pbr``), a frozen config loadable through ``torm.config``.

The renderer itself lives in ``sim.render`` (it needs the simulator's scene); the settings live here so a
:class:`~torm.pipeline.TrialConfig` can hold them without importing the simulator. Every field is part of the
render-cache key (see ``sim.render.cache``): change one and cached images are never reused.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from torm.config import Range, check_finite
from torm.errors import ConfigError, UnknownNameError

#: Mitsuba variants: ``auto`` = ``llvm_ad_rgb`` when a usable libLLVM (>= 16) is found, else ``scalar_rgb``
#: with a warning; naming one forces it (``llvm_ad_rgb`` without libLLVM raises, naming the apt package).
VARIANTS = ("auto", "llvm_ad_rgb", "scalar_rgb")
#: Light transport: ``glass_path`` = path tracing with straight-through shadow rays for glass and no refractive
#: caustics (converges at a few spp; JIT variants only, ``scalar_rgb`` runs ``path``), ``path`` = Mitsuba's exact
#: path tracer (glass interiors and shadows converge slowly). See ``sim.render.integrator``.
INTEGRATORS = ("glass_path", "path")
#: Mitsuba samplers: ``ldsampler`` (low-discrepancy, Kollig & Keller's (0, 2)-sequence) halved the RMSE of
#: ``independent`` at 16 spp at the same speed (measured here: 4.8 vs 9.1 grey levels on rw3).
SAMPLERS = ("ldsampler", "independent", "multijitter", "stratified")
#: Sample counts the ldsampler accepts (square powers of two, at least 4: it renders 1 as 4).
LDSAMPLER_SPP = (4, 16, 64, 256, 1024, 4096)
#: Samples per pixel when ``spp`` is 0 (auto) and no segmenter card names a count: the count every committed PBR
#: result before 2026-12-07 used (16 spp + bilateral: ``benchmarks/results/render.md``).
DEFAULT_SPP = 16
#: Denoisers: ``none``; on the tone-mapped 8-bit image ``nlmeans`` = OpenCV's ``fastNlMeansDenoisingColored`` with
#: strength ``denoise_strength``, ``bilateral`` = OpenCV's bilateral filter; on the linear radiance before tone
#: mapping ``oidn`` / ``oidn_fast`` = Intel Open Image Denoise's ``RT`` filter at quality high / fast
#: (:mod:`sim.render.oidn`; optional ``pyoidn``: ``pip install 'torm-glass[denoise]'``; strength unused).
DENOISERS = ("none", "nlmeans", "bilateral", "oidn", "oidn_fast")


@dataclass(frozen=True)
class PbrSettings:
    """Physically based (Mitsuba 3 path tracer) render settings.

    Attributes:
        spp: samples per pixel of the RGB pass (>= 1); 0 = auto: the sample count the image segmenter reads at
            unchanged quality, from its model card (``capture.pbr_spp``; a trial resolves it,
            :func:`torm.pipeline.resolve_spp`), else :data:`DEFAULT_SPP` (every other segmenter, and outside a trial).
        max_depth: longest light path in bounces (``path`` integrator; -1 = unbounded). Solid glass needs
            at least 2 refractions plus the surface behind it; hollow glass 4 interfaces plus total internal
            reflections: 8 keeps both.
        rr_depth: path depth at which Russian roulette starts.
        integrator: one of :data:`INTEGRATORS`.
        sampler: one of :data:`SAMPLERS`.
        denoise: one of :data:`DENOISERS`.
        denoise_strength: filter strength in 8-bit grey levels (``h`` of non-local means, sigma colour of the
            bilateral filter); OIDN has no strength and ignores it.
        render_scale: the RGB pass is traced at this fraction of each camera's size and resized (area / linear
            interpolation) to it; 1.0 = native. Instance ids are always traced at the native size. 0 = auto: the
            width the image segmenter reads (a trial resolves it, :func:`torm.pipeline.resolve_render_scale`:
            the learned segmenter's ``input_width`` / the capture width, at most 1; 1.0 for every other segmenter
            and outside a trial), so no more pixels are traced than the method reads.
        variant: one of :data:`VARIANTS`.
        threads: render threads (0 = ``TORM_THREADS`` or the free cores).
        exposure: ``0`` = auto exposure (the scene's log-average luminance maps to 0.18, Reinhard et al. 2002's
            key value, like a camera's auto exposure); > 0 = a fixed linear gain.
        cache: read and write the on-disk render cache (``TORM_CACHE_DIR``, default ``~/.cache/torm``).
    """

    spp: Annotated[int, Range(0, 65_536, "samples per pixel; 0 = auto (the segmenter's card, else 16)")] = 0
    max_depth: Annotated[int, Range(-1, 1024, "bounces; -1 = unbounded")] = 8
    rr_depth: Annotated[int, Range(1, 1024, "bounces before Russian roulette")] = 5
    integrator: str = "glass_path"
    sampler: str = "ldsampler"
    denoise: str = "bilateral"
    denoise_strength: float = 10.0
    render_scale: float = 1.0
    variant: str = "auto"
    threads: int = 0
    exposure: float = 0.0
    cache: bool = True

    def __post_init__(self) -> None:
        check_finite(self, "capture.pbr")  # ranges and NaN / inf (torm.config), also when built in Python
        if self.spp < 0:
            raise ConfigError(f"capture.pbr.spp must be >= 1 sample per pixel or 0 (auto), got {self.spp}")
        if self.max_depth != -1 and self.max_depth < 1:
            raise ConfigError(f"capture.pbr.max_depth must be >= 1 bounce (or -1 = unbounded), got {self.max_depth}")
        if self.rr_depth < 1:
            raise ConfigError(f"capture.pbr.rr_depth must be >= 1, got {self.rr_depth}")
        if self.integrator not in INTEGRATORS:
            raise UnknownNameError("capture.pbr.integrator", self.integrator, INTEGRATORS)
        if self.sampler not in SAMPLERS:
            raise UnknownNameError("capture.pbr.sampler", self.sampler, SAMPLERS)
        if self.sampler == "ldsampler" and self.spp and self.spp not in LDSAMPLER_SPP:
            raise ConfigError(f"capture.pbr.spp={self.spp}: the ldsampler needs a square power of two "
                              f"{LDSAMPLER_SPP} (Mitsuba would round it up silently); pick one or set "
                              f"capture.pbr.sampler to one of {SAMPLERS[1:]}")
        if self.denoise not in DENOISERS:
            raise UnknownNameError("capture.pbr.denoise", self.denoise, DENOISERS)
        if not self.denoise_strength >= 0:
            raise ConfigError(f"capture.pbr.denoise_strength must be >= 0 grey levels, got {self.denoise_strength}")
        if not (self.render_scale == 0 or 0.05 <= self.render_scale <= 4.0):
            raise ConfigError(f"capture.pbr.render_scale must be in [0.05, 4] or 0 (auto: the width the segmenter "
                              f"reads), got {self.render_scale}")
        if self.variant not in VARIANTS:
            raise UnknownNameError("capture.pbr.variant", self.variant, VARIANTS)
        if self.threads < 0:
            raise ConfigError(f"capture.pbr.threads must be >= 0 (0 = automatic), got {self.threads}")
        if not self.exposure >= 0:
            raise ConfigError(f"capture.pbr.exposure must be 0 (auto) or a positive gain, got {self.exposure}")
