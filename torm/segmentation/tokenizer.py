"""A BERT WordPiece tokenizer (bert-base-uncased ``vocab.txt``) and Grounding DINO's text inputs.

Tokenisation is Hugging Face's ``tokenizers`` library (``BertWordPieceTokenizer``: BERT's basic tokenisation
-- text cleaning, lower-casing, accent stripping, punctuation and CJK splitting -- then greedy
longest-match-first WordPiece), with ``[CLS] ... [SEP]`` framing. :func:`grounding_text_inputs` adds the
phrase-level self-attention mask and position ids of the official
``generate_masks_with_special_tokens_and_transfer_map`` (GroundingDINO ``bertwarper.py``): tokens attend only
within their phrase, phrases are delimited by ``[CLS]``, ``[SEP]``, ``.`` and ``?``, and position ids restart at 0
after every delimiter.

A prompt is never cut: one whose token count (``[CLS]`` and ``[SEP]`` included) exceeds the export's static token
count, or ``max_text_len``, is a :class:`~torm.errors.ConfigError` stating both numbers. :func:`check_vocabulary`
proves a vocabulary file at load time: its size and sha256 against the model card the export wrote, and the
special-token ids Grounding DINO's weights hard-code (:data:`GROUNDING_SPECIAL_IDS`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError, ModelFileError

_SPECIALS = ("[PAD]", "[UNK]", "[CLS]", "[SEP]")
#: token -> id that Grounding DINO's text encoder (bert-base-uncased) and its phrase masks hard-code: padding, the
#: framing tokens and the phrase delimiter (``generate_masks_with_special_tokens_and_transfer_map``)
GROUNDING_SPECIAL_IDS: dict[str, int] = {"[PAD]": 0, "[CLS]": 101, "[SEP]": 102, ".": 1012}


class WordPieceTokenizer:
    """BERT uncased tokenizer from a ``vocab.txt`` (one token per line, line number = id), on ``tokenizers``."""

    def __init__(self, vocab: dict[str, int], lowercase: bool = True, max_chars_per_word: int = 100) -> None:
        missing = [t for t in _SPECIALS if t not in vocab]
        if missing:
            raise ModelFileError(f"the BERT vocabulary lacks the special token(s) {missing}; use bert-base-uncased "
                                 "vocab.txt")
        from tokenizers import BertWordPieceTokenizer

        self.vocab = vocab
        #: the file the vocabulary was read from (None when built from a dict) and its number of lines (= ids)
        self.path: Path | None = None
        self.n_lines = max(vocab.values()) + 1
        self.inv_vocab = {i: t for t, i in vocab.items()}
        self.lowercase = lowercase
        self.max_chars_per_word = max_chars_per_word
        self._tok = BertWordPieceTokenizer(dict(vocab), lowercase=lowercase, strip_accents=lowercase,
                                           clean_text=True, handle_chinese_chars=True, wordpieces_prefix="##")
        self._tok.post_processor = None  # framing added by encode(), truncation keeps the final [SEP]
        self._tok.no_truncation()

    @classmethod
    def from_file(cls, path: str | Path, lowercase: bool = True) -> WordPieceTokenizer:
        p = Path(path)
        if not p.is_file():
            raise ModelFileError(f"BERT vocabulary {p} does not exist; point bert_vocab at bert-base-uncased's "
                                 "vocab.txt (see torm/segmentation/README.md)")
        tokens = p.read_text(encoding="utf-8").splitlines()
        vocab: dict[str, int] = {}
        for i, t in enumerate(tokens):
            vocab.setdefault(t.rstrip("\n"), i)
        try:
            out = cls(vocab, lowercase=lowercase)
        except ModelFileError as exc:
            raise ModelFileError(f"{p}: {exc}") from exc
        out.path, out.n_lines = p, len(tokens)
        return out

    def token_id(self, token: str) -> int:
        return self.vocab.get(token, self.vocab["[UNK]"])

    def tokenize(self, text: str) -> list[str]:
        """WordPiece tokens of ``text`` without framing."""
        return list(self._tok.encode(text, add_special_tokens=False).tokens)

    def encode(self, text: str, max_length: int | None = None) -> list[int]:
        """``[CLS] tokens [SEP]`` ids, truncated to ``max_length`` (keeping the final ``[SEP]``)."""
        ids = list(self._tok.encode(text, add_special_tokens=False).ids)
        if max_length is not None and len(ids) + 2 > max_length:
            ids = ids[: max(max_length - 2, 0)]
        return [self.vocab["[CLS]"], *ids, self.vocab["[SEP]"]]

    def decode(self, ids: list[int] | np.ndarray) -> str:
        """Join token ids into text: ``##`` pieces glue to the previous token, others are space separated."""
        out = ""
        for i in ids:
            tok = self.inv_vocab.get(int(i), "[UNK]")
            if tok.startswith("##"):
                out += tok[2:]
            else:
                out += (" " if out else "") + tok
        return out


