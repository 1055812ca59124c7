"""Export Grounding DINO and SAM (Hugging Face ``transformers`` models) to the ONNX files torm's ``grounded_sam``
segmenter loads (``pip install 'torm[models]'``).

The signatures are the ones :mod:`torm.segmentation.grounded_sam` documents:

- **Grounding DINO** (:class:`GroundingDinoOnnx`): inputs ``img`` (1, 3, H, W) at a static size, ``input_ids``,
  ``attention_mask``, ``position_ids``, ``token_type_ids`` (1, T) and ``text_token_mask`` (1, T, T) at a static
  token count; outputs ``logits`` (1, Q, 256) and ``boxes`` (1, Q, 4). The phrase mask and position ids are inputs
  (torm computes them, :func:`torm.segmentation.tokenizer.grounding_text_inputs`): the model's own helper uses
  ``aten::isin``, which the TorchScript exporter cannot export.
- **SAM image encoder**: ``image`` (1, 3, S, S) -> ``image_embeddings`` (1, 256, S/16, S/16), S = 1024 for SAM.
- **SAM mask decoder** (:class:`SamDecoderOnnx`): segment-anything's ``scripts/export_onnx_model.py`` signature,
  rebuilt on ``transformers``' ``SamModel``: ``image_embeddings``, ``point_coords`` (1, N, 2) in the resized
  frame, ``point_labels`` (1, N) (0/1 points, 2/3 box corners, -1 padding), ``mask_input`` (1, 1, 256, 256),
  ``has_mask_input`` (1,), ``orig_im_size`` (2,) -> ``masks`` (1, C, H, W) logits at the original size,
  ``iou_predictions`` (1, C), ``low_res_masks`` (1, C, 256, 256).

Weights: :func:`load_models` reads a local folder or the Hugging Face cache (``IDEA-Research/grounding-dino-tiny``,
``facebook/sam-vit-base``; a machine with internet downloads them once); ``random_weights=True`` builds the same
architectures from their configs with random weights, which is how the tests and the timing benchmark verify the
export here (no weights can be downloaded on the build machines). Every export writes a model card
(``<file>.json``: source, licence, sha256, opset, input and output names and shapes, ``random_weights``, the
sha256 of every file of the source folder, and for Grounding DINO the vocabulary's size, sha256 and the special
token ids the weights hard-code).

Loading refuses what would export silently wrong: a checkpoint whose ``model_type`` is not the requested
architecture (a SAM 2 folder given as SAM), and any checkpoint that leaves a weight freshly initialised (missing
or shape-mismatched tensors, named) -- only ``random_weights=True`` builds a model whose weights are not loaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torm.errors import ConfigError, ModelFileError

log = logging.getLogger(__name__)

#: Opset of every export (the TorchScript exporter's well-trodden one for both models).
OPSET = 17
#: Hugging Face ids and licences of the published weights.
GDINO_ID, GDINO_LICENCE = "IDEA-Research/grounding-dino-tiny", "Apache-2.0"
SAM_ID, SAM_LICENCE = "facebook/sam-vit-base", "Apache-2.0"
#: the small SAM-family model for CPUs: SAM 2.1 Hiera-Tiny (transformers has no MobileSAM or EfficientSAM class)
SAM2_ID, SAM2_LICENCE = "facebook/sam2.1-hiera-tiny", "Apache-2.0"
#: which SAM an export holds (``torm export-models --sam-kind``)
SAM_KINDS = ("sam", "sam2")


def _torch():
    try:
        import torch
        import transformers  # noqa: F401
    except ImportError as exc:
        raise ConfigError("exporting models needs transformers: pip install 'torm[models]'") from exc
    return torch


@contextlib.contextmanager
def _given_text_masks(mask: Any, position_ids: Any) -> Iterator[None]:
    """Make Grounding DINO use the phrase mask and position ids it is given instead of computing them."""
    from transformers.models.grounding_dino import modeling_grounding_dino as m

    original = m.generate_masks_with_special_tokens_and_transfer_map
    m.generate_masks_with_special_tokens_and_transfer_map = lambda *a, **k: (mask, position_ids)
    try:
        yield
    finally:
        m.generate_masks_with_special_tokens_and_transfer_map = original


def _gdino_wrapper(model: Any) -> Any:
    torch = _torch()

    class GroundingDinoOnnx(torch.nn.Module):
        """``transformers``' GroundingDinoForObjectDetection with torm's input signature (module docstring)."""

        def __init__(self, inner: Any) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, img, input_ids, attention_mask, position_ids, token_type_ids, text_token_mask):
            with _given_text_masks(text_token_mask.bool(), position_ids):
                out = self.inner(pixel_values=img, input_ids=input_ids, attention_mask=attention_mask,
                                 token_type_ids=token_type_ids)
            return out.logits, out.pred_boxes

    return GroundingDinoOnnx(model)


def _sam_decoder_wrapper(sam: Any, image_size: int, multimask: bool) -> Any:
    torch = _torch()
    from torch.nn import functional

    class SamDecoderOnnx(torch.nn.Module):
        """segment-anything's ONNX decoder signature on ``transformers``' SamModel (module docstring)."""

        def __init__(self, inner: Any) -> None:
            super().__init__()
            self.sam = inner

        def forward(self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size):
            pe = self.sam.prompt_encoder
            coords = (point_coords + 0.5) / image_size  # pixel centres, normalised to [0, 1]
            sparse = self.sam.shared_image_embedding(coords[:, None])  # (1, 1, N, C)
            labels = point_labels[:, None, :, None]
            sparse = torch.where(labels == -1, pe.not_a_point_embed.weight.to(sparse.dtype), sparse)
            for i in range(len(pe.point_embed)):
                sparse = sparse + pe.point_embed[i].weight * (labels == i).to(sparse.dtype)
            has = has_mask_input.reshape(-1, 1, 1, 1)
            dense = has * pe.mask_embed(mask_input) + (1 - has) * pe.no_mask_embed.weight.reshape(1, -1, 1, 1)
            masks, iou = self.sam.mask_decoder(image_embeddings, self.sam.get_image_wide_positional_embeddings(),
                                               sparse, dense, multimask_output=multimask)
            low = masks[:, 0]
            up = functional.interpolate(low, size=(image_size, image_size), mode="bilinear", align_corners=False)
            orig = orig_im_size.to(torch.float32)
            pre = torch.floor(orig * (image_size / torch.max(orig)) + 0.5).to(torch.int64)
            up = up[..., : pre[0], : pre[1]]
            hw = orig_im_size.to(torch.int64)
            up = functional.interpolate(up, size=(hw[0], hw[1]), mode="bilinear", align_corners=False)
            return up, iou[:, 0], low

    return SamDecoderOnnx(sam)


def _sam_encoder_wrapper(sam: Any) -> Any:
    torch = _torch()

    class SamEncoderOnnx(torch.nn.Module):
        def __init__(self, inner: Any) -> None:
            super().__init__()
            self.sam = inner

        def forward(self, image):
            return self.sam.get_image_embeddings(image)

    return SamEncoderOnnx(sam)


def _sam2_encoder_wrapper(sam2: Any) -> Any:
    torch = _torch()

    class Sam2EncoderOnnx(torch.nn.Module):
        """SAM 2's image encoder: the embeddings and the two high-resolution feature maps its decoder reads."""

        def __init__(self, inner: Any) -> None:
            super().__init__()
            self.sam2 = inner

        def forward(self, image):
            s0, s1, emb = self.sam2.get_image_embeddings(image)
            return emb, s0, s1

    return Sam2EncoderOnnx(sam2)


