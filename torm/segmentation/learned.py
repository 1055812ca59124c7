"""The learned segmenter: a small U-Net trained here on rendered scenes, run with onnxruntime.

It reads pixels only (no ground truth, no depth): per view, the network predicts an object-foreground
probability and an instance-boundary probability, and (models with the centre head) an instance-centre
probability and each pixel's offset to its instance's centre;
:func:`torm.segmentation.instances.instances_from_maps` turns them into instances (``grouping``: connected cores
grown back into the foreground, or pixels grouped by the centre their offsets vote for). Ids are per view, 1..N by
descending area, and do **not** correspond across views (like Grounded-SAM); the reconstruction uses the
union ``mask > 0``.

Model file signature (``model``; default the shipped ``models/learned_seg.onnx``):
    input  ``image`` (1, 3, H, W) float32, RGB in [0, 255] (normalisation is inside the graph), H and W
           multiples of 16 (torm pads bottom/right by edge replication);
    output ``logits`` (1, C, H, W) float32, C = 2, 5 or 6: channel 0 foreground, 1 boundary band, 2 instance
           centre (sigmoid -> prob), 3-4 offset (dy, dx) to the instance's centre in units of
           ``OFFSET_SCALE`` px of the network input, 5 (class-head models, v6) the logit that the pixel's object is
           transparent rather than opaque.

Classes (a prompt, as the paper's text prompt): ``classes`` names what to segment among :data:`CLASSES`. A class-head
model finds every object on the table, gives each instance the class its pixels vote for (mean transparent
probability >= 0.5) and keeps the prompted ones; ``("transparent", "opaque")`` also picks the opaque cup of RW2 and
RW5, as the paper's prompt does. A model without the class head (v3, v4, v4fast) answers the ``transparent`` prompt
only (v3 was trained with opaque objects labelled too, so it marks them as well).
The input size must be a multiple of the model's stride (its card's ``stride``: 32 for v6, else 16).

Each view is resized to ``input_width`` px wide (aspect kept), padded, run, cropped and the probabilities resized
back to the capture size (bilinear). Unset, ``input_width`` is the width of the frames the model was trained on
(its card's ``data.full_width``: 640 px for the shipped model, the pipeline's 640x360 frames of the 91.5 deg camera;
320 px for ``learned_seg_v4fast``), so that objects have the pixel size the model learned.
Training, data recipe and held-out metrics: the JSON beside the model file (``models/learned_seg.json``).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm import vocabulary as _vocab
from torm.errors import CaptureError, ConfigError, ModelFileError
from torm.segmentation.base import Detection, SegmentationResult, Segmenter, score_against_capture
from torm.segmentation.instances import instances_from_maps
from torm.segmentation.onnx_models import TensorSpec, open_session
from torm.types import Capture

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = MODELS_DIR / "learned_seg.onnx"
#: short names of the shipped models (``learned.model``): v3 (the default), v4 (trained for transfer to real photos),
#: v4ref (reference mode: reads each view with its empty-workspace view), v4fast (v4's recipe at 4 spp and 320 px),
#: v6 and v7 (photo-trained encoder, two classes; v7's opaque class finds the opaque objects a prompt names), v7q
#: (v7's int8 copy, :mod:`torm.segmentation.quantize`: 2.2x faster on a CPU, the same on renders)
SHIPPED_MODELS = {"v3": "learned_seg.onnx", "v4": "learned_seg_v4.onnx", "v4ref": "learned_seg_v4ref.onnx",
                  "v4fast": "learned_seg_v4fast.onnx", "v6": "learned_seg_v6.onnx", "v7": "learned_seg_v7.onnx",
                  "v7q": "learned_seg_v7q.onnx"}
#: the classes a prompt may name (``LearnedConfig.classes``); a class-head model's channel 5 separates them
CLASSES = _vocab.CLASSES
INPUTS = (TensorSpec("image", ("image",), (1, None, None, None)),)
#: input channel counts a model file may have: RGB, or RGB + the reference view's RGB (reference mode)
IN_CHANNELS = (3, 6)
OUTPUTS = (TensorSpec("logits", ("logits",), (1, None, None, None)),)
#: output channel counts a model file may have (without / with the centre head / with the class head too)
CHANNELS = (2, 5, 6)
STRIDE = 16
#: offsets are stored in units of this many px (must equal ``training.model.OFFSET_SCALE``; kept here so that
#: inference does not import torch)
OFFSET_SCALE = 10.0


def model_fingerprint(model: str | Path = "") -> str:
    """``<file name>@sha256:<first 12 hex>`` of a learned-segmenter model file (``""``: the shipped one; a short name
    such as ``v4``: that shipped model), or
    ``<file name>@missing``: what a result record names as the model that segmented it."""
    import hashlib

    path = LearnedConfig(model=str(model or "")).model_path  # a path or a shipped model's short name
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
    except OSError:
        return f"{path.name}@missing"
    return f"{path.name}@sha256:{digest}"


#: post-processing used when neither the config nor the model card sets it (the first model's untuned values;
#: ``grouping`` None = ``centre`` for a centre-head model, else ``boundary``)
POSTPROCESS_DEFAULTS: dict[str, Any] = {"fg_threshold": 0.5, "boundary_threshold": 0.5, "min_core_px": 8,
                                        "flip_tta": False, "grouping": None, "centre_threshold": 0.3, "nms_px": 5,
                                        "max_vote_px": 20.0}


@dataclass(frozen=True)
class LearnedConfig:
    """Settings of the learned segmenter (thresholds are probabilities; sizes in pixels of the capture).

    ``model`` empty = the shipped file. ``input_width`` 0 = the capture's own width; None (unset) = the width of
    the model's training frames (:func:`card_input_width`).
    ``min_area_px`` / ``min_core_px`` refer to the network input resolution.
    ``fg_threshold``, ``boundary_threshold``, ``min_core_px`` and ``flip_tta`` left unset (None) come from the
    model card's ``postprocess`` entry (calibrated on the model's validation split by
    ``benchmarks/seg_postprocess.py``), else 0.5, 0.5, 8 px and False. ``flip_tta``: average the probabilities
    with those of the horizontally flipped view (two network runs per view). ``grouping`` (``boundary``,
    ``centre``, ``hybrid``; centre-head models only for the last two), ``centre_threshold``, ``nms_px`` and
    ``max_vote_px`` (network input px) likewise come from the card when unset
    (:func:`torm.segmentation.instances.instances_from_maps`). ``classes``: the prompt, a non-empty subset of
    :data:`CLASSES` (what to segment). ``core_split_px`` (network input
    pixels, 0 = off): split an instance core at a neck this deep
    (:func:`torm.segmentation.instances.split_cores_at_necks`); off: at 4 px (chosen on val) it gained 0.003 object
    IoU on unseen layouts and 0.015 on held-out shapes for 0.3-0.5 more false positives per view
    (``benchmarks/results/seg_miss_causes.md``).
    """

    model: str = ""
    input_width: int | None = None
    fg_threshold: float | None = None
    boundary_threshold: float | None = None
    min_core_px: int | None = None
    flip_tta: bool | None = None
    grouping: str | None = None
    centre_threshold: float | None = None
    nms_px: int | None = None
    max_vote_px: float | None = None
    min_area_px: int = 30
    core_split_px: float = 0.0
    providers: tuple[str, ...] = ()
    threads: int = 0
    classes: tuple[str, ...] = ("transparent",)

    def __post_init__(self) -> None:
        from torm.segmentation.instances import GROUPINGS

        if isinstance(self.classes, str):  # "transparent" or "transparent,opaque" from a command line
            object.__setattr__(self, "classes", tuple(c.strip() for c in self.classes.split(",") if c.strip()))
        object.__setattr__(self, "classes", tuple(self.classes))
        bad = [c for c in self.classes if c not in CLASSES]
        if bad or not self.classes or len(set(self.classes)) != len(self.classes):
            raise ConfigError(f"learned.classes {list(self.classes)}: name each class once, among "
                              f"{', '.join(CLASSES)} (e.g. classes=transparent,opaque)")

        if self.grouping is not None and self.grouping not in GROUPINGS:
            raise ConfigError(f"learned.grouping {self.grouping!r}; valid choices: {', '.join(GROUPINGS)}")
        if (self.nms_px is not None and self.nms_px < 0) or (self.max_vote_px is not None and self.max_vote_px <= 0):
            raise ConfigError("learned: need nms_px >= 0 and max_vote_px > 0")
        for name in ("fg_threshold", "boundary_threshold", "centre_threshold"):
            v = getattr(self, name)
            if v is not None and not 0.0 < v < 1.0:
                raise ConfigError(f"learned.{name} = {v} must be in (0, 1)")
        w = self.input_width
        if w is not None and (w < 0 or 0 < w < STRIDE):
            raise ConfigError(f"learned.input_width must be 0 (capture width) or >= {STRIDE} px")
        if (self.min_core_px is not None and self.min_core_px < 1) or self.min_area_px < 0 or self.threads < 0:
            raise ConfigError("learned: need min_core_px >= 1, min_area_px >= 0, threads >= 0")
        if self.core_split_px < 0:
            raise ConfigError(f"learned.core_split_px = {self.core_split_px} must be >= 0 (0 turns the split off)")

    @property
    def model_path(self) -> Path:
        """The ONNX file: ``model`` as a path, a shipped model's short name (:data:`SHIPPED_MODELS`) or file stem
        (``learned_seg_v4``), or empty for the default."""
        if not self.model:
            return DEFAULT_MODEL
        if self.model in SHIPPED_MODELS:
            return MODELS_DIR / SHIPPED_MODELS[self.model]
        if "/" not in self.model and not self.model.endswith(".onnx") and (MODELS_DIR / f"{self.model}.onnx").is_file():
            return MODELS_DIR / f"{self.model}.onnx"  # a shipped file's stem, e.g. learned_seg_v4
        return Path(self.model).expanduser()

    def resolved_input_width(self) -> int:
        """The width (px) the network reads: ``input_width``, or unset the model card's (:func:`card_input_width`);
        0 = the capture's own width."""
        return int(self.input_width) if self.input_width is not None else card_input_width(self.model_path)


