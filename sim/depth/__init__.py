"""Simulated depth sensors behind one interface (:class:`DepthModel`): ``ideal``, ``statistical``, ``stereo``.

``make_depth_model(name, options)`` builds one; ``capture.depth_model`` names it in a trial, and
``capture.depth_options`` (a mapping) overrides its config fields. See ``sim/depth/README.md`` for the
parameter tables with their sources.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sim.depth.base import DepthModel, DepthScene
from sim.depth.d455 import D455Sensor
from sim.depth.ideal import IdealDepth
from sim.depth.statistical import StatisticalDepth, StatisticalDepthConfig
from torm.errors import ConfigError, UnknownNameError

#: Names of the depth models (``capture.depth_model``).
DEPTH_MODEL_NAMES: tuple[str, ...] = ("ideal", "statistical", "stereo")


def make_depth_model(name: str, options: Mapping[str, Any] | None = None) -> DepthModel:
    """The depth model ``name`` with its config fields overridden by ``options`` (unknown keys rejected)."""
    from torm import config as tcfg

    opts = dict(options or {})
    if name == "ideal":
        if opts:
            raise ConfigError(f"depth model 'ideal' takes no options, got {sorted(opts)}")
        return IdealDepth()
    if name == "statistical":
        return StatisticalDepth(tcfg.from_dict(StatisticalDepthConfig, opts, where="capture.depth_options"))
    if name == "stereo":
        from sim.depth.stereo import StereoDepth, StereoDepthConfig

        return StereoDepth(tcfg.from_dict(StereoDepthConfig, opts, where="capture.depth_options"))
    raise UnknownNameError("capture.depth_model", name, DEPTH_MODEL_NAMES)


__all__ = ["DEPTH_MODEL_NAMES", "D455Sensor", "DepthModel", "DepthScene", "IdealDepth", "StatisticalDepth",
           "StatisticalDepthConfig", "make_depth_model"]