def _sam2_decoder_wrapper(sam2: Any, multimask: bool) -> Any:
    torch = _torch()
    from torch.nn import functional

    class Sam2DecoderOnnx(torch.nn.Module):
        """SAM 2's mask decoder with the segment-anything-style signature plus the high-resolution features
        (module docstring). Points as SAM 2's predictor gives them: box corners are points labelled 2/3, and a
        padding point is appended; masks are resized from 256 x 256 straight to the original size (SAM 2 resizes
        the image to a square, no padding)."""

        def __init__(self, inner: Any) -> None:
            super().__init__()
            self.sam2 = inner

        def forward(self, image_embeddings, high_res_feats_0, high_res_feats_1, point_coords, point_labels,
                    mask_input, has_mask_input, orig_im_size):
            pe = self.sam2.prompt_encoder
            sparse = pe._embed_points(point_coords[:, None], point_labels[:, None].to(torch.int64), pad=True)
            has = has_mask_input.reshape(-1, 1, 1, 1)
            dense = has * pe.mask_embed(mask_input) + (1 - has) * pe.no_mask_embed.weight.reshape(1, -1, 1, 1)
            masks, iou, _, _ = self.sam2.mask_decoder(
                image_embeddings=image_embeddings,
                image_positional_embeddings=self.sam2.get_image_wide_positional_embeddings(),
                sparse_prompt_embeddings=sparse, dense_prompt_embeddings=dense, multimask_output=multimask,
                high_resolution_features=[high_res_feats_0, high_res_feats_1])
            low = masks[:, 0]
            hw = orig_im_size.to(torch.int64)
            up = functional.interpolate(low, size=(hw[0], hw[1]), mode="bilinear", align_corners=False)
            return up, iou[:, 0], low

    return Sam2DecoderOnnx(sam2)


