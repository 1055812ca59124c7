"""Silhouette extraction: per-view instance masks for a capture (paper Sec. III-A).

Segmenters (``make_segmenter(name, config)``):
    ``gt``            the simulator's instance masks stored in the capture;
    ``noisy``         those masks corrupted by a seeded error model (presets none/mild/moderate/severe/paper);
    ``grounded_sam``  Grounding DINO + SAM on onnxruntime from user-supplied ONNX files;
    ``learned``       the shipped U-Net (foreground + boundary) trained here on rendered scenes, onnxruntime
                      (a reference-mode model also reads each view's empty-workspace reference view);
    ``difference``    the plain scene-minus-reference difference (needs reference views; a baseline).

Each returns a :class:`SegmentationResult` ((V, H, W) int32 masks, detections, timings, quality vs GT
when available); ``result.apply(capture)`` attaches the masks. :mod:`torm.segmentation.multiview` turns
the masks into union silhouettes and can flag views inconsistent with the others.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torm.config import from_dict
from torm.errors import ConfigError, UnknownNameError
from torm.segmentation.base import Detection, SegmentationResult, Segmenter, segment_capture
from torm.segmentation.gt import GTConfig, GTSegmenter
from torm.segmentation.noise import PRESETS, NoiseConfig, NoisyConfig, NoisySegmenter, corrupt_masks
from torm.segmentation.quality import mask_quality

#: registry names; grounded_sam and learned are imported lazily (onnxruntime).
from torm.vocabulary import SEGMENTERS  # noqa: E402  (one definition, re-exported)

log = logging.getLogger(__name__)


#: config keys that hold file paths, per segmenter: relative ones in a YAML file are relative to the file's folder
PATH_KEYS: dict[str, tuple[str, ...]] = {"grounded_sam": ("gdino_model", "bert_vocab", "sam_encoder", "sam_decoder")}


def resolve_config_paths(name: str, data: Mapping[str, Any], yaml_path: str | Path) -> dict[str, Any]:
    """``data`` (segmenter ``name``'s mapping read from ``yaml_path``) with its relative file paths
    (:data:`PATH_KEYS`) made relative to the YAML file's own folder, as ``torm export-models`` writes them.

    A path that does not exist there but does relative to the working directory (a config written before paths
    were relative to their file) is kept as given, with a log line.
    """
    base = Path(yaml_path).resolve().parent
    out = dict(data)
    for key in PATH_KEYS.get(name, ()):
        val = out.get(key)
        if not isinstance(val, str) or not val or Path(val).is_absolute():
            continue
        here = base / val
        if not here.exists() and Path(val).exists():
            log.info("%s: %s=%s is not in %s but is relative to the working directory; kept (write paths relative "
                     "to the config's folder)", yaml_path, key, val, base)
            continue
        out[key] = str(here)
    return out


def segmenter_config_class(name: str) -> type:
    """The frozen config dataclass of segmenter ``name``."""
    if name == "gt":
        return GTConfig
    if name == "noisy":
        return NoisyConfig
    if name == "grounded_sam":
        from torm.segmentation.grounded_sam import GroundedSAMConfig

        return GroundedSAMConfig
    if name == "learned":
        from torm.segmentation.learned import LearnedConfig

        return LearnedConfig
    if name == "difference":
        from torm.segmentation.reference import DifferenceConfig

        return DifferenceConfig
    raise UnknownNameError("segmenter", name, SEGMENTERS)


def make_segmenter(name: str, config: Any = None) -> Segmenter:
    """Build segmenter ``name`` from its config dataclass, a mapping of its fields, or None (defaults).

    Raises UnknownNameError (listing the names) for an unknown segmenter, ConfigError for a bad config,
    and ModelFileError when grounded_sam's or learned's model files are missing or do not match.
    """
    cls = segmenter_config_class(name)
    if config is None or isinstance(config, Mapping):
        config = from_dict(cls, dict(config or {}), where=name)
    elif not isinstance(config, cls):
        raise ConfigError(f"segmenter {name!r} needs a {cls.__name__} or a mapping, got {type(config).__name__}")
    if name == "gt":
        return GTSegmenter(config)
    if name == "noisy":
        return NoisySegmenter(config)
    if name == "learned":
        from torm.segmentation.learned import LearnedSegmenter

        return LearnedSegmenter(config)
    if name == "difference":
        from torm.segmentation.reference import DifferenceSegmenter

        return DifferenceSegmenter(config)
    from torm.segmentation.grounded_sam import GroundedSAMSegmenter

    return GroundedSAMSegmenter(config)


__all__ = [
    "PRESETS", "SEGMENTERS", "Detection", "GTConfig", "GTSegmenter", "NoiseConfig", "NoisyConfig", "NoisySegmenter",
    "SegmentationResult", "Segmenter", "corrupt_masks", "make_segmenter", "mask_quality", "segment_capture",
    "resolve_config_paths", "segmenter_config_class",
]
