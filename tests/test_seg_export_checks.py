"""Bring your own weights safely (issue 60): the export refuses the wrong checkpoint and a partly initialised one,
reads the vocabulary from the tokenizer object, records provenance in the cards and writes paths relative to its
YAML; at load time the vocabulary is proven against the card and a prompt that does not fit is refused.

Tiny configs of the published ``transformers`` classes with random weights, saved with ``save_pretrained`` as a
user's local checkpoint folders are."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import yaml

pytest.importorskip("transformers")

from torm.cli import main  # noqa: E402
from torm.errors import ConfigError, ModelFileError  # noqa: E402
from torm.segmentation import resolve_config_paths  # noqa: E402
from torm.segmentation.export import load_models, load_sam2, write_vocab  # noqa: E402
from torm.segmentation.grounded_sam import GroundedSAMConfig, GroundedSAMSegmenter  # noqa: E402


def _tokenizer_folder(folder: Path) -> Path:
    """A transformers-5-style tokenizer saved by ``save_pretrained`` (no vocab.txt kept in the folder)."""
    from transformers import BertTokenizer

    vocab = write_vocab(folder.parent / f"{folder.name}_source_vocab.txt")
    ids = {t: i for i, t in enumerate(vocab.read_text().splitlines())}
    BertTokenizer(vocab=ids).save_pretrained(str(folder))
    (folder / "vocab.txt").unlink(missing_ok=True)
    return vocab


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Local checkpoint folders: Grounding DINO (+ its tokenizer), SAM and SAM 2, all complete."""
    root = tmp_path_factory.mktemp("ckpt")
    g, s = load_models(random_weights=True, tiny=True)
    g.save_pretrained(str(root / "gdino"))
    vocab = _tokenizer_folder(root / "gdino")
    s.save_pretrained(str(root / "sam"))
    load_sam2(random_weights=True, tiny=True).save_pretrained(str(root / "sam2"))
    return root, vocab


@pytest.fixture(scope="module")
def exported_real(checkpoints, tmp_path_factory):
    root, _ = checkpoints
    out = tmp_path_factory.mktemp("gsam_real")
    assert main(["-q", "export-models", "--out", str(out), "--gdino", str(root / "gdino"), "--sam", str(root / "sam"),
                 "--image-hw", "128", "160"]) == 0
    return out


def _config(out: Path) -> dict:
    path = out / "grounded_sam.yaml"
    return resolve_config_paths("grounded_sam", yaml.safe_load(path.read_text()), path)


def test_a_folder_without_vocab_txt_exports_with_cards_that_prove_it(checkpoints, exported_real):
    root, source_vocab = checkpoints
    assert not (root / "gdino" / "vocab.txt").exists()
    # the vocabulary was read from the tokenizer object, id by id
    assert (exported_real / "vocab.txt").read_text() == source_vocab.read_text()
    card = json.loads((exported_real / "grounding_dino.onnx.json").read_text())
    assert card["random_weights"] is False and card["source"] == str(root / "gdino")
    files = card["source_files_sha256"]
    assert "model.safetensors" in files and "tokenizer.json" in files and all(len(h) == 64 for h in files.values())
    import hashlib

    assert card["vocab_sha256"] == hashlib.sha256((exported_real / "vocab.txt").read_bytes()).hexdigest()
    assert card["vocab_size"] == 30522
    sam = json.loads((exported_real / "sam_encoder.onnx.json").read_text())
    assert sam["random_weights"] is False and "model.safetensors" in sam["source_files_sha256"]


def test_the_config_is_relative_to_its_folder_and_loads_from_anywhere(exported_real, tmp_path, monkeypatch):
    raw = yaml.safe_load((exported_real / "grounded_sam.yaml").read_text())
    assert {raw[k] for k in ("gdino_model", "bert_vocab", "sam_encoder", "sam_decoder")} == {
        "grounding_dino.onnx", "vocab.txt", "sam_encoder.onnx", "sam_decoder.onnx"}
    monkeypatch.chdir(tmp_path)  # another working directory
    from torm.commands.segment import load_segmenter_config

    cfg = load_segmenter_config("grounded_sam", os.path.relpath(exported_real / "grounded_sam.yaml"), [])
    assert Path(cfg.gdino_model) == exported_real.resolve() / "grounding_dino.onnx"
    seg = GroundedSAMSegmenter(cfg)
    assert seg.gdino_card["vocab_size"] == 30522


def test_a_sam2_checkpoint_exported_as_sam_is_refused(checkpoints, tmp_path):
    root, _ = checkpoints
    with pytest.raises(ModelFileError, match=r"holds a 'sam2' checkpoint, not SAM \('sam'\).*--sam-kind sam2"):
        load_models(None, str(root / "sam2"), with_gdino=False)
    assert main(["-q", "export-models", "--out", str(tmp_path / "o"), "--boxes", "learned",
                 "--sam", str(root / "sam2")]) != 0
    assert not (tmp_path / "o" / "sam_encoder.onnx").exists()
    with pytest.raises(ModelFileError, match=r"holds a 'sam' checkpoint, not SAM 2.*--sam-kind sam"):
        load_sam2(str(root / "sam"))


