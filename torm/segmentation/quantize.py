"""Static int8 quantization of a learned-segmenter model (onnxruntime, QDQ format, per-channel weights).

EfficientNet-Lite was designed to quantize well (ReLU6, no squeeze-excitation); an int8 copy of a model runs about
twice as fast on a CPU. :func:`quantize_model` calibrates the activation ranges on images the caller passes (renders
of the model's own validation split, never the frames a result is reported on), writes the int8 ONNX file and a card
beside it (the source card, its ``model`` renamed, plus ``quantized``: the source's fingerprint and how it was
calibrated). Inference needs only onnxruntime; quantizing needs the ``onnx`` package (``pip install
"torm-glass[models]"``).

Weights use 7 bits (``reduce_range``, the default): onnxruntime's u8s8 kernels can saturate on x86 CPUs without
VNNI (AVX2, early AVX-512), so a full-range model could read differently on the machines users run; the 7-bit
model reads the same on every x86 ISA within the kernels' rounding.
"""

from __future__ import annotations

import datetime as dt
import json
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError

#: calibration images: at least this many, at most that many (each is one network run at the model's input size)
MIN_CALIBRATION, MAX_CALIBRATION = 4, 512


def quantize_model(model: str | Path, out: str | Path, calibration_rgb: Sequence[np.ndarray],
                   calibration_source: str, reduce_range: bool = True, threads: int = 1) -> Path:
    """Write an int8 copy of a learned-segmenter model and its card; returns the ONNX path.

    Args:
        model: the fp32 model (a path or a shipped model's short name, as ``learned.model`` takes it).
        out: the ``.onnx`` file to write (its card goes beside it as ``.json``).
        calibration_rgb: (H, W, 3) uint8 RGB images the activation ranges are calibrated on, read exactly as the
            segmenter reads a view (resized to the model's input width, padded to its stride); 4 to 512 of them.
        calibration_source: where the images came from (written into the card), e.g.
            ``"runs/seg_data/v7/val (48 renders)"``.
        reduce_range: 7-bit weights (see the module docstring); False only for VNNI-only deployments.
        threads: onnxruntime threads while calibrating.
    """
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter, model_fingerprint

    n = len(calibration_rgb)
    if not MIN_CALIBRATION <= n <= MAX_CALIBRATION:
        raise ConfigError(f"quantize_model: {n} calibration images; pass {MIN_CALIBRATION} to {MAX_CALIBRATION} "
                          "renders of the model's validation split")
    out = Path(out)
    if out.suffix != ".onnx":
        raise ConfigError(f"quantize_model: the output {out} must be an .onnx file")
    try:
        from onnxruntime.quantization import (
            CalibrationDataReader,
            QuantFormat,
            QuantType,
            quant_pre_process,
            quantize_static,
        )
    except ImportError as exc:  # onnxruntime.quantization imports onnx
        raise ConfigError('quantizing a model needs the onnx package: pip install "torm-glass[models]"') from exc
    seg = LearnedSegmenter(LearnedConfig(model=str(model), threads=threads))
    if seg.needs_reference:
        raise ConfigError(f"{seg.config.model_path.name} is a reference-mode model; quantize_model takes RGB models")
    inputs = []
    for rgb in calibration_rgb:
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ConfigError(f"calibration images must be (H, W, 3) uint8 RGB, got {rgb.shape} {rgb.dtype}")
        inputs.append({"image": seg.network_input(rgb)[0]})

    class _Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._it = iter(inputs)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self._it, None)

    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(seg.config.model_path), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(out), _Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        reduce_range=reduce_range, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    card: dict[str, Any] = dict(seg.card)
    card["model"] = out.name
    card["quantized"] = {
        "from": model_fingerprint(seg.config.model_path), "format": "onnxruntime QDQ, int8 weights per channel, "
        "uint8 activations", "reduce_range": bool(reduce_range), "calibration": f"{n} images: {calibration_source}",
        "method": "MinMax", "produced_by": "torm.segmentation.quantize.quantize_model",
        "date_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    if card.get("postprocess"):
        card["quantized"]["postprocess"] = "the fp32 model's, copied"
    out.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")
    return out


__all__ = ["MAX_CALIBRATION", "MIN_CALIBRATION", "quantize_model"]