@dataclass(frozen=True)
class ExportedModel:
    """One exported file: its path, what it holds and its card (also written beside it as ``<file>.json``)."""

    path: Path
    card: dict[str, Any]


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _float_grid_samples(path: Path) -> int:
    """Cast double inputs of GridSample nodes to float in the ONNX file at ``path`` (in place); returns how many.

    transformers' multi-scale deformable attention can trace a float64 sampling grid (its reference points), and
    onnxruntime implements GridSample for float only ("Could not find an implementation for GridSample(16)").
    """
    import onnx
    from onnx import TensorProto, helper

    model = onnx.load(str(path))
    inferred = onnx.shape_inference.infer_shapes(model)
    types = {v.name: v.type.tensor_type.elem_type for v in [*inferred.graph.value_info, *inferred.graph.input]}
    nodes, n = [], 0
    for node in model.graph.node:
        if node.op_type == "GridSample":
            for k, name in enumerate(node.input):
                if types.get(name) == TensorProto.DOUBLE:
                    cast_out = f"{name}__as_float_{n}"
                    nodes.append(helper.make_node("Cast", [name], [cast_out], to=TensorProto.FLOAT,
                                                  name=f"{node.name}_cast_{k}"))
                    node.input[k] = cast_out
                    n += 1
        nodes.append(node)
    if n:
        del model.graph.node[:]
        model.graph.node.extend(nodes)
        onnx.save(model, str(path))
    return n


def _export(module: Any, args: tuple, names_in: list[str], names_out: list[str], path: Path,
            card: dict[str, Any], dynamic_axes: dict | None = None) -> ExportedModel:
    torch = _torch()
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    module.eval()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)  # static shapes are intended
        torch.onnx.export(module, args, str(path), input_names=names_in, output_names=names_out, opset_version=OPSET,
                          dynamic_axes=dynamic_axes or {}, dynamo=False, do_constant_folding=True)
    n_cast = _float_grid_samples(path)
    if n_cast:
        card = {**card, "grid_sample_casts": n_cast}
    card = {**card, "file": path.name, "sha256": sha256(path), "bytes": path.stat().st_size, "opset": OPSET,
            "inputs": {n: list(a.shape) for n, a in zip(names_in, args, strict=True)}, "outputs": names_out,
            "export_s": round(time.perf_counter() - t0, 2), "torch": torch.__version__}
    path.with_suffix(path.suffix + ".json").write_text(json.dumps(card, indent=2) + "\n")
    log.info("exported %s (%.0f MB) in %.1f s", path, card["bytes"] / 1e6, card["export_s"])
    return ExportedModel(path, card)