def test_a_checkpoint_with_a_missing_tensor_is_refused_naming_it(checkpoints, tmp_path):
    import shutil

    from safetensors.torch import load_file, save_file

    root, _ = checkpoints
    bad = tmp_path / "sam_partial"
    shutil.copytree(root / "sam", bad)
    tensors = load_file(str(bad / "model.safetensors"))
    dropped = sorted(k for k in tensors if "mask_decoder" in k)[0]
    del tensors[dropped]
    save_file(tensors, str(bad / "model.safetensors"), metadata={"format": "pt"})
    with pytest.raises(ModelFileError, match=r"1 SAM weight\(s\) are not in the checkpoint.*" + dropped.split(".")[-2]):
        load_models(None, str(bad), with_gdino=False)


def test_a_vocabulary_with_a_dropped_line_is_refused(exported_real, tmp_path):
    cfg = _config(exported_real)
    lines = Path(cfg["bert_vocab"]).read_text().splitlines()
    short = tmp_path / "vocab.txt"
    short.write_text("\n".join(lines[:500] + lines[501:]) + "\n")
    with pytest.raises(ModelFileError, match=r"has 30521 lines but .* 30522-line vocabulary"):
        GroundedSAMSegmenter(GroundedSAMConfig(**{**cfg, "bert_vocab": str(short)}))
    swapped = tmp_path / "swapped.txt"  # same size, another vocabulary: the hash tells
    swapped.write_text("\n".join(lines[:2000] + [lines[2001], lines[2000]] + lines[2002:]) + "\n")
    with pytest.raises(ModelFileError, match=r"sha256 .* another vocabulary"):
        GroundedSAMSegmenter(GroundedSAMConfig(**{**cfg, "bert_vocab": str(swapped)}))


def test_special_token_ids_are_checked(tmp_path):
    from torm.segmentation.tokenizer import WordPieceTokenizer, check_vocabulary

    lines = write_vocab(tmp_path / "v.txt").read_text().splitlines()
    lines[101], lines[102] = lines[102], lines[101]  # [CLS] and [SEP] swapped
    (tmp_path / "w.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ModelFileError, match=r"'\[CLS\]' is id 102 \(expected 101\).*hard-code"):
        check_vocabulary(WordPieceTokenizer.from_file(tmp_path / "w.txt"))


def test_a_prompt_longer_than_the_export_is_refused_with_its_count(exported_real):
    cfg = _config(exported_real)
    long = "a transparent glass. a clear plastic bottle. a beaker. " * 3
    with pytest.raises(ConfigError, match=r"has 38 tokens \(\[CLS\] and \[SEP\] included\) but the Grounding DINO "
                                          r"export's static token count is 32; it is not cut.*--max-tokens 38"):
        GroundedSAMSegmenter(GroundedSAMConfig(**{**cfg, "prompt": long}))
    # the prompt fits the default maximum and keeps every token
    seg = GroundedSAMSegmenter(GroundedSAMConfig(**{**cfg, "prompt": "a transparent glass. a clear plastic bottle. "
                                                                     "a beaker."}))
    assert seg.text.n_real == 14 and seg.text.length == 32
    assert seg.tokenizer.decode(seg.text.input_ids[0, :14]).endswith("beaker . [SEP]")


def test_a_static_size_export_letterboxes_instead_of_stretching():
    """A 4:3 and a 16:9 image into an 800 x 1333 export keep their aspect; boxes map back to image pixels."""
    import numpy as np

    from torm.segmentation.grounded_sam import gdino_letterbox, letterbox_hw

    for h, w in ((480, 640), (720, 1280), (1280, 720)):
        (rh, rw), s = letterbox_hw(h, w, (800, 1333))
        assert rh <= 800 and rw <= 1333 and (rh == 800 or rw == 1333)
        assert abs(rw / rh - w / h) < 0.01 * (w / h)  # the aspect is kept (4:3 is not stretched by 25 %)
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[:, :320] = 255  # the left half white
    x, (cw, ch) = gdino_letterbox(rgb, (800, 1333))
    assert x.shape == (1, 3, 800, 1333)
    assert np.all(x[0, :, :, 1067:] == 0)  # padding at the right: the mean, 0 after normalisation
    assert abs(cw / ch - 1333 / 800) < 1e-6 and abs(ch - 480) < 1e-6  # canvas in image pixels
    # a box normalised to the canvas around the white half maps back to the image's left half
    from torm.segmentation.boxes import cxcywh_to_xyxy as conv

    box = np.array([[160 / cw, 240 / ch, 320 / cw, 480 / ch]])
    np.testing.assert_allclose(conv(box, cw, ch)[0], [0, 0, 320, 480], atol=1e-6)
