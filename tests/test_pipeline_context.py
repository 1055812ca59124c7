"""Every trial record names what produced it (method, mode, segmenter, renderer, depth model, realism)."""

from __future__ import annotations

import pytest

from torm import config
from torm.errors import UnknownNameError
from torm.pipeline import TrialConfig, trial_context


def test_context_names_every_choice():
    cfg = config.from_dict(TrialConfig, {"method": "torm"}, overrides=["segmentation.segmenter=noisy",
                                                                       "segmentation.preset=severe"])
    ctx = trial_context(cfg)
    assert ctx == {"method": "torm", "reconstruction_mode": "fast", "segmenter": "noisy:severe",
                   "renderer": "mujoco", "depth_model": "ideal", "realism": "ideal", "backend": "sim"}
    ctx = trial_context(config.from_dict(TrialConfig, {"method": "oracle"}))
    assert ctx["reconstruction_mode"] is None and ctx["segmenter"] is None


@pytest.mark.parametrize("key", ["capture.renderer", "capture.depth_model", "world.realism"])
def test_unknown_choice_lists_the_valid_ones(key):
    with pytest.raises(UnknownNameError, match="valid choices"):
        config.from_dict(TrialConfig, {}, overrides=[f"{key}=nonsense"])