def export_grounding_dino(model: Any, out: Path, image_hw: tuple[int, int] = (800, 1333), n_tokens: int = 8,
                          source: str = GDINO_ID, card_extra: dict[str, Any] | None = None) -> ExportedModel:
    """Export ``model`` (a ``GroundingDinoForObjectDetection``) at a static image size (H, W px) and token count
    (the maximum a prompt may have with ``[CLS]``/``[SEP]``; torm pads shorter ones and refuses longer ones).
    ``card_extra``: more card fields (:func:`provenance`, :func:`vocab_card`). Returns the file and its card."""
    torch = _torch()
    h, w = image_hw
    ids = torch.full((1, n_tokens), 1012, dtype=torch.int64)
    ids[0, 0], ids[0, -1] = 101, 102
    args = (torch.randn(1, 3, h, w), ids, torch.ones(1, n_tokens, dtype=torch.int64),
            torch.arange(n_tokens, dtype=torch.int64)[None], torch.zeros(1, n_tokens, dtype=torch.int64),
            torch.eye(n_tokens, dtype=torch.bool)[None])
    names = ["img", "input_ids", "attention_mask", "position_ids", "token_type_ids", "text_token_mask"]
    card = {"model": "grounding_dino", "source": source, "licence": GDINO_LICENCE, "image_hw": [h, w],
            "n_tokens": n_tokens, "max_tokens": n_tokens, **(card_extra or {}), "config": model.config.to_diff_dict()}
    return _export(_gdino_wrapper(model), args, names, ["logits", "boxes"], out, card)


def export_sam(model: Any, encoder_out: Path, decoder_out: Path, multimask: bool = False,
               source: str = SAM_ID, card_extra: dict[str, Any] | None = None) -> tuple[ExportedModel, ExportedModel]:
    """Export ``model`` (a ``SamModel``) as torm's image encoder and segment-anything-style mask decoder
    (``multimask``: 3 masks per prompt, else 1); ``card_extra``: more card fields (:func:`provenance`). Returns
    both files with their cards."""
    torch = _torch()
    size = int(model.config.vision_config.image_size)
    side = int(model.config.prompt_encoder_config.image_embedding_size)
    enc = _export(_sam_encoder_wrapper(model), (torch.randn(1, 3, size, size),), ["image"], ["image_embeddings"],
                  encoder_out, {"model": "sam_image_encoder", "source": source, "licence": SAM_LICENCE,
                                "image_size": size, **(card_extra or {}),
                                "config": model.config.vision_config.to_diff_dict()})
    args = (torch.randn(1, 256, side, side), torch.tensor([[[10.0, 20.0], [200.0, 300.0]]]),
            torch.tensor([[2.0, 3.0]]), torch.zeros(1, 1, 4 * side, 4 * side), torch.zeros(1),
            torch.tensor([480.0, 640.0]))
    names = ["image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size"]
    dec = _export(_sam_decoder_wrapper(model, size, multimask), args, names,
                  ["masks", "iou_predictions", "low_res_masks"], decoder_out,
                  {"model": "sam_mask_decoder", "source": source, "licence": SAM_LICENCE, "multimask": multimask,
                   **(card_extra or {})},
                  dynamic_axes={"point_coords": {1: "n_points"}, "point_labels": {1: "n_points"},
                                "masks": {2: "height", 3: "width"}})
    return enc, dec


