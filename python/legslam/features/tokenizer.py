"""CLIP's byte-level BPE tokenizer (OpenAI `clip.simple_tokenizer`) in plain Python.

Same cleaning except ftfy (html unescape, whitespace collapse, lowercase), the same pre-split
pattern, byte encoder and merges, <|startoftext|> = 49406, <|endoftext|> = 49407, context
length 77, zero padded. The pre-split regex needs Unicode letter/number classes (\\p{L}, \\p{N})
that Python's `re` lacks, so `_pre_split` scans with `unicodedata` categories instead, trying
the pattern's alternatives in its order at each position (which is what the regex does).
Checked against the `regex` package on every assigned code point: the same split except for
U+0345 (a combining mark that regex's IGNORECASE case-folding counts as a letter), and for
code points newer than Python's Unicode database.
"""

from __future__ import annotations

import functools
import gzip
import html
import re
import unicodedata
from pathlib import Path

import numpy as np

VOCAB_PATH = Path(__file__).parent / "data" / "bpe_simple_vocab_16e6.txt.gz"
SOT, EOT = "<|startoftext|>", "<|endoftext|>"
SOT_ID, EOT_ID = 49406, 49407
CONTEXT_LENGTH = 77
_CONTRACTIONS = ("'s", "'t", "'re", "'ve", "'m", "'ll", "'d")  # the regex's order
# str.isspace() also counts these separators; the regex's \s (Unicode White_Space) does not.
_NOT_WHITE_SPACE = "\x1c\x1d\x1e\x1f"


def _bytes_to_unicode() -> dict[int, str]:
    """CLIP/GPT-2's reversible map of bytes to printable unicode characters."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, map(chr, cs)))


def _char_class(c: str) -> str:
    """'L' letter, 'N' number, 'S' whitespace, 'O' other: the pattern's \\p{L}, \\p{N}, \\s."""
    if c.isspace() and c not in _NOT_WHITE_SPACE:
        return "S"
    cat = unicodedata.category(c)[0]
    return cat if cat in "LN" else "O"


def _pre_split(text: str) -> list[str]:
    """Equivalent of re.findall on CLIP's pattern
    <|startoftext|>|<|endoftext|>|'s|'t|'re|'ve|'m|'ll|'d|[\\p{L}]+|[\\p{N}]|[^\\s\\p{L}\\p{N}]+
    for lower-cased text."""
    out, i, n = [], 0, len(text)
    while i < n:
        rest = text[i:]
        lit = next((t for t in (SOT, EOT) + _CONTRACTIONS if rest.startswith(t)), None)
        if lit is not None:
            out.append(lit)
            i += len(lit)
            continue
        cls = _char_class(text[i])
        if cls == "S":
            i += 1
            continue
        j = i + 1
        if cls != "N":  # letters and "other" run on; a number is one character
            while j < n and _char_class(text[j]) == cls:
                j += 1
        out.append(text[i:j])
        i = j
    return out


class Tokenizer:
    def __init__(self, vocab_path: Path = VOCAB_PATH):
        with gzip.open(vocab_path, "rt", encoding="utf-8") as f:
            lines = f.read().split("\n")
        merges = [tuple(m.split()) for m in lines[1 : 49152 - 256 - 2 + 1]]
        self.byte_encoder = _bytes_to_unicode()
        vocab = list(self.byte_encoder.values())
        vocab += [v + "</w>" for v in vocab]
        vocab += ["".join(m) for m in merges]
        vocab += [SOT, EOT]
        self.encoder = {v: i for i, v in enumerate(vocab)}
        self.decoder = dict(enumerate(vocab))
        self.bpe_ranks = {m: i for i, m in enumerate(merges)}
        self.cache = {SOT: SOT, EOT: EOT}
        self._byte_decoder = {c: b for b, c in self.byte_encoder.items()}

    def bpe(self, token: str) -> str:
        if token in self.cache:
            return self.cache[token]
        word = tuple(token[:-1]) + (token[-1] + "</w>",)
        while len(word) > 1:
            pairs = set(zip(word, word[1:]))
            best = min(pairs, key=lambda p: self.bpe_ranks.get(p, float("inf")))
            if best not in self.bpe_ranks:
                break
            first, second = best
            merged, i = [], 0
            while i < len(word):
                if i < len(word) - 1 and word[i] == first and word[i + 1] == second:
                    merged.append(first + second)
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = tuple(merged)
        result = " ".join(word)
        self.cache[token] = result
        return result

    def encode(self, text: str) -> list[int]:
        """Text -> BPE ids, without <|startoftext|>/<|endoftext|>."""
        text = html.unescape(html.unescape(text)).strip()
        text = re.sub(r"\s+", " ", text).strip().lower()
        ids = []
        for token in _pre_split(text):
            token = "".join(self.byte_encoder[b] for b in token.encode("utf-8"))
            ids.extend(self.encoder[t] for t in self.bpe(token).split(" "))
        return ids

    def decode(self, ids) -> str:
        text = "".join(self.decoder[int(i)] for i in ids)
        raw = bytearray(self._byte_decoder[c] for c in text)
        return raw.decode("utf-8", errors="replace").replace("</w>", " ")

    def __call__(self, texts, context_length: int = CONTEXT_LENGTH, truncate: bool = False) -> np.ndarray:
        """A string or list of strings -> int64 [N, context_length]: SOT, ids, EOT, zeros.

        Too long a text is a ValueError, or with truncate=True is cut and ends in EOT."""
        if isinstance(texts, str):
            texts = [texts]
        out = np.zeros((len(texts), context_length), dtype=np.int64)
        for row, text in zip(out, texts):
            ids = [SOT_ID, *self.encode(text), EOT_ID]
            if len(ids) > context_length:
                if not truncate:
                    raise ValueError(
                        f"text is {len(ids)} tokens, longer than the context length {context_length}: {text!r}"
                    )
                ids = ids[: context_length - 1] + [EOT_ID]
            row[: len(ids)] = ids
        return out


@functools.lru_cache(maxsize=1)
def default_tokenizer() -> Tokenizer:
    return Tokenizer()


def tokenize(texts, context_length: int = CONTEXT_LENGTH, truncate: bool = False) -> np.ndarray:
    """`clip.tokenize` equivalent with the shipped vocabulary: int64 [N, context_length]."""
    return default_tokenizer()(texts, context_length, truncate)
