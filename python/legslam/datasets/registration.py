"""Depth registered to the colour camera, for sensors whose depth image comes from a camera of
its own (7-Scenes' Kinect): each depth pixel is lifted to 3D, moved into the colour camera and
projected there, the nearest surface winning where several land on one pixel."""

from __future__ import annotations

import numpy as np


def register_depth(depth: np.ndarray, K_depth: np.ndarray, K_color: np.ndarray,
                   color_from_depth: np.ndarray, size: tuple) -> np.ndarray:
    """The depth the colour camera of `size` (width, height) would see.

    depth: HxW, z along the depth camera's axis in any unit, 0 where there is none.
    color_from_depth: 4x4 taking depth-camera points to colour-camera points, its translation in
    the depth's unit. Returns an array of `size` and depth's dtype (rounded for integers), z along
    the colour camera's axis, 0 where no depth pixel lands."""
    hd, wd = depth.shape
    z = depth.astype(np.float64)
    x = ((np.arange(wd) - K_depth[0, 2]) / K_depth[0, 0])[None, :] * z
    y = ((np.arange(hd) - K_depth[1, 2]) / K_depth[1, 1])[:, None] * z
    r, t = color_from_depth[:3, :3], color_from_depth[:3, 3]
    pz = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
    keep = (z > 0) & (pz > 0)
    x, y, z, pz = x[keep], y[keep], z[keep], pz[keep]
    uc = np.rint(K_color[0, 0] * (r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]) / pz
                 + K_color[0, 2]).astype(np.int64)
    vc = np.rint(K_color[1, 1] * (r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]) / pz
                 + K_color[1, 2]).astype(np.int64)
    w, h = size
    inside = (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
    # The nearest of the points that land on a pixel.
    nearest = np.full(w * h, np.inf)
    np.minimum.at(nearest, vc[inside] * w + uc[inside], pz[inside])
    hit = np.isfinite(nearest)
    nearest[~hit] = 0
    if np.issubdtype(depth.dtype, np.integer):  # a hit stays a measurement: at least 1
        nearest[hit] = np.clip(np.rint(nearest[hit]), 1, np.iinfo(depth.dtype).max)
    return nearest.reshape(h, w).astype(depth.dtype)