def export_sam2(model: Any, encoder_out: Path, decoder_out: Path, multimask: bool = False,
                source: str = SAM2_ID, card_extra: dict[str, Any] | None = None) -> tuple[ExportedModel, ExportedModel]:
    """Export ``model`` (a ``transformers`` ``Sam2Model``) as torm's SAM 2 image encoder (``image`` ->
    ``image_embeddings``, ``high_res_feats_0``, ``high_res_feats_1``) and mask decoder (the SAM decoder's inputs
    plus the two feature maps); ``card_extra``: more card fields (:func:`provenance`). Returns both files with their
    cards (``sam_kind: sam2``)."""
    torch = _torch()
    size = int(model.config.vision_config.backbone_config.image_size[0])
    side = int(model.config.prompt_encoder_config.image_size // model.config.prompt_encoder_config.patch_size)
    base = {"source": source, "licence": SAM2_LICENCE, "sam_kind": "sam2", **(card_extra or {})}
    enc = _export(_sam2_encoder_wrapper(model), (torch.randn(1, 3, size, size),), ["image"],
                  ["image_embeddings", "high_res_feats_0", "high_res_feats_1"], encoder_out,
                  {"model": "sam2_image_encoder", **base, "image_size": size,
                   "config": model.config.vision_config.to_diff_dict()})
    c0, c1 = (int(model.mask_decoder.conv_s0.out_channels), int(model.mask_decoder.conv_s1.out_channels))
    args = (torch.randn(1, 256, side, side), torch.randn(1, c0, 4 * side, 4 * side),
            torch.randn(1, c1, 2 * side, 2 * side), torch.tensor([[[10.0, 20.0], [200.0, 300.0]]]),
            torch.tensor([[2.0, 3.0]]), torch.zeros(1, 1, 4 * side, 4 * side), torch.zeros(1),
            torch.tensor([480.0, 640.0]))
    names = ["image_embeddings", "high_res_feats_0", "high_res_feats_1", "point_coords", "point_labels",
             "mask_input", "has_mask_input", "orig_im_size"]
    dec = _export(_sam2_decoder_wrapper(model, multimask), args, names,
                  ["masks", "iou_predictions", "low_res_masks"], decoder_out,
                  {"model": "sam2_mask_decoder", **base, "multimask": multimask},
                  dynamic_axes={"point_coords": {1: "n_points"}, "point_labels": {1: "n_points"},
                                "masks": {2: "height", 3: "width"}})
    return enc, dec


#: ``model_type`` of each architecture's ``config.json``
MODEL_TYPES = {"grounding_dino": "grounding-dino", "sam": "sam", "sam2": "sam2"}
_NAMES = {"grounding_dino": "Grounding DINO", "sam": "SAM", "sam2": "SAM 2"}
_FLAGS = {"grounding_dino": "--gdino", "sam": "--sam", "sam2": "--sam (with --sam-kind sam2)"}


def _load_checked(cls: Any, source: str, kind: str) -> Any:
    """``cls.from_pretrained(source)`` that refuses another architecture's checkpoint and any weight left freshly
    initialised (missing or shape-mismatched tensors), naming them (:class:`ModelFileError`)."""
    from transformers import AutoConfig

    name, flag = _NAMES[kind], _FLAGS[kind]
    try:
        cfg = AutoConfig.from_pretrained(source)
    except (OSError, ValueError, KeyError) as exc:
        raise ModelFileError(f"cannot load {name} from {source!r} ({exc}); give a local folder with {flag}, run once "
                             "on a machine with internet to fill the Hugging Face cache, or pass --random-weights to "
                             "verify the export with the real architecture") from exc
    if cfg.model_type != MODEL_TYPES[kind]:
        other = {v: k for k, v in MODEL_TYPES.items()}.get(cfg.model_type)
        hint = (f"export it with --sam-kind {other}" if other in ("sam", "sam2") and kind in ("sam", "sam2")
                else f"point {flag} at a {name} checkpoint")
        raise ModelFileError(f"{source} holds a {cfg.model_type!r} checkpoint, not {name} ({MODEL_TYPES[kind]!r}): "
                             f"every weight would be freshly initialised; {hint}")
    try:
        model, info = cls.from_pretrained(source, output_loading_info=True)
    except (OSError, ValueError, RuntimeError) as exc:
        raise ModelFileError(f"cannot load {name} from {source!r} ({exc}); check the folder's files") from exc
    missing = sorted(str(k) for k in info.get("missing_keys") or ())
    missing += sorted(str(m[0] if isinstance(m, (tuple, list)) else m) for m in info.get("mismatched_keys") or ())
    if missing:
        shown = ", ".join(missing[:12]) + (f", ... ({len(missing)} in all)" if len(missing) > 12 else "")
        raise ModelFileError(f"{source}: {len(missing)} {name} weight(s) are not in the checkpoint (or have another "
                             f"shape) and would be freshly initialised: {shown}; give the complete checkpoint, or "
                             "pass --random-weights for an export whose weights are all random")
    return model.eval()


def source_files_sha256(source: str) -> dict[str, str] | None:
    """sha256 of every file (relative path -> hex) of a local model folder or of the Hugging Face cache's snapshot
    of a model id; None when neither is found (nothing to hash)."""
    folder = Path(source)
    if not folder.is_dir():
        try:
            from huggingface_hub import snapshot_download

            folder = Path(snapshot_download(source, local_files_only=True))
        except Exception:  # noqa: BLE001 - no cache entry: the card says so (None)
            return None
    return {p.relative_to(folder).as_posix(): sha256(p) for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)}


