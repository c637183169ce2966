"""Depth registered to the colour camera, for sensors whose depth image comes from a camera of
its own (7-Scenes' Kinect): each depth pixel is lifted to 3D, moved into the colour camera and
projected there, the nearest surface winning where several land on one pixel (in the engine)."""

from __future__ import annotations

import numpy as np


def register_depth(depth: np.ndarray, K_depth: np.ndarray, K_color: np.ndarray,
                   color_from_depth: np.ndarray, size: tuple) -> np.ndarray:
    """The depth the colour camera of `size` (width, height) would see.

    depth: HxW, z along the depth camera's axis in any unit, 0 where there is none.
    color_from_depth: 4x4 taking depth-camera points to colour-camera points, its translation in
    the depth's unit. Returns an array of `size` and depth's dtype (rounded for integers), z along
    the colour camera's axis, 0 where no depth pixel lands."""
    from .. import _core

    depth = np.asarray(depth)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    out = _core.register_depth(np.ascontiguousarray(depth, dtype=np.float32), f64(K_depth),
                               f64(K_color), f64(color_from_depth), int(size[0]), int(size[1]))
    if np.issubdtype(depth.dtype, np.integer):
        rounded = np.minimum(np.rint(out), np.iinfo(depth.dtype).max)
        rounded[(rounded == 0) & (out > 0)] = 1  # a hit stays a measurement
        out = rounded
    return out.astype(depth.dtype, copy=False)
