"""Few-shot adaptation: fine-tune a learned segmenter on a handful of a user's labelled real frames.

A folder of frames with masks from any tool (hand-drawn, SAM clicks, a labelling app) is read by
:func:`load_labelled_frames`:

- ``DIR/images/<name>.(png|jpg|jpeg)`` with ``DIR/masks/<name>.png``, or
- flat: ``DIR/<name>.(png|jpg|jpeg)`` with ``DIR/<name>-mask.png`` or ``DIR/<name>_mask.png`` (ClearGrasp names its
  frames ``<id>-transparent-rgb-img.jpg`` and ``<id>-mask.png``: a ``-transparent-rgb-img`` suffix is dropped when
  looking for the mask).

A mask is 8- or 16-bit, 0 = background; binary masks (one value > 0) are split into 8-connected components, one
instance each (touching objects then merge, as in the source mask); instance-id masks are kept as they are. Every
frame is resized to ``input_width`` px wide (the width the segmenter runs at; masks nearest), then
:func:`finetune` continues training the model from its weights (BatchNorms frozen, the v4 augmentation: crops,
magnification, sensor effects) for ``steps`` steps and exports an ONNX file whose model card names the frames it
saw (file names and sha256), so that nobody later scores it on them as if they were unseen.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm.errors import ConfigError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: frames at most (a few-shot set: more belongs in a training recipe)
MAX_FRAMES = 200


def _mask_for(image: Path, root: Path) -> Path | None:
    if image.parent.name == "images":
        m = image.parent.parent / "masks" / f"{image.stem}.png"
        return m if m.is_file() else None
    stem = image.stem.removesuffix("-transparent-rgb-img")
    for cand in (f"{stem}-mask.png", f"{stem}_mask.png"):
        if (root / cand).is_file():
            return root / cand
    return None


def find_frames(folder: str | Path) -> list[tuple[Path, Path]]:
    """(image, mask) pairs of a fine-tune folder (see the module docstring); a named error when there are none."""
    root = Path(folder).expanduser()
    if not root.is_dir():
        raise ConfigError(f"fine-tune folder {root} does not exist; give a folder of frames with masks "
                          "(images/<name>.jpg + masks/<name>.png, or <name>.jpg + <name>-mask.png)")
    base = root / "images" if (root / "images").is_dir() else root
    images = sorted(p for p in base.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
                    and not p.stem.endswith(("-mask", "_mask")))
    pairs = [(p, m) for p in images if (m := _mask_for(p, root)) is not None]
    if not pairs:
        raise ConfigError(f"fine-tune folder {root}: no frame with a mask among {len(images)} image(s); put masks in "
                          f"{root / 'masks'}/<name>.png beside images/<name>.jpg, or name them <name>-mask.png")
    missing = [p.name for p in images if _mask_for(p, root) is None]
    if missing:
        log.warning("fine-tune folder %s: %d image(s) without a mask are skipped: %s", root, len(missing),
                    ", ".join(missing[:5]))
    if len(pairs) > MAX_FRAMES:
        raise ConfigError(f"fine-tune folder {root} holds {len(pairs)} labelled frames; few-shot takes at most "
                          f"{MAX_FRAMES}: train a recipe (torm train-segmenter --config) for more")
    return pairs


def instance_mask(mask_hxw: np.ndarray) -> np.ndarray:
    """(H, W) int32 instances of a mask: binary masks (one value > 0) split into 8-connected components."""
    m = np.asarray(mask_hxw)
    if m.ndim == 3:
        m = m[..., 0]
    vals = np.unique(m[m > 0])
    if len(vals) <= 1:
        _n, lab = cv2.connectedComponents((m > 0).astype(np.uint8), connectivity=8)
        return lab.astype(np.int32)
    return m.astype(np.int32)


def load_labelled_frames(folder: str | Path, input_width: int = 640) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """``rgb`` (N, H, W, 3) uint8 and ``mask`` (N, H, W) uint8 instances of a fine-tune folder, every frame resized
    to ``input_width`` px wide (all frames must then share one height), and a list of {file, sha256} per frame."""
    rgbs, masks, files = [], [], []
    for img_p, mask_p in find_frames(folder):
        bgr = cv2.imread(str(img_p), cv2.IMREAD_COLOR)
        m = cv2.imread(str(mask_p), cv2.IMREAD_UNCHANGED)
        if bgr is None or m is None:
            raise ConfigError(f"cannot read {img_p if bgr is None else mask_p}; use PNG or JPEG files")
        if m.shape[:2] != bgr.shape[:2]:
            raise ConfigError(f"mask {mask_p.name} is {m.shape[1]}x{m.shape[0]} px but its frame {img_p.name} is "
                              f"{bgr.shape[1]}x{bgr.shape[0]}: masks must have their frame's size (re-export them)")
        inst = instance_mask(m)
        if inst.max() > 255:
            raise ConfigError(f"mask {mask_p.name} has {inst.max()} instances; at most 255 per frame")
        h = int(round(bgr.shape[0] * input_width / bgr.shape[1]))
        rgbs.append(cv2.resize(bgr[..., ::-1], (input_width, h), interpolation=cv2.INTER_AREA))
        masks.append(cv2.resize(inst.astype(np.uint8), (input_width, h), interpolation=cv2.INTER_NEAREST))
        files.append({"image": img_p.name, "mask": mask_p.name,
                      "sha256": hashlib.sha256(img_p.read_bytes()).hexdigest()[:16]})
    heights = {r.shape[0] for r in rgbs}
    if len(heights) > 1:
        raise ConfigError(f"fine-tune frames have different aspect ratios (heights {sorted(heights)} px at width "
                          f"{input_width}); use frames of one camera")
    return np.stack(rgbs), np.stack(masks), files


def finetune(folder: str | Path, out: str | Path, base_model: str | Path = "", steps: int = 300,
             work: str | Path | None = None, threads: int = 1, seed: int = 0, input_width: int | None = None,
             progress: bool = True, lr: float = 2.5e-4, freeze: str = "", fg_crop_bias: float = 0.5,
             zoom_range: tuple[float, float] = (1.0, 2.0), anchor_weight: float = 0.0,
             select_on: str = "fg_iou", rehearsal_shards: int = 4, rehearsal_fraction: float = 0.5,
             rehearsal_data: str | Path | None = None) -> dict[str, Any]:
    """Fine-tune ``base_model`` (default: the shipped model) on the frames of ``folder`` for ``steps`` steps and
    export ``out`` (.onnx) with its card (.json). ``work`` (default ``<out>.work``) holds the resumable checkpoint.

    There is no validation split (a handful of frames): the exported weights are the best on the training frames
    themselves, which says nothing about other frames; measure on frames it did not see (``benchmarks/
    segmentation_real.py --finetune-loo`` does so leave-one-frame-out). ``base_model``: a path or a shipped model's
    short name (``v4``); ``input_width`` (px, None = the base model's training frame width; the fine-tuned card
    records it as ``finetune.input_width``): the width the frames are resized to, the width the fine-tuned model
    then reads.

    Rehearsal (``rehearsal_shards`` > 0, default 4 = 64 views, about 1.5 min to render on 2 cores): half of every
    batch (``rehearsal_fraction``) comes from renders of the base model's own data recipe (rendered once into
    ``rehearsal_data``, default ``<work>/rehearsal``), so that a few frames of one scene do not erase what the
    model knew. Leave one frame out on ClearGrasp's real frames (``benchmarks/results/segmentation_real.md``) it
    kept 0.38 mean IoU where plain fine-tuning fell to 0.26-0.28; neither beat the base model (0.47) on frames of
    other scenes and objects: fine-tune on frames of the objects and the place you will use it in.
    ``fg_crop_bias``: share of training windows centred on an object pixel; ``select_on``: the training-frame score
    that picks the exported checkpoint (``fg_iou``: union IoU, false positives count; ``object_iou``: per object);
    ``freeze="encoder"`` trains the decoder only; ``anchor_weight`` > 0 adds L2-SP towards the base weights."""
    from torm.segmentation.learned import LearnedConfig, card_input_width, model_fingerprint
    from torm.segmentation.training.model import SegUNet  # noqa: F401  (torch present: a clear ImportError early)
    from torm.segmentation.training.train import TrainConfig, export_onnx, load_best, train, write_card

    base = LearnedConfig(model=str(base_model or "")).model_path
    card_p = base.with_suffix(".json")
    if not base.is_file() or not card_p.is_file():
        raise ConfigError(f"base model {base} (and its card {card_p.name}) must exist; train one or use the shipped "
                          "model")
    base_card = json.loads(card_p.read_text())
    if steps < 1:
        raise ConfigError(f"fine-tune steps = {steps} must be >= 1")
    if rehearsal_shards < 0:
        raise ConfigError(f"rehearsal_shards = {rehearsal_shards} must be >= 0 (0 = no rehearsal)")
    out = Path(out)
    work = Path(work) if work else out.with_suffix(".work")
    input_width = int(input_width or card_input_width(base))
    rgb, mask, files = load_labelled_frames(folder, input_width)
    base_train = base_card.get("train", {})
    crop_h = min(192, rgb.shape[1] - rgb.shape[1] % 16)
    cfg = TrainConfig(**{**{k: v for k, v in base_train.items() if k in {f.name for f in dataclasses.fields(
        TrainConfig)}}, "steps": int(steps), "init_from": str(base), "freeze_bn": True, "threads": int(threads),
        "seed": int(seed), "lr": float(lr), "val_every": max(1, int(steps) // 4), "checkpoint_every": 50,
        "select_on": select_on, "val_split": "val", "crop": (crop_h, 256), "freeze": freeze,
        "anchor_weight": float(anchor_weight),
        "fg_crop_bias": float(fg_crop_bias), "zoom_range": tuple(zoom_range), "sensor_effects": 0.7})
    rehearsal = rehearsal_views(base_card, rehearsal_shards, Path(rehearsal_data) if rehearsal_data else
                                work / "rehearsal", progress) if rehearsal_shards else None
    if rehearsal is not None:
        cfg = dataclasses.replace(cfg, rehearsal_fraction=float(rehearsal_fraction))
    summary = train(cfg, rgb, mask, rgb, mask, work, progress=progress, rehearsal=rehearsal)
    net = load_best(work, cfg)
    export_onnx(net, out)
    card = {k: v for k, v in base_card.items() if k not in ("model", "training", "history", "validated_on")}
    card.update({"model": out.name, "finetuned_from": {"model": model_fingerprint(base), "card": base_card.get(
        "model")}, "finetune": {"folder": str(Path(folder)), "frames": files, "input_width": input_width,
                                "train": cfg.to_dict(), "rehearsal_shards": int(rehearsal_shards),
                                "selection": f"best {select_on.replace('_', ' ')} on the training frames"},
                 "training": {k: v for k, v in summary.items() if k != "history"}, "history": summary["history"],
                 "validated_on": {"recorded": {"validated": False, "metric": "union IoU", "value": None,
                                               "source": f"fine-tuned on {len(files)} frame(s) of {Path(folder).name}; "
                                                         "not measured on frames it did not see"}},
                 "produced_by": "torm train-segmenter --finetune"})
    write_card(out.with_suffix(".json"), card)
    return card


def rehearsal_views(base_card: dict[str, Any], shards: int, root: Path, progress: bool = True
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (M, h, w, 3) uint8, instance masks (M, h, w)) of the first ``shards`` ``train`` shards of the base
    model's own data recipe (its card's ``data``), rendered into ``root`` when missing (resumable; a shard of the v4
    recipe is 16 views, about a minute on 2 cores). A fine-tune draws part of every batch from them (rehearsal), so
    that a handful of frames of one scene does not erase what the model learnt from thousands of renders."""
    from torm.config import from_dict
    from torm.segmentation.training.dataset import DataRecipe, generate, load_split

    if "data" not in base_card:
        raise ConfigError(f"base model card {base_card.get('model')} has no data recipe to rehearse; fine-tune "
                          "without rehearsal (rehearsal_shards=0) or from a model trained by torm train-segmenter")
    recipe = from_dict(DataRecipe, {**base_card["data"], "shards": {"train": int(shards)}},
                       where="base model card data recipe")
    generate(recipe, root, splits=("train",), progress=progress)
    split = load_split(root, "train")
    n = int(shards) * recipe.scenes_per_shard * recipe.views_per_scene  # shards load in order: the first ones
    return split["rgb"][:n], split["mask"][:n]