def vocab_sha256(path: str | Path) -> str:
    """sha256 (hex) of a vocabulary file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_vocabulary(tokenizer: WordPieceTokenizer, card: Mapping[str, Any] | None = None,
                     expected_ids: Mapping[str, int] = GROUNDING_SPECIAL_IDS) -> None:
    """Prove that ``tokenizer``'s vocabulary is the one the model was exported with.

    ``card``: the Grounding DINO export's model card (``vocab_size`` lines, ``vocab_sha256``); None or a card
    without them (an ONNX file exported elsewhere) skips that part. ``expected_ids``: token -> id the weights
    hard-code. Raises :class:`ModelFileError` naming the file, what differs and the fix.
    """
    where = tokenizer.path or "the BERT vocabulary"
    if card and card.get("vocab_size") is not None and tokenizer.n_lines != int(card["vocab_size"]):
        raise ModelFileError(f"{where} has {tokenizer.n_lines} lines but the Grounding DINO export was made with a "
                             f"{card['vocab_size']}-line vocabulary (its card); a dropped or added line shifts every "
                             "id: use the vocab.txt `torm export-models` wrote beside the model")
    if card and card.get("vocab_sha256") and tokenizer.path is not None:
        digest = vocab_sha256(tokenizer.path)
        if digest != card["vocab_sha256"]:
            raise ModelFileError(f"{where} has sha256 {digest[:12]}... but the Grounding DINO export was made with "
                                 f"{card['vocab_sha256'][:12]}... (its card): another vocabulary; use the vocab.txt "
                                 "`torm export-models` wrote beside the model")
    wrong = {t: tokenizer.vocab.get(t) for t, i in expected_ids.items() if tokenizer.vocab.get(t) != i}
    if wrong:
        got = ", ".join(f"{t!r} is {'missing' if i is None else f'id {i}'} (expected {expected_ids[t]})"
                        for t, i in wrong.items())
        raise ModelFileError(f"{where}: {got}; Grounding DINO's weights hard-code these ids: use bert-base-uncased's "
                             "vocab.txt (30522 lines), e.g. the one `torm export-models` writes")


@dataclass(frozen=True, eq=False)
class TextInputs:
    """Grounding DINO text inputs for one caption, all with a leading batch dimension of 1.

    ``input_ids``, ``attention_mask`` (1 = real token), ``token_type_ids``, ``position_ids``: (1, T) int64;
    ``self_attention_mask``: (1, T, T) bool, the phrase-block mask (``text_token_mask`` of the export).
    """

    caption: str
    input_ids: np.ndarray
    attention_mask: np.ndarray
    token_type_ids: np.ndarray
    position_ids: np.ndarray
    self_attention_mask: np.ndarray

    @property
    def length(self) -> int:
        return int(self.input_ids.shape[1])

    @property
    def n_real(self) -> int:
        return int(self.attention_mask.sum())


def normalize_caption(prompt: str) -> str:
    """Grounding DINO's caption convention: lower case, stripped, ending with ``.``."""
    cap = prompt.strip().lower()
    return cap if cap.endswith(".") else cap + "."


def grounding_text_inputs(
    tokenizer: WordPieceTokenizer, prompt: str, max_text_len: int = 256, pad_to: int | None = None
) -> TextInputs:
    """Tokenise ``prompt`` (phrases separated by ``.``) into Grounding DINO inputs.

    ``pad_to`` pads with ``[PAD]`` to a fixed length (for exports with a static sequence length);
    otherwise the length is the token count (``padding="longest"`` for one caption).

    Raises:
        ConfigError: the caption has more tokens (``[CLS]``/``[SEP]`` included) than ``pad_to`` or
            ``max_text_len``; it is never cut, the message states the count and the maximum.
    """
    caption = normalize_caption(prompt)
    limit = min(max_text_len, pad_to) if pad_to else max_text_len
    ids = tokenizer.encode(caption)
    n = len(ids)
    if n > limit:
        fix = (f"shorten it or re-export with `torm export-models --max-tokens {n}` (or more)"
               if pad_to and pad_to <= max_text_len else f"shorten it or raise grounded_sam.max_text_len to {n}")
        which = "the Grounding DINO export's static token count" if pad_to and pad_to <= max_text_len \
            else "max_text_len"
        raise ConfigError(f"prompt {caption!r} has {n} tokens ([CLS] and [SEP] included) but {which} is {limit}; "
                          f"it is not cut: {fix}")
    T = pad_to if pad_to else n
    input_ids = np.full((1, T), tokenizer.vocab["[PAD]"], dtype=np.int64)
    input_ids[0, :n] = ids
    attention = np.zeros((1, T), dtype=np.int64)
    attention[0, :n] = 1
    special = {tokenizer.vocab[t] for t in ("[CLS]", "[SEP]") } | {
        tokenizer.vocab[t] for t in (".", "?") if t in tokenizer.vocab}
    mask = np.eye(T, dtype=bool)[None]
    pos = np.zeros((1, T), dtype=np.int64)
    prev = 0
    for col in [c for c in range(T) if int(input_ids[0, c]) in special]:
        if col == 0 or col == T - 1:
            mask[0, col, col] = True
            pos[0, col] = 0
        else:
            mask[0, prev + 1: col + 1, prev + 1: col + 1] = True
            pos[0, prev + 1: col + 1] = np.arange(0, col - prev)
        prev = col
    return TextInputs(caption, input_ids, attention, np.zeros((1, T), np.int64), pos, mask)