def provenance(source: str, random_weights: bool) -> dict[str, Any]:
    """The card fields that say where the weights come from: ``random_weights`` and the source files' sha256."""
    return {"random_weights": bool(random_weights),
            "source_files_sha256": None if random_weights else source_files_sha256(source)}


def load_sam2(sam2: str = SAM2_ID, random_weights: bool = False, tiny: bool = False, seed: int = 0) -> Any:
    """SAM 2 as a ``transformers`` ``Sam2Model``: from ``sam2`` (a local folder or a Hugging Face id in the cache),
    or, with ``random_weights``, built from the default config (SAM 2.1 Hiera-Tiny's architecture) or, with
    ``tiny``, from a small config of the same classes (tests)."""
    torch = _torch()
    from transformers import Sam2Config, Sam2Model

    if not random_weights:
        return _load_checked(Sam2Model, sam2, "sam2")
    torch.manual_seed(seed)
    if tiny:
        cfg = Sam2Config(
            vision_config={"backbone_config": {"model_type": "sam2_hiera_det_model", "hidden_size": 16,
                                               "blocks_per_stage": [1, 1, 2, 1],
                                               "embed_dim_per_stage": [16, 32, 64, 128],
                                               "num_attention_heads_per_stage": [1, 1, 1, 1],
                                               "global_attention_blocks": [3]},
                           "backbone_channel_list": [128, 64, 32, 16]},
            mask_decoder_config={"num_hidden_layers": 1})
    else:
        cfg = Sam2Config()
    m = Sam2Model(cfg).eval()
    with torch.no_grad():  # as for SAM: informative random weights
        for p in m.parameters():
            if p.dim() > 1:
                p.normal_(0.0, 0.02)
    return m


def load_models(gdino: str | None = GDINO_ID, sam: str = SAM_ID, random_weights: bool = False,
                tiny: bool = False, seed: int = 0, with_sam: bool = True, with_gdino: bool = True
                ) -> tuple[Any, Any]:
    """Grounding DINO and SAM as ``transformers`` models: from ``gdino`` / ``sam`` (a local folder or a Hugging
    Face id in the cache), or, with ``random_weights``, built from their default configs (the published
    architectures: Swin-T + BERT-base Grounding DINO, SAM ViT-B) or, with ``tiny``, from small configs of the
    same classes (tests). Random weights are drawn from a generator seeded with ``seed``. ``with_sam`` /
    ``with_gdino`` False: that model is not loaded (None in its place).

    Raises:
        ModelFileError: a checkpoint of another architecture, or one that leaves weights freshly initialised
            (named); or no checkpoint found.
    """
    torch = _torch()
    from transformers import GroundingDinoConfig, GroundingDinoForObjectDetection, SamConfig, SamModel

    if not random_weights:
        return (_load_checked(GroundingDinoForObjectDetection, gdino or GDINO_ID, "grounding_dino")
                if with_gdino else None,
                _load_checked(SamModel, sam, "sam") if with_sam else None)
    torch.manual_seed(seed)
    if tiny:
        gcfg = GroundingDinoConfig(
            backbone_config={"model_type": "swin", "embed_dim": 16, "depths": [1, 1, 1, 1], "num_heads": [1, 1, 1, 1],
                             "window_size": 7, "out_features": ["stage2", "stage3", "stage4"]},
            text_config={"model_type": "bert", "hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2,
                         "intermediate_size": 64},
            d_model=32, encoder_layers=1, decoder_layers=2, encoder_ffn_dim=64, decoder_ffn_dim=64,
            encoder_attention_heads=2, decoder_attention_heads=2, num_queries=30, num_feature_levels=4)
        scfg = SamConfig(vision_config={"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2,
                                        "mlp_dim": 64, "global_attn_indexes": [0], "window_size": 7},
                         mask_decoder_config={"num_hidden_layers": 1})
    else:
        gcfg, scfg = GroundingDinoConfig(), SamConfig()
    g = GroundingDinoForObjectDetection(gcfg).eval() if with_gdino else None
    s = SamModel(scfg).eval() if with_sam else None
    if s is not None:
        with torch.no_grad():  # transformers' init leaves SAM's embeddings near 1e-19: make them informative
            for p in s.parameters():
                if p.dim() > 1:
                    p.normal_(0.0, 0.02)
    return g, s


