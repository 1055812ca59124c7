"""``torm export-models``: Grounding DINO and SAM to the ONNX files ``torm segment --segmenter grounded_sam`` loads.

Loads the models with ``transformers`` (``pip install 'torm[models]'``) from local folders or the Hugging Face
cache (a machine with internet downloads IDEA-Research/grounding-dino-tiny and facebook/sam-vit-base once), exports
them (:mod:`torm.segmentation.export`) and writes a segmenter config that points at the files, plus a model card
per file (source, licence, sha256, opset, shapes, ``random_weights``, the sha256 of the source folder's files and,
for Grounding DINO, the vocabulary's size, sha256 and special-token ids). The config's paths are relative to its own
folder, so the folder can be moved and ``torm segment`` run from anywhere.

A checkpoint of another architecture than the one asked for (a SAM 2 folder without ``--sam-kind sam2``), or one
that leaves any weight freshly initialised, is refused with the missing tensors named; only ``--random-weights``
exports random weights, and its cards say so (``random_weights: true``). The vocabulary is read from the tokenizer
object itself (``get_vocab()``), whatever files the folder holds (a transformers-5 ``save_pretrained`` folder has
no ``vocab.txt``), and written as ``vocab.txt`` beside the model.

Examples::

    torm export-models --out models/gsam                                   # the published weights
    torm export-models --out models/gsam --gdino ./gdino-tiny --sam ./sam-vit-base
    torm export-models --out /tmp/gsam --random-weights                    # the real architectures, random weights
    torm export-models --out models/sam2 --sam-kind sam2 --boxes learned   # SAM 2.1 Hiera-Tiny for CPUs, no DINO
    torm segment my_capture --segmenter grounded_sam --config models/gsam/grounded_sam.yaml

Grounding DINO is exported at a static image size (``--image-hw``, default 800 1333: the official resize of a
16:9 image) and a static token count, the most a prompt may have (``--max-tokens``, default 32 with
``[CLS]`` and ``[SEP]``: torm pads shorter prompts and refuses longer ones, naming their count); SAM at 1024 px.
``--sam-kind sam2`` exports SAM 2.1 Hiera-Tiny (facebook/sam2.1-hiera-tiny, Apache-2.0; the small SAM-family
model: transformers has no MobileSAM or EfficientSAM class) instead of SAM ViT-B; ``--boxes learned`` skips
Grounding DINO and writes a config in which torm's learned segmenter prompts SAM with its boxes (hybrid prompting).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torm.commands._common import add_parser, check_output_dir, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "export-models", __doc__,
                   help="export Grounding DINO and SAM (transformers) to torm's ONNX signatures")
    p.add_argument("--out", required=True, help="output folder for the ONNX files, their cards and the config")
    p.add_argument("--gdino", default=None, help="Grounding DINO folder or Hugging Face id "
                   "(default IDEA-Research/grounding-dino-tiny)")
    p.add_argument("--sam", default=None, help="SAM folder or Hugging Face id (default facebook/sam-vit-base, or "
                   "facebook/sam2.1-hiera-tiny with --sam-kind sam2)")
    p.add_argument("--sam-kind", choices=("sam", "sam2"), default="sam",
                   help="sam: SAM ViT-B (the paper's); sam2: SAM 2.1 Hiera-Tiny (about 3x fewer parameters)")
    p.add_argument("--boxes", choices=("gdino", "learned"), default="gdino",
                   help="gdino: export Grounding DINO too (the paper); learned: no Grounding DINO, the learned "
                   "segmenter's boxes prompt SAM")
    p.add_argument("--random-weights", action="store_true",
                   help="build the published architectures from their configs with random weights (no download)")
    p.add_argument("--tiny", action="store_true", help="with --random-weights: small configs of the same classes")
    p.add_argument("--image-hw", type=int, nargs=2, default=(800, 1333), metavar=("H", "W"),
                   help="Grounding DINO's static input size (default 800 1333)")
    p.add_argument("--prompt", default="clear glass. transparent object.",
                   help="the prompt written into the config (it must fit --max-tokens)")
    p.add_argument("--max-tokens", type=int, default=32, metavar="T",
                   help="Grounding DINO's static token count: the most a prompt may have, [CLS] and [SEP] included "
                        "(default 32; longer prompts are refused, never cut)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import yaml

    from torm.errors import ConfigError
    from torm.segmentation.export import (
        GDINO_ID,
        SAM2_ID,
        SAM_ID,
        export_grounding_dino,
        export_sam,
        export_sam2,
        load_models,
        load_sam2,
        provenance,
        vocab_card,
    )
    from torm.segmentation.tokenizer import WordPieceTokenizer, check_vocabulary, grounding_text_inputs

    if args.max_tokens < 3:
        raise ConfigError(f"--max-tokens {args.max_tokens}: need at least 3 ([CLS], one token, [SEP])")
    out = check_output_dir(args.out)
    files = []
    config: dict = {}
    s = None
    if args.boxes == "gdino":
        gdino_src = args.gdino or GDINO_ID
        g, s = load_models(gdino_src, args.sam or SAM_ID, random_weights=args.random_weights,
                           tiny=args.tiny, with_sam=args.sam_kind == "sam")
        vocab = _write_vocab(out / "vocab.txt", gdino_src, args.random_weights)
        tok = WordPieceTokenizer.from_file(vocab)
        check_vocabulary(tok)  # the ids Grounding DINO hard-codes
        grounding_text_inputs(tok, args.prompt, pad_to=args.max_tokens)  # refuses a prompt that does not fit
        gd = export_grounding_dino(g, out / "grounding_dino.onnx", tuple(args.image_hw), args.max_tokens,
                                   source=gdino_src,
                                   card_extra={**provenance(gdino_src, args.random_weights), **vocab_card(vocab)})
        files.append(gd)
        config = {"gdino_model": gd.path.name, "bert_vocab": vocab.name}
    else:
        config = {"box_source": "learned"}
    if args.sam_kind == "sam2":
        source = args.sam or SAM2_ID
        enc, dec = export_sam2(load_sam2(source, random_weights=args.random_weights, tiny=args.tiny),
                               out / "sam2_encoder.onnx", out / "sam2_decoder.onnx", source=source,
                               card_extra=provenance(source, args.random_weights))
    else:
        source = args.sam or SAM_ID
        if s is None:
            _, s = load_models(None, source, random_weights=args.random_weights, tiny=args.tiny, with_gdino=False)
        enc, dec = export_sam(s, out / "sam_encoder.onnx", out / "sam_decoder.onnx", source=source,
                              card_extra=provenance(source, args.random_weights))
    files += [enc, dec]
    config.update({"sam_encoder": enc.path.name, "sam_decoder": dec.path.name})  # relative to the YAML's folder
    if args.boxes == "gdino":
        config["prompt"] = args.prompt
    (out / "grounded_sam.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    print_json({"out": str(out), "config": str(out / "grounded_sam.yaml"), "random_weights": args.random_weights,
                "files": {m.path.name: {k: m.card[k] for k in ("sha256", "bytes", "export_s")}
                          for m in files}})
    return 0


def _write_vocab(path: Path, gdino_source: str, random_weights: bool) -> Path:
    """Write Grounding DINO's vocabulary as ``path`` (vocab.txt): with real weights, the tokenizer shipped with
    them, read from the tokenizer object (``get_vocab()``: a folder with only ``tokenizer.json`` works); with
    random weights, a bert-base-uncased-shaped synthetic one."""
    from torm.segmentation.export import write_tokenizer_vocab, write_vocab

    if random_weights:
        return write_vocab(path)
    from transformers import AutoTokenizer

    from torm.errors import ModelFileError

    try:
        tokenizer = AutoTokenizer.from_pretrained(gdino_source)
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"cannot load the tokenizer of {gdino_source!r} ({exc}); the Grounding DINO folder "
                             "needs its tokenizer files (tokenizer.json or vocab.txt, as save_pretrained writes "
                             "them)") from exc
    return write_tokenizer_vocab(tokenizer, path)
