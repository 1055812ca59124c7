"""WordPiece tokenizer and Grounding DINO text inputs on a tiny vocabulary."""

from __future__ import annotations

import numpy as np
import pytest

from torm.errors import ConfigError, ModelFileError
from torm.segmentation.boxes import box_iou, cxcywh_to_xyxy, nms
from torm.segmentation.tokenizer import WordPieceTokenizer, grounding_text_inputs, normalize_caption

VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "?", ",", "clear", "glass", "trans", "##par", "##ent", "object",
         "##s", "cafe", "a", "##b", "ab"]


@pytest.fixture()
def tok(tmp_path):
    p = tmp_path / "vocab.txt"
    p.write_text("\n".join(VOCAB) + "\n")
    return WordPieceTokenizer.from_file(p)


def test_basic_and_wordpiece_tokenisation(tok):
    assert tok.tokenize("  Clear,GLASS.\tCafé?") == ["clear", ",", "glass", ".", "cafe", "?"]
    assert tok.tokenize("Transparent objects") == ["trans", "##par", "##ent", "object", "##s"]
    assert tok.tokenize("abb") == ["ab", "##b"]  # longest match first: "ab" then "##b"
    assert tok.tokenize("glassy") == ["[UNK]"]  # "##y" is not in the vocabulary
    assert tok.tokenize("x" * 101) == ["[UNK]"]
    assert tok.encode("clear glass") == [2, 7, 8, 3]
    assert tok.decode([9, 10, 11, 12, 13]) == "transparent objects"


def test_grounding_inputs_match_the_official_phrase_masks(tok):
    t = grounding_text_inputs(tok, "Clear glass. transparent object")
    assert t.caption == "clear glass. transparent object."
    # [CLS] clear glass . trans ##par ##ent object . [SEP]
    np.testing.assert_array_equal(t.input_ids[0], [2, 7, 8, 4, 9, 10, 11, 12, 4, 3])
    np.testing.assert_array_equal(t.position_ids[0], [0, 0, 1, 2, 0, 1, 2, 3, 4, 0])
    np.testing.assert_array_equal(t.attention_mask[0], np.ones(10))
    np.testing.assert_array_equal(t.token_type_ids[0], np.zeros(10))
    m = t.self_attention_mask[0]
    expected = np.eye(10, dtype=bool)
    expected[1:4, 1:4] = True
    expected[4:9, 4:9] = True
    np.testing.assert_array_equal(m, expected)


def test_padding_and_refusing_long_prompts(tok):
    t = grounding_text_inputs(tok, "clear glass.", pad_to=8)
    np.testing.assert_array_equal(t.input_ids[0], [2, 7, 8, 4, 3, 0, 0, 0])
    np.testing.assert_array_equal(t.attention_mask[0], [1, 1, 1, 1, 1, 0, 0, 0])
    assert t.n_real == 5 and t.length == 8
    np.testing.assert_array_equal(t.self_attention_mask[0, 5:], np.eye(8, dtype=bool)[5:])  # pads see themselves
    # a prompt that does not fit is refused with its token count, never cut (issue 60)
    with pytest.raises(ConfigError, match=r"has 10 tokens .* max_text_len is 5; it is not cut"):
        grounding_text_inputs(tok, "clear glass. transparent object.", max_text_len=5)
    with pytest.raises(ConfigError, match=r"has 10 tokens .* static token count is 8.*--max-tokens 10"):
        grounding_text_inputs(tok, "clear glass. transparent object.", pad_to=8)
    assert normalize_caption("  A cup ") == "a cup."


def test_bad_vocab_files(tmp_path):
    with pytest.raises(ModelFileError, match="missing.txt"):
        WordPieceTokenizer.from_file(tmp_path / "missing.txt")
    p = tmp_path / "v.txt"
    p.write_text("a\nb\n")
    with pytest.raises(ModelFileError, match=r"v\.txt.*\[PAD\]"):
        WordPieceTokenizer.from_file(p)


def test_box_helpers_and_nms():
    b = cxcywh_to_xyxy(np.array([[0.5, 0.5, 0.5, 0.5], [0.0, 0.0, 0.4, 0.4]]), 200, 100)
    np.testing.assert_allclose(b, [[50, 25, 150, 75], [0, 0, 40, 20]])  # the second one clipped at 0
    assert box_iou(b[:1], b[:1])[0, 0] == pytest.approx(1.0)
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 20, 30, 30], [0, 0, 10, 5]], float)
    scores = np.array([0.6, 0.9, 0.5, 0.8])
    # box 0 overlaps box 1 (IoU 0.82) -> removed; box 3 has IoU 0.45 with box 1 -> kept
    np.testing.assert_array_equal(nms(boxes, scores, 0.5), [1, 3, 2])
    np.testing.assert_array_equal(nms(boxes, scores, 0.4), [1, 2])


def _full_vocab(path):
    """A 30522-entry WordPiece vocabulary laid out like bert-base-uncased's ([PAD] 0, [UNK] 100, [CLS] 101,
    [SEP] 102, "." 1012, "?" 1029: ids Grounding DINO hard-codes), with real words, pieces and filler."""
    words = ["clear", "glass", "transparent", "object", "cup", "bottle", "the", "a", "of", "wine", "beaker",
             "trans", "par", "ent", "test", "tube", "flask", "petri", "dish", "shiny", "cafe", "plastic"]
    pieces = ["##s", "##par", "##ent", "##y", "##er", "##ed", "##ing", "##ly", "##e", "##a", "##t"]
    vocab = [f"[unused{i}]" for i in range(30522)]
    vocab[0], vocab[100], vocab[101], vocab[102], vocab[103] = "[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"
    vocab[1012], vocab[1029], vocab[1010] = ".", "?", ","
    entries = [*words, *pieces, *"abcdefghijklmnopqrstuvwxyz", *[f"##{c}" for c in "abcdefghijklmnop"]]
    for i, w in enumerate(dict.fromkeys(entries)):  # each token once, as in a real vocabulary
        vocab[2000 + i] = w
    path.write_text("\n".join(vocab) + "\n")
    return path


def test_matches_transformers_bert_tokenizer_on_a_full_size_vocabulary(tmp_path):
    pytest.importorskip("transformers")  # the dev extra installs it
    from transformers.models.bert import BertTokenizerLegacy  # the pure-Python BERT tokenizer: an independent one

    path = _full_vocab(tmp_path / "vocab.txt")
    ours = WordPieceTokenizer.from_file(path)
    ref = BertTokenizerLegacy(vocab_file=str(path), do_lower_case=True)
    prompts = ["clear glass. transparent object.", "Wine Glass? test tubes, petri dish.", "Café  PLASTIC bottles",
               "shiny beakers and flasks", "xyzzy glassware", "a" * 120, "clear\tglass\n. cup?"]
    for p in prompts:
        assert ours.tokenize(p) == ref.tokenize(p), p
        assert ours.encode(p) == ref.encode(p), p
