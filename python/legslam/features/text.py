"""Text side of the queries: the CLIP text tower (ONNX) and the Talk2DINO projection.

Text-tower ONNX contract (what `legslam export-models` writes): input `input_ids` int64 [B,77]
(CLIP token ids, `tokenize`), output `text_embeds` float32 [B,512], the RAW (not normalised)
CLIP text feature read at the <|endoftext|> position, as `encode_text` returns it. Talk2DINO
was trained on raw features, so they must not be normalised before the projection.
"""

from __future__ import annotations

import numpy as np

from legslam import models
from legslam.features.encoder import session
from legslam.features.tokenizer import CONTEXT_LENGTH, tokenize

TEXT_INPUT = "input_ids"
TEXT_OUTPUT = "text_embeds"

# A short prompt ensemble (a subset of CLIP's 80 ImageNet templates, as used for
# open-vocabulary segmentation); embeddings are averaged over it after projection.
TEMPLATES = (
    "a photo of a {}.",
    "a photo of the {}.",
    "a photo of a small {}.",
    "a photo of a large {}.",
    "a close-up photo of a {}.",
    "a cropped photo of the {}.",
    "a bright photo of a {}.",
    "a dark photo of the {}.",
    "there is a {} in the scene.",
    "this is a {}.",
)


class TextEncoder:
    """`TextEncoder(model="clip_vitb16_text" | path, threads=None)`: texts -> raw CLIP features."""

    def __init__(self, model="clip_vitb16_text", threads: int | None = None):
        self.path = models.resolve(model)
        self.session = session(self.path, threads)
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs != [TEXT_INPUT] or TEXT_OUTPUT not in outputs:
            raise ValueError(
                f"{self.path} is not a text encoder: needs input {TEXT_INPUT!r} and output "
                f"{TEXT_OUTPUT!r}, has inputs {inputs} and outputs {outputs}"
            )

    def encode_ids(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids)
        if ids.dtype != np.int64 or ids.ndim != 2 or ids.shape[1] != CONTEXT_LENGTH:
            raise ValueError(f"expected int64 token ids [B,{CONTEXT_LENGTH}], got {ids.dtype} {ids.shape}")
        return self.session.run([TEXT_OUTPUT], {TEXT_INPUT: ids})[0].astype(np.float32, copy=False)

    def encode(self, texts) -> np.ndarray:
        """A string or list of strings -> float32 [N, 512], raw (not normalised)."""
        return self.encode_ids(tokenize(texts, truncate=True))


class Talk2DinoProjection:
    """CLIP text space -> DINOv2 patch space: W2 tanh(W1 t + b1) + b2 (Talk2DINO's
    `ProjectionLayer.project_clip_txt`), loaded from an npz with the torch state-dict keys
    `linear_layer.{weight,bias}` and `hidden_layers.0.{weight,bias}`."""

    def __init__(self, w1, b1, w2, b2):
        self.w1, self.b1 = np.asarray(w1, np.float32), np.asarray(b1, np.float32)
        self.w2, self.b2 = np.asarray(w2, np.float32), np.asarray(b2, np.float32)
        if self.w1.shape[0] != self.b1.shape[0] or self.w2.shape != (self.b2.shape[0], self.w1.shape[0]):
            raise ValueError(f"inconsistent projection shapes {self.w1.shape} {self.b1.shape} {self.w2.shape}")

    @classmethod
    def load(cls, path) -> "Talk2DinoProjection":
        keys = ("linear_layer.weight", "linear_layer.bias", "hidden_layers.0.weight", "hidden_layers.0.bias")
        with np.load(path) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise ValueError(f"{path} is not a Talk2DINO projection: missing {missing} (has {z.files})")
            return cls(*(z[k] for k in keys))

    @property
    def in_dim(self) -> int:
        return self.w1.shape[1]

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """[N, in_dim] raw CLIP text features -> [N, out_dim] float32 (not normalised)."""
        t = np.asarray(t, np.float32)
        if t.ndim != 2 or t.shape[1] != self.in_dim:
            raise ValueError(f"expected text features [N,{self.in_dim}], got {t.shape}")
        return np.tanh(t @ self.w1.T + self.b1) @ self.w2.T + self.b2
