"""The CLIP BPE tokenizer against token ids published for OpenAI's / open_clip's tokenizer."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from legslam.features import tokenize
from legslam.features.tokenizer import VOCAB_PATH, _pre_split, default_tokenizer

KNOWN = [
    # OpenAI CLIP README / clip.tokenize examples
    ("a photo of a cat.", [49406, 320, 1125, 539, 320, 2368, 269, 49407]),
    ("a diagram", [49406, 320, 22697, 49407]),
    ("a dog", [49406, 320, 1929, 49407]),
    ("a cat", [49406, 320, 2368, 49407]),
    # published by other CLIP tokenizer ports' tests (HF/open_clip reference ids)
    ("Hello, world!", [49406, 3306, 267, 1002, 256, 49407]),
    ("A PHOTO of  a Cat!", [49406, 320, 1125, 539, 320, 2368, 256, 49407]),
    ("don't stop 42 times", [49406, 847, 713, 1691, 275, 273, 1661, 49407]),
    ("cafe uber naive", [49406, 4979, 10668, 43362, 49407]),
    ("hello-world, 3.14 (test)", [49406, 3306, 268, 1002, 267, 274, 269, 272, 275, 263, 1628, 264, 49407]),
    ("caf\u00e9 \u00fcber na\u00efve", [49406, 15304, 6522, 1516, 1097, 35689, 563, 49407]),
    ("  spaced   out  ", [49406, 10336, 538, 620, 49407]),
    ("a dog in the snow", [49406, 320, 1929, 530, 518, 2583, 49407]),
    ("", [49406, 49407]),
]


def test_shipped_vocabulary_is_openais_file():
    assert hashlib.sha256(VOCAB_PATH.read_bytes()).hexdigest() == (
        "924691ac288e54409236115652ad4aa250f48203de50a9e4722a6ecd48d6804a"
    )


@pytest.mark.parametrize("text,ids", KNOWN)
def test_known_token_ids(text, ids):
    row = tokenize(text)[0]
    assert row.tolist() == ids + [0] * (77 - len(ids))


def test_batch_shape_dtype_and_decode():
    out = tokenize(["a photo of a cat.", "a dog"])
    assert out.shape == (2, 77) and out.dtype == np.int64
    assert default_tokenizer().decode(default_tokenizer().encode("a photo of a cat.")).strip() == "a photo of a cat ."


def test_too_long_raises_or_truncates_ending_in_eot():
    text = " ".join(["cat"] * 100)
    with pytest.raises(ValueError, match="context length"):
        tokenize(text)
    row = tokenize(text, truncate=True)[0]
    assert row[0] == 49406 and row[-1] == 49407 and (row[1:-1] == 2368).all()


def test_pre_split_follows_the_clip_pattern():
    # letters run on, a number is one character each (including non-ASCII numbers), other
    # symbols run on, contractions and the special tokens split off.
    assert _pre_split("it's 42½ x²!?") == ["it", "'s", "4", "2", "½", "x", "²", "!?"]
    assert _pre_split("naïve<|endoftext|>") == ["naïve", "<|endoftext|>"]
    assert _pre_split("!'s") == ["!'", "s"]
    assert _pre_split("a\x1cb") == ["a", "\x1c", "b"]  # not White_Space, unlike str.isspace()
