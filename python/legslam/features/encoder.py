"""Dense image features from an ONNX ViT: RGB frame -> (h, w, D) L2-normalised patch features.

The model contract (the default encoder and `legslam export-models` both follow it): input
`input_image` float32 [B,3,H,W], ImageNet-normalised RGB; output `x_norm_patchtokens` float32
[B, h*w, D] (row-major patch grid, no CLS/register tokens) or [B, h, w, D]. The patch size comes
from the model's metadata (`patch_size`), 14 if absent. If the model fixes H and W, frames are
resized to that size whatever `input_size` says.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import onnxruntime as ort

from legslam import models

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
INPUT_NAME = "input_image"
OUTPUT_NAME = "x_norm_patchtokens"


def session(path, threads: int | None) -> ort.InferenceSession:
    """A CPU onnxruntime session with `threads` intra-op threads (default: all cores)."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads or os.cpu_count() or 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    # Idle pool threads sleep instead of spinning, so they leave the cores to tracking.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def l2_normalize(x: np.ndarray, axis: int = -1) -> np.ndarray:
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return (x / np.maximum(norm, 1e-12)).astype(np.float32, copy=False)


class Encoder:
    """`Encoder(model="default" | name | path, input_size=224, threads=None)`.

    input_size: int (square, as the paper: the whole frame resized to 518x518) or (height,
    width); rounded to the nearest multiple of the patch size. Ignored when the model fixes
    its input size (then `self.input_size` tells the size used).
    """

    def __init__(self, model="default", input_size=224, threads: int | None = None):
        self.path = models.resolve(model)
        self.session = session(self.path, threads)
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = [o.name for o in self.session.get_outputs()]
        if INPUT_NAME not in inputs or OUTPUT_NAME not in outputs:
            raise ValueError(
                f"{self.path} is not a dense encoder: needs input {INPUT_NAME!r} and output "
                f"{OUTPUT_NAME!r}, has inputs {list(inputs)} and outputs {outputs}"
            )
        meta = self.session.get_modelmeta().custom_metadata_map
        self.patch_size = int(meta.get("patch_size", 14))
        shape = inputs[INPUT_NAME].shape  # [B, 3, H, W]; symbolic dims are strings or None
        if len(shape) != 4 or shape[1] != 3:
            raise ValueError(f"{self.path}: input {INPUT_NAME!r} must be [B,3,H,W], is {shape}")
        if isinstance(shape[2], int) and isinstance(shape[3], int):
            self.input_size = (shape[2], shape[3])
            self.fixed_size = True
        else:
            h, w = (input_size, input_size) if np.isscalar(input_size) else input_size
            p = self.patch_size
            self.input_size = (max(p, round(h / p) * p), max(p, round(w / p) * p))
            self.fixed_size = False
        self.batch_fixed = isinstance(shape[0], int)
        self.grid = (self.input_size[0] // self.patch_size, self.input_size[1] // self.patch_size)
        out = {o.name: o for o in self.session.get_outputs()}[OUTPUT_NAME].shape
        #: The feature dimension D, or None where the model leaves it symbolic.
        self.dim = out[-1] if out and isinstance(out[-1], int) else None

    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """uint8 RGB HxWx3 -> float32 [3, H', W'] resized and ImageNet-normalised."""
        if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            desc = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
            raise ValueError(f"expected a uint8 RGB image HxWx3, got {desc}")
        h, w = self.input_size
        # INTER_AREA anti-aliases when shrinking (the usual case); cubic when enlarging.
        shrink = h * w <= rgb.shape[0] * rgb.shape[1]
        img = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
        img = (img.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(img.transpose(2, 0, 1))

    def encode_batch(self, frames) -> np.ndarray:
        """A list of uint8 RGB frames -> [B, h, w, D] float32, L2-normalised per patch."""
        if not len(frames):
            raise ValueError("encode_batch needs at least one frame")
        if self.batch_fixed and len(frames) != 1:
            return np.concatenate([self.encode_batch([f]) for f in frames])
        x = np.stack([self.preprocess(f) for f in frames])
        y = self.session.run([OUTPUT_NAME], {INPUT_NAME: x})[0]
        h, w = self.grid
        if y.ndim == 3 and y.shape[1] == h * w:
            y = y.reshape(y.shape[0], h, w, y.shape[2])
        if y.shape[1:3] != (h, w):
            raise ValueError(f"{self.path}: output {y.shape} does not match the {h}x{w} patch grid")
        return l2_normalize(y)

    def encode(self, rgb: np.ndarray) -> np.ndarray:
        """A uint8 RGB frame HxWx3 -> (h, w, D) float32 patch features, each of unit length."""
        return self.encode_batch([rgb])[0]