#: the input width of a model whose card names no training frame width (px): the pipeline's 640x360 frames
DEFAULT_INPUT_WIDTH = 640


def card_input_width(model_path: str | Path) -> int:
    """The width (px) of the frames a model was trained on, from its card (``<model>.json``: ``finetune.input_width``
    for a model fine-tuned on a user's frames, else ``data.full_width``):
    reading views at that width gives objects the pixel size the model learned. :data:`DEFAULT_INPUT_WIDTH` when the
    card is missing or names none."""
    return training_width(_read_card(model_path))


def card_capture_spp(model_path: str | Path) -> int | None:
    """The path-traced sample count per pixel a model reads at unchanged quality, from its card
    (``capture.pbr_spp``, measured by ``benchmarks/perception_speed.py`` and a closed-loop run); None when the card
    is missing or names none (the renderer's default count then applies)."""
    spp = (_read_card(model_path).get("capture") or {}).get("pbr_spp")
    return int(spp) if isinstance(spp, int) and spp >= 1 else None


def _read_card(model_path: str | Path) -> dict[str, Any]:
    """The model card beside ``model_path`` (``<model>.json``); ``{}`` when missing or unreadable."""
    card = Path(model_path).expanduser().with_suffix(".json")
    try:
        d = json.loads(card.read_text()) if card.is_file() else {}
    except (OSError, ValueError):
        d = {}
    return d if isinstance(d, dict) else {}