def tokenizer_vocab(tokenizer: Any) -> list[str]:
    """The tokens of a ``transformers`` tokenizer in id order, read from the tokenizer object itself
    (``get_vocab()``: whatever files its folder had, ``vocab.txt`` or only ``tokenizer.json``).

    Raises:
        ModelFileError: the ids are not 0..N-1 without gaps (a vocab.txt needs one token per id).
    """
    by_id = sorted((int(i), str(t)) for t, i in tokenizer.get_vocab().items())
    ids = [i for i, _ in by_id]
    if ids != list(range(len(ids))):
        gaps = sorted(set(range(max(ids) + 1)) - set(ids))[:5] if ids else []
        raise ModelFileError(f"the tokenizer's vocabulary has ids that are not 0..{len(ids) - 1} without gaps "
                             f"(missing e.g. {gaps}, or duplicates); give a BERT WordPiece tokenizer "
                             "(bert-base-uncased's)")
    return [t for _, t in by_id]


def write_tokenizer_vocab(tokenizer: Any, path: Path) -> Path:
    """Write ``tokenizer``'s vocabulary as ``vocab.txt`` (one token per line, line number = id) at ``path``."""
    tokens = tokenizer_vocab(tokenizer)
    bad = [t for t in tokens if "\n" in t or "\r" in t]
    if bad:
        raise ModelFileError(f"the tokenizer has token(s) with a line break ({bad[:3]!r}); they cannot be written "
                             "one per line")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(tokens) + "\n", encoding="utf-8")
    return path


def vocab_card(path: Path) -> dict[str, Any]:
    """The card fields that prove a vocabulary file: its name, line count, sha256 and the hard-coded special ids."""
    from torm.segmentation.tokenizer import GROUNDING_SPECIAL_IDS

    return {"vocab_file": path.name, "vocab_size": len(path.read_text(encoding="utf-8").splitlines()),
            "vocab_sha256": sha256(path), "special_token_ids": dict(GROUNDING_SPECIAL_IDS)}


def write_vocab(path: Path, size: int = 30522) -> Path:
    """A bert-base-uncased-shaped WordPiece vocabulary for random-weight checks (the ids Grounding DINO
    hard-codes: [PAD] 0, [UNK] 100, [CLS] 101, [SEP] 102, "." 1012, "?" 1029; real words for the default prompt).
    Use bert-base-uncased's own ``vocab.txt`` with real weights."""
    vocab = [f"[unused{i}]" for i in range(size)]
    vocab[0], vocab[100], vocab[101], vocab[102], vocab[103] = "[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"
    vocab[1012], vocab[1029], vocab[1010] = ".", "?", ","
    words = ("clear", "glass", "transparent", "object", "cup", "bottle", "beaker", "##s", "a", "an", "the", "plastic",
             "of", "and", "jar", "vase", "bowl", "wine", "water", "container")
    for i, w in enumerate(words):
        vocab[2000 + i] = w
    path.write_text("\n".join(vocab) + "\n")
    return path


__all__ = ["GDINO_ID", "MODEL_TYPES", "OPSET", "SAM2_ID", "SAM_ID", "SAM_KINDS", "ExportedModel",
           "export_grounding_dino", "export_sam", "export_sam2", "load_models", "load_sam2", "provenance", "sha256",
           "source_files_sha256", "tokenizer_vocab", "vocab_card", "write_tokenizer_vocab", "write_vocab"]
