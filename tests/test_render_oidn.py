"""OIDN on a path-traced view: it removes Monte Carlo noise, keeps the scale, and names its missing package."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from sim.render import MitsubaRenderer, PbrSettings
from sim.render.base import RenderError
from sim.render.mitsuba_renderer import develop, render_linear, tone_map
from tests.render_helpers import camera, tiny_world

pytest.importorskip("pyoidn", reason="the denoise extra (pyoidn) is not installed")

from sim.render.oidn import OidnUnavailableError, oidn_denoise  # noqa: E402


def _noisy(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth HDR gradient (0.2-1.4) and the same with gamma-distributed noise of mean 1 (relative std 0.5)."""
    h, w = 48, 64
    clean = np.repeat(np.linspace(0.2, 1.4, w, dtype=np.float32)[None, :, None], h, 0).repeat(3, 2)
    return clean, (clean * rng.gamma(4.0, 0.25, clean.shape)).astype(np.float32)


@pytest.mark.parametrize("quality", ["high", "fast"])
def test_oidn_removes_noise_and_keeps_the_radiance_scale(quality):
    clean, noisy = _noisy(np.random.default_rng(0))
    out = oidn_denoise(noisy, quality=quality, threads=1)
    assert out.shape == noisy.shape and out.dtype == np.float32
    err_in, err_out = np.abs(noisy - clean).mean(), np.abs(out - clean).mean()
    # gamma(4, 1/4) noise: mean absolute deviation ~0.4 of the signal; a denoiser must take most of it away
    assert err_out < err_in / 3, (err_in, err_out)
    # no re-exposure: the mean radiance stays within 5 % (noise of mean 1 has the clean image's mean)
    assert abs(out.mean() / clean.mean() - 1) < 0.05


def test_oidn_reads_nan_and_inf_as_black_and_rejects_bad_input():
    img = np.full((16, 16, 3), 0.5, np.float32)
    img[3, 4] = np.nan
    img[5, 6] = np.inf
    out = oidn_denoise(img, threads=1)
    assert np.isfinite(out).all()
    with pytest.raises(RenderError, match="quality"):
        oidn_denoise(img, quality="ultra")
    with pytest.raises(RenderError, match=r"\(H, W, 3\)"):
        oidn_denoise(img[..., :2])


def test_missing_bindings_raise_a_named_error_with_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # import pyoidn -> ImportError
    with pytest.raises(OidnUnavailableError, match=r"pip install 'torm-glass\[denoise\]'"):
        oidn_denoise(np.zeros((4, 4, 3), np.float32))


def test_the_renderer_denoises_the_linear_radiance_before_tone_mapping():
    w = tiny_world()
    cam = camera(width=64, height=48)
    s = PbrSettings(spp=4, max_depth=6, denoise="oidn_fast", cache=False, threads=1)
    r = MitsubaRenderer(w, s)
    mi_scene, _ = r.scene()
    seed = 11
    lin = render_linear(mi_scene, cam, s, seed)
    via_develop = develop(lin, s, 0.0, threads=1)
    assert np.array_equal(via_develop, tone_map(oidn_denoise(lin, quality="fast", threads=1), 0.0))
    # against 256 spp, the denoised 4 spp image is closer than the raw 4 spp one
    ref = tone_map(render_linear(mi_scene, cam, dataclasses.replace(s, spp=256), seed + 1), 0.0).astype(float)
    raw = tone_map(lin, 0.0).astype(float)
    assert np.abs(via_develop - ref).mean() < np.abs(raw - ref).mean()
    view = r.render([cam], instance=False)[0]
    assert view.rgb.shape == (48, 64, 3) and view.rgb.dtype == np.uint8
    assert "denoise oidn_fast" in r.describe()