#: the post-processing keys that matter per grouping (for :func:`postprocess_label`)
_LABEL_KEYS = {"boundary": ("fg_threshold", "boundary_threshold", "min_core_px"),
               "centre": ("fg_threshold", "centre_threshold", "nms_px", "max_vote_px"),
               "hybrid": ("fg_threshold", "boundary_threshold", "min_core_px", "centre_threshold")}


def postprocess_label(model: str | Path = "", options: dict[str, Any] | None = None) -> str:
    """The post-processing a learned-segmenter run uses, as a result record names it (the model file's hash does not
    change when its card's calibration does): where it comes from (``config`` options, the model ``card``'s
    calibration, or the ``default``), the grouping, its thresholds and ``flip`` when flip TTA doubles the network
    runs, e.g. ``card: centre fg 0.3 centre 0.1 nms 15 vote 40``. Reads the card only; loads no model."""
    opts = {k: v for k, v in (options or {}).items() if k in POSTPROCESS_DEFAULTS and v is not None}
    post = _read_card(LearnedConfig(model=str(model or "")).model_path).get("postprocess") or {}
    pp = {k: opts.get(k, post.get(k, d)) for k, d in POSTPROCESS_DEFAULTS.items()}
    source = "config" if opts else ("card" if post else "default")
    grouping = pp["grouping"] or "auto"
    short = {"fg_threshold": "fg", "boundary_threshold": "boundary", "min_core_px": "core",
             "centre_threshold": "centre", "nms_px": "nms", "max_vote_px": "vote"}
    keys = _LABEL_KEYS.get(grouping, _LABEL_KEYS["hybrid"])
    text = " ".join(f"{short[k]} {float(pp[k]):g}" for k in keys)
    return f"{source}: {grouping} {text}" + (" flip" if pp["flip_tta"] else "")


