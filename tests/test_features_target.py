"""feature_target: bilinear upsampling of the compressed patch grid (align_corners=False)."""

from __future__ import annotations

import numpy as np
import pytest

from legslam.features import feature_target


def _bilinear_reference(grid, height, width):
    """Slow, obvious bilinear upsampling with half-pixel centres and clamped edges."""
    h, w, _ = grid.shape
    out = np.zeros((height, width, grid.shape[2]), np.float64)
    for y in range(height):
        sy = min(max((y + 0.5) * h / height - 0.5, 0), h - 1)
        y0 = int(np.floor(sy))
        y1, fy = min(y0 + 1, h - 1), sy - y0
        for x in range(width):
            sx = min(max((x + 0.5) * w / width - 0.5, 0), w - 1)
            x0 = int(np.floor(sx))
            x1, fx = min(x0 + 1, w - 1), sx - x0
            top = grid[y0, x0] * (1 - fx) + grid[y0, x1] * fx
            bottom = grid[y1, x0] * (1 - fx) + grid[y1, x1] * fx
            out[y, x] = top * (1 - fy) + bottom * fy
    return out


@pytest.mark.parametrize("k", [1, 3, 64, 200])
def test_matches_reference_bilinear(k):
    grid = np.random.default_rng(k).standard_normal((4, 5, k)).astype(np.float32)
    t = feature_target(grid, 22, 31)
    assert t.shape == (22, 31, k) and t.dtype == np.float32
    np.testing.assert_allclose(t, _bilinear_reference(grid, 22, 31), atol=2e-3)


def test_constant_grid_stays_constant():
    grid = np.tile(np.arange(6, dtype=np.float32), (3, 3, 1))
    np.testing.assert_allclose(feature_target(grid, 48, 64), np.broadcast_to(np.arange(6), (48, 64, 6)), atol=1e-6)


@pytest.mark.parametrize(
    "grid,size,msg",
    [
        (np.zeros((4, 4), np.float32), (8, 8), "patch grid"),
        (np.zeros((4, 4, 3), np.int64), (8, 8), "patch grid"),
        (np.zeros((4, 4, 3), np.float32), (0, 8), "positive"),
        (np.full((4, 4, 3), np.nan, np.float32), (8, 8), "NaN"),
    ],
)
def test_bad_input_is_rejected(grid, size, msg):
    with pytest.raises(ValueError, match=msg):
        feature_target(grid, *size)
