"""The feature target of the mapping loss: the compressed patch grid at the training resolution."""

from __future__ import annotations

import cv2
import numpy as np


def feature_target(patch_grid: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w, K) patch features -> (height, width, K) float32, bilinearly upsampled.

    Pixel centres are aligned as torch's `interpolate(..., mode="bilinear", align_corners=False)`
    does (the paper's upsampling), with edge values repeated. Not renormalised: the loss is
    1 - cos, which ignores length."""
    grid = np.asarray(patch_grid)
    if grid.ndim != 3 or not np.issubdtype(grid.dtype, np.floating):
        raise ValueError(f"expected a floating (h, w, K) patch grid, got {grid.dtype} {grid.shape}")
    if height < 1 or width < 1:
        raise ValueError(f"target size must be positive, got {height}x{width}")
    if not np.isfinite(grid).all():
        raise ValueError("patch grid contains NaN or inf")
    grid = np.ascontiguousarray(grid, dtype=np.float32)
    k = grid.shape[2]
    # cv2.resize takes at most 128 channels in OpenCV 5 (512 in 4) and drops a trailing axis
    # of 1: resize in chunks of 128.
    chunks = [
        cv2.resize(np.ascontiguousarray(grid[:, :, i : i + 128]), (width, height), interpolation=cv2.INTER_LINEAR)
        .reshape(height, width, -1)
        for i in range(0, k, 128)
    ]
    return np.concatenate(chunks, axis=2) if len(chunks) > 1 else chunks[0]