def training_width(card: dict[str, Any]) -> int:
    """:func:`card_input_width` of an already loaded model card (px)."""
    card = card if isinstance(card, dict) else {}
    width = (card.get("finetune") or {}).get("input_width") or (card.get("data") or {}).get("full_width")
    return int(width) if width else DEFAULT_INPUT_WIDTH


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -30, 30)))


class LearnedSegmenter(Segmenter):
    """U-Net foreground + boundary on onnxruntime; the session is loaded (and checked) on construction."""

    name = "learned"

    def __init__(self, config: LearnedConfig | None = None) -> None:
        self.config = c = config or LearnedConfig()
        self.session = open_session(c.model_path, "learned.model", INPUTS, OUTPUTS, list(c.providers) or None,
                                    c.threads)
        ch = self.session.session.get_outputs()[0].shape[1]
        if ch not in CHANNELS:
            raise ModelFileError(f"{c.model_path}: output 'logits' has {ch} channels; the learned segmenter's "
                                 f"signature is (1, 2, H, W), with the centre head (1, 5, H, W), with the class "
                                 f"head (1, 6, H, W)")
        #: number of output maps (2, or 5 with the centre head)
        self.channels = int(ch)
        cin = self.session.session.get_inputs()[0].shape[1]
        if cin not in IN_CHANNELS:
            raise ModelFileError(f"{c.model_path}: input 'image' has {cin} channels; the learned segmenter reads "
                                 "(1, 3, H, W) RGB or, in reference mode, (1, 6, H, W) scene + reference RGB")
        #: 3 (RGB) or 6 (reference mode: each view's RGB and its empty-workspace reference view)
        self.in_channels = int(cin)
        card = c.model_path.with_suffix(".json")
        self.card: dict[str, Any] = json.loads(card.read_text()) if card.is_file() else {}
        #: the classes this model separates (a prompt may name only these)
        self.classes_available: tuple[str, ...] = CLASSES if self.channels == 6 else ("transparent",)
        missing = [k for k in c.classes if k not in self.classes_available]
        if missing:
            raise ConfigError(f"learned.classes {list(c.classes)}: {c.model_path.name} has no class head and segments "
                              f"only {', '.join(self.classes_available)}; drop {', '.join(missing)} from the prompt or "
                              f"use a class-head model (learned.model=v6, classes {', '.join(CLASSES)})")
        #: input sizes are padded to multiples of this (the model's card: 32 for an EfficientNet encoder)
        self.stride = int(self.card.get("stride") or STRIDE)
        #: the width (px) the network reads each view at; 0 = the view's own width
        self.input_width = int(c.input_width) if c.input_width is not None else training_width(self.card)
        post = self.card.get("postprocess", {})
        #: the post-processing in use: the config's values, else the card's calibration, else the defaults
        self.postprocess: dict[str, Any] = {k: getattr(c, k) if getattr(c, k) is not None else post.get(k, d)
                                            for k, d in POSTPROCESS_DEFAULTS.items()}
        if self.postprocess["grouping"] is None:
            self.postprocess["grouping"] = "centre" if self.channels >= 5 else "boundary"  # a centre head: 5 or 6
        if self.postprocess["grouping"] != "boundary" and self.channels < 5:
            raise ConfigError(f"learned.grouping {self.postprocess['grouping']!r} needs a model with the centre head "
                              f"(5 output channels); {c.model_path} has {self.channels}: use grouping 'boundary'")

    def probabilities(self, rgb: np.ndarray, flip_tta: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) foreground and boundary probabilities of one (H, W, 3) uint8 RGB image, at its own size.

        ``flip_tta`` (None = :attr:`postprocess`): the mean of the view's and its mirror image's probabilities.
        """
        m = self.maps(rgb, flip_tta)
        return m[0], m[1]

    @property
    def needs_reference(self) -> bool:
        """True for a reference-mode model: every view needs its empty-workspace view (``reference_rgb``)."""
        return self.in_channels == 6

    def maps(self, rgb: np.ndarray, flip_tta: bool | None = None, reference: np.ndarray | None = None) -> np.ndarray:
        """(C, H, W) float32 maps of one (H, W, 3) uint8 RGB image at its own size: foreground and boundary
        probabilities, and for a centre-head model the centre probability and the offsets (dy, dx) to the
        instance's centre in px of the image. ``flip_tta`` (None = :attr:`postprocess`): the mean of the view's and
        its mirror image's maps (the mirror's dx negated). ``reference``: the view of the empty workspace, (H, W, 3)
        uint8, required by (and only read by) a reference-mode model."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise CaptureError(f"the learned segmenter needs (H, W, 3) uint8 RGB images, got {rgb.shape} {rgb.dtype}")
        if self.needs_reference:
            if reference is None:
                raise CaptureError(f"{self.config.model_path.name} is a reference-mode model: each view needs its view "
                                   "of the empty workspace (a reference pass: --set capture.reference=true in "
                                   "simulation, torm segment --reference DIR for recorded frames), or use a model "
                                   "without reference (learned_seg.onnx)")
            reference = np.asarray(reference)
            if reference.shape != rgb.shape or reference.dtype != np.uint8:
                raise CaptureError(f"reference view {reference.shape} {reference.dtype} must match its view "
                                   f"{rgb.shape} uint8")
            rgb = np.concatenate([rgb, reference], axis=2)
        m = self._maps(rgb)
        if flip_tta if flip_tta is not None else self.postprocess["flip_tta"]:
            f = self._maps(np.ascontiguousarray(rgb[:, ::-1]))[:, :, ::-1]
            if len(f) >= 5:
                f[4] = -f[4]
            m = (m + f) / 2
        return m

    def network_input(self, rgb: np.ndarray) -> tuple[np.ndarray, int, int]:
        """(the (1, C, H', W') float32 tensor the network reads, th, tw) for an (H, W, 3 or 6) uint8 image: resized
        to :attr:`input_width` (th x tw px) and padded to multiples of :attr:`stride` by edge replication."""
        h, w = rgb.shape[:2]
        tw = self.input_width or w
        th = max(int(round(h * tw / w)), 1)
        ph, pw = -th % self.stride, -tw % self.stride
        parts = []
        for k in range(0, rgb.shape[2], 3):  # RGB (and the reference's RGB): OpenCV works on 3-channel images
            x = np.ascontiguousarray(rgb[..., k:k + 3])
            x = x if (th, tw) == (h, w) else cv2.resize(x, (tw, th), interpolation=cv2.INTER_AREA)
            if ph or pw:
                x = cv2.copyMakeBorder(x, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
            parts.append(x)
        x = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)
        return x.astype(np.float32).transpose(2, 0, 1)[None], th, tw

    def _maps(self, rgb: np.ndarray) -> np.ndarray:
        h, w = rgb.shape[:2]
        inp, th, tw = self.network_input(rgb)
        logits = self.session.run({"image": inp}, ("logits",))[0][0, :, :th, :tw].astype(np.float32)
        out = _sigmoid(logits)
        if len(out) >= 5:  # offsets in px of the image
            out[3] = logits[3] * OFFSET_SCALE * (h / th)
            out[4] = logits[4] * OFFSET_SCALE * (w / tw)
        if (th, tw) != (h, w):
            out = np.stack([cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR) for p in out])
        return out

    def segment_image(self, rgb: np.ndarray, reference: np.ndarray | None = None
                      ) -> tuple[np.ndarray, tuple[Detection, ...]]:
        """(H, W) int32 instance mask and one detection (box, mean foreground probability) per instance.
        ``reference``: the empty workspace's view (reference-mode models)."""
        c, pp = self.config, self.postprocess
        maps = self.maps(rgb, reference=reference)
        lin = rgb.shape[1] / (self.input_width or rgb.shape[1])  # image px per network input px
        mask, scores = instances_from_maps(
            maps[:5], pp["grouping"], pp["fg_threshold"], pp["boundary_threshold"],
            max(int(round(pp["min_core_px"] * lin ** 2)), 1), int(round(c.min_area_px * lin ** 2)),
            pp["centre_threshold"], max(int(round(pp["nms_px"] * lin)), 0), pp["max_vote_px"] * lin,
            c.core_split_px * lin)
        labels = ["object"] * len(scores)
        if len(maps) == 6:  # class head: each instance takes the class its pixels vote for; the prompt filters
            mask, scores, labels = select_classes(mask, scores, maps[5], c.classes)
        dets = []
        for i, (s, lab) in enumerate(zip(scores, labels, strict=True), start=1):
            ys, xs = np.nonzero(mask == i)
            dets.append(Detection((float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)), s,
                                  lab, i))
        return mask, tuple(dets)

    def check_domain(self, capture: Capture) -> dict[str, Any]:
        """Where this model was validated against the capture's domain (:func:`capture_domain`); warns once per
        model and domain when the model card (``validated_on``) does not list the domain as validated, with the
        score measured there when there is one. Returns ``{"domain", "validated", "measured"}``."""
        dom = capture_domain(capture)
        table = self.card.get("validated_on") or {}
        entry = table.get(dom) or {}
        validated = bool(entry.get("validated"))
        key = (str(self.config.model_path), dom)
        if not validated and key not in _DOMAIN_WARNED:
            _DOMAIN_WARNED.add(key)
            where = [f"{d} ({v['metric']} {v['value']})" for d, v in table.items() if v.get("validated")]
            there = (f"measured there: {entry['metric']} {entry['value']}" if entry.get("value") is not None
                     else "never validated there") + (f" ({entry['source']})" if entry.get("source") else "")
            log.warning("learned segmenter %s is used on %s images, a domain it was not validated on (%s); it was "
                        "validated on %s. Expect worse silhouettes; see torm/segmentation/README.md", self.config.
                        model_path.name, dom, there, ", ".join(where) or "nothing its card lists")
        return {"domain": dom, "validated": validated, "measured": entry.get("value")}

    def check_pixel_scale(self, capture: Capture) -> dict[str, Any] | None:
        """How large objects appear to the network against its training: the focal length in network-input pixels
        (the first view's ``fx`` x input width / view width) over that of the model's training frames (its card's
        ``data.full_width`` and ``hfov_deg``), and the range its training magnification covered (``train.zoom_range``).
        Warns once per model and image size when the ratio lies more than 1.5x outside that range, naming the
        ``input_width`` that reads at the trained scale. None when the card names no training camera, or the model was
        fine-tuned on a user's frames (their camera is not recorded). Unitless."""
        data, train = self.card.get("data") or {}, self.card.get("train") or {}
        if not data.get("full_width") or not data.get("hfov_deg") or self.card.get("finetune"):
            return None
        f_train = 0.5 * float(data["full_width"]) / np.tan(np.deg2rad(float(data["hfov_deg"])) / 2)
        v = capture.views[0]
        read_w = self.input_width or v.width
        ratio = float(v.K[0, 0]) * read_w / v.width / f_train
        lo, hi = (float(z) for z in train.get("zoom_range") or (1.0, 1.0))
        ok = lo / PIXEL_SCALE_SLACK <= ratio <= hi * PIXEL_SCALE_SLACK
        key = (str(self.config.model_path), f"scale {v.width}x{v.height} @{read_w}")
        if not ok and key not in _DOMAIN_WARNED:
            _DOMAIN_WARNED.add(key)
            best = int(round(v.width * f_train * np.sqrt(lo * hi) / float(v.K[0, 0]) / STRIDE)) * STRIDE
            log.warning("learned segmenter %s reads these %dx%d views at %d px wide, where objects appear %.2fx the "
                        "size of its training frames (it was trained on %.2f-%.2fx); expect worse silhouettes. Set "
                        "segmentation.options.input_width=%d to read them at its trained scale", self.config.
                        model_path.name, v.width, v.height, read_w, ratio, lo, hi, max(best, STRIDE))
        return {"ratio": ratio, "trained": [lo, hi], "within": ok}

    def segment(self, capture: Capture) -> SegmentationResult:
        t0 = time.perf_counter()
        domain = self.check_domain(capture)
        scale = self.check_pixel_scale(capture)
        masks, dets = [], []
        for i, view in enumerate(capture.views):
            if view.rgb is None:
                raise CaptureError(f"view {i} ({view.name!r}) has no RGB image; the learned segmenter reads pixels")
            m, d = self.segment_image(view.rgb, view.reference_rgb)
            masks.append(m)
            dets.append(d)
        out = np.stack(masks)
        info: dict[str, Any] = {"segmenter": self.name, "model": str(self.config.model_path),
                                "model_fingerprint": model_fingerprint(self.config.model_path), "domain": domain,
                                "input_width": self.input_width, "pixel_scale": scale,
                                "model_renderer": self.card.get("data", {}).get("renderer"),
                                "classes": list(self.config.classes),
                                "postprocess": dict(self.postprocess)}
        info.update(score_against_capture(out, capture))
        return SegmentationResult(out, tuple(dets), {"total": time.perf_counter() - t0}, info)


