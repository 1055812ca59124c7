"""A BERT WordPiece tokenizer (bert-base-uncased ``vocab.txt``) and Grounding DINO's text inputs.

Tokenisation is Hugging Face's ``tokenizers`` library (``BertWordPieceTokenizer``: BERT's basic tokenisation
-- text cleaning, lower-casing, accent stripping, punctuation and CJK splitting -- then greedy
longest-match-first WordPiece), with ``[CLS] ... [SEP]`` framing. :func:`grounding_text_inputs` adds the
phrase-level self-attention mask and position ids of the official
``generate_masks_with_special_tokens_and_transfer_map`` (GroundingDINO ``bertwarper.py``): tokens attend only
within their phrase, phrases are delimited by ``[CLS]``, ``[SEP]``, ``.`` and ``?``, and position ids restart at 0
after every delimiter.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torm.errors import ModelFileError

_SPECIALS = ("[PAD]", "[UNK]", "[CLS]", "[SEP]")


class WordPieceTokenizer:
    """BERT uncased tokenizer from a ``vocab.txt`` (one token per line, line number = id), on ``tokenizers``."""

    def __init__(self, vocab: dict[str, int], lowercase: bool = True, max_chars_per_word: int = 100) -> None:
        missing = [t for t in _SPECIALS if t not in vocab]
        if missing:
            raise ModelFileError(f"the BERT vocabulary lacks the special token(s) {missing}; use bert-base-uncased "
                                 "vocab.txt")
        from tokenizers import BertWordPieceTokenizer

        self.vocab = vocab
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
            return cls(vocab, lowercase=lowercase)
        except ModelFileError as exc:
            raise ModelFileError(f"{p}: {exc}") from exc

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
    otherwise the length is the token count (``padding="longest"`` for one caption), capped at
    ``max_text_len``.
    """
    caption = normalize_caption(prompt)
    limit = min(max_text_len, pad_to) if pad_to else max_text_len
    ids = tokenizer.encode(caption, max_length=limit)
    n = len(ids)
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
