"""``torm export-models``: Grounding DINO and SAM to the ONNX files ``torm segment --segmenter grounded_sam`` loads.

Loads the models with ``transformers`` (``pip install 'torm[models]'``) from local folders or the Hugging Face
cache (a machine with internet downloads IDEA-Research/grounding-dino-tiny and facebook/sam-vit-base once), exports
them (:mod:`torm.segmentation.export`) and writes a segmenter config that points at the files, plus a model card
per file (source, licence, sha256, opset, shapes).

Examples::

    torm export-models --out models/gsam                                   # the published weights
    torm export-models --out models/gsam --gdino ./gdino-tiny --sam ./sam-vit-base
    torm export-models --out /tmp/gsam --random-weights                    # the real architectures, random weights
    torm export-models --out models/sam2 --sam-kind sam2 --boxes learned   # SAM 2.1 Hiera-Tiny for CPUs, no DINO
    torm segment my_capture --segmenter grounded_sam --config models/gsam/grounded_sam.yaml

Grounding DINO is exported at a static image size (``--image-hw``, default 800 1333: the official resize of a
16:9 image) and a static token count (the prompt's, padded by torm); SAM at 1024 px. ``--sam-kind sam2`` exports
SAM 2.1 Hiera-Tiny (facebook/sam2.1-hiera-tiny, Apache-2.0; the small SAM-family model: transformers has no
MobileSAM or EfficientSAM class) instead of SAM ViT-B; ``--boxes learned`` skips Grounding DINO and writes a config
in which torm's learned segmenter prompts SAM with its boxes (hybrid prompting).
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
    p.add_argument("--prompt", default="clear glass. transparent object.", help="the prompt the token count is for")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import yaml

    from torm.segmentation.export import (
        GDINO_ID,
        SAM2_ID,
        SAM_ID,
        export_grounding_dino,
        export_sam,
        export_sam2,
        load_models,
        load_sam2,
        write_vocab,
    )
    from torm.segmentation.tokenizer import WordPieceTokenizer, grounding_text_inputs

    out = check_output_dir(args.out)
    files = []
    config: dict = {}
    if args.boxes == "gdino":
        g, s = load_models(args.gdino or GDINO_ID, args.sam or SAM_ID, random_weights=args.random_weights,
                           tiny=args.tiny, with_sam=args.sam_kind == "sam")
        if args.random_weights:
            vocab = write_vocab(out / "vocab.txt")
        else:  # the tokenizer shipped with the Grounding DINO weights
            from transformers import AutoTokenizer

            vocab = Path(AutoTokenizer.from_pretrained(args.gdino or GDINO_ID).save_vocabulary(str(out))[0])
        n_tokens = grounding_text_inputs(WordPieceTokenizer.from_file(vocab), args.prompt).length
        gd = export_grounding_dino(g, out / "grounding_dino.onnx", tuple(args.image_hw), n_tokens,
                                   source=args.gdino or GDINO_ID)
        files.append(gd)
        config = {"gdino_model": str(gd.path), "bert_vocab": str(vocab)}
    else:
        s = None
        config = {"box_source": "learned"}
    if args.sam_kind == "sam2":
        source = args.sam or SAM2_ID
        enc, dec = export_sam2(load_sam2(source, random_weights=args.random_weights, tiny=args.tiny),
                               out / "sam2_encoder.onnx", out / "sam2_decoder.onnx", source=source)
    else:
        if s is None:
            _, s = load_models(None, args.sam or SAM_ID, random_weights=args.random_weights, tiny=args.tiny,
                               with_gdino=False)
        enc, dec = export_sam(s, out / "sam_encoder.onnx", out / "sam_decoder.onnx", source=args.sam or SAM_ID)
    files += [enc, dec]
    config.update({"sam_encoder": str(enc.path), "sam_decoder": str(dec.path)})
    if args.boxes == "gdino":
        config["prompt"] = args.prompt
    (out / "grounded_sam.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    print_json({"out": str(out), "config": str(out / "grounded_sam.yaml"), "random_weights": args.random_weights,
                "files": {m.path.name: {k: m.card[k] for k in ("sha256", "bytes", "export_s")}
                          for m in files}})
    return 0