def select_classes(mask_hxw: np.ndarray, scores: list[float] | tuple[float, ...], p_transparent_hxw: np.ndarray,
                   classes: tuple[str, ...]) -> tuple[np.ndarray, list[float], list[str]]:
    """Keep the instances whose class is in ``classes``: an instance is ``transparent`` when the mean of
    ``p_transparent`` (probability, (H, W)) over its pixels is >= 0.5, else ``opaque``. Returns the relabelled
    (H, W) int32 mask (1..M in the input's order), the kept scores and their class names."""
    keep_ids, keep_scores, names = [], [], []
    for i, s in enumerate(scores, start=1):
        on = mask_hxw == i
        name = CLASSES[0] if on.any() and float(p_transparent_hxw[on].mean()) >= 0.5 else CLASSES[1]
        if name in classes:
            keep_ids.append(i)
            keep_scores.append(float(s))
            names.append(name)
    lut = np.zeros(len(scores) + 1, np.int32)
    lut[keep_ids] = np.arange(1, len(keep_ids) + 1, dtype=np.int32)
    return lut[mask_hxw], keep_scores, names


_SHIPPED: list[LearnedSegmenter] = []
#: how far (a factor) outside its training magnification a model may read objects before the pixel-scale warning
PIXEL_SCALE_SLACK = 1.5
#: (model path, domain) pairs already warned about in this process (the domain warning fires once).
_DOMAIN_WARNED: set[tuple[str, str]] = set()


def capture_domain(capture: Capture) -> str:
    """The image domain of a capture, from its metadata: ``mujoco``, ``pbr:llvm_ad_rgb``, ``pbr:scalar_rgb`` or
    ``recorded`` (no renderer named: real photos or third-party frames)."""
    r = str(capture.metadata.get("renderer") or "")
    if r.startswith("mujoco"):
        return "mujoco"
    if r.startswith("pbr"):
        return "pbr:scalar_rgb" if "scalar_rgb" in r else "pbr:llvm_ad_rgb"
    return r.split()[0] if r else "recorded"


def foreground_mask(rgb: np.ndarray) -> np.ndarray:
    """(H, W) bool foreground of the shipped model on one (H, W, 3) uint8 RGB image (instances merged).

    A ``MODULE:FUNCTION`` hook for ``benchmarks/render.py --segmenter torm.segmentation.learned:foreground_mask``:
    the render-noise agreement measured with the segmenter the pipeline runs, not a proxy. The session is
    created on the first call (the shipped ONNX file, onnxruntime's default threads) and kept.
    """
    if not _SHIPPED:
        _SHIPPED.append(LearnedSegmenter())
    return _SHIPPED[0].segment_image(rgb)[0] > 0
