"""Rendering a Gaussian map with the engine's rasterizer, and its backward pass.

    out = legslam.render(means, log_scales, quats, opacity_logits, sh, K, pose, width, height,
                         features=feats)
    out.color, out.depth, out.alpha, out.features      # numpy images, float32
    grads = out.backward(d_color=dL_dcolor, d_depth=dL_ddepth)

Poses are camera-to-world 4x4 (OpenCV axes). The pose gradient is with respect to the twist
xi = (rho, phi) of a left perturbation of the *world-to-camera* pose, T_cw <- exp(xi^) T_cw.

`feature_rgb` shows a rendered feature map as colour (its first three principal directions).
"""

from __future__ import annotations

import numpy as np

from . import _core

__all__ = ["render", "Render", "feature_rgb", "feature_basis"]


def _f32(a) -> np.ndarray:
    """Numbers as float32 (what the engine computes in); anything else as it is, for the
    bindings to refuse by name."""
    a = np.asarray(a)
    return np.ascontiguousarray(a, dtype=np.float32) if a.dtype.kind in "fiu" else a


def _intrinsics(K) -> np.ndarray:
    """A 3x3 K from a 3x3 matrix or (fx, fy, cx, cy)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (4,):
        fx, fy, cx, cy = K
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return np.ascontiguousarray(K)


class Render:
    """Images of one render (float32 numpy arrays; None when not requested) and its backward."""

    def __init__(self, core):
        self._core = core

    color = property(lambda self: self._core.color, doc="HxWx3 colour")
    depth = property(lambda self: self._core.depth, doc="HxW alpha-blended depth (metres)")
    alpha = property(lambda self: self._core.alpha, doc="HxW accumulated opacity")
    features = property(lambda self: self._core.features, doc="HxWxK features, or None")
    radii = property(lambda self: self._core.radii, doc="per-Gaussian screen extent, 0 if culled")
    num_pairs = property(lambda self: self._core.num_pairs, doc="tile-Gaussian pairs composited")

    def backward(self, d_color=None, d_depth=None, d_alpha=None, d_features=None) -> dict:
        """Gradients of a scalar loss given d(loss)/d(image) for the images in the loss.

        Returns a dict of float32 arrays shaped like the inputs: means, log_scales, quats,
        opacity_logits, sh, features, plus means2d (N x 2, pixels) and pose (6, see module doc).
        """
        def grad(a):
            return None if a is None else _f32(a)

        return self._core.backward(d_color=grad(d_color), d_depth=grad(d_depth),
                                   d_alpha=grad(d_alpha), d_features=grad(d_features))


def render(means, log_scales, quats, opacity_logits, sh, K, pose, width: int, height: int,
           features=None, sh_degree: int | None = None, color: bool = True, depth: bool = True,
           alpha: bool = True) -> Render:
    """Renders N Gaussians from a pinhole camera.

    means, log_scales: N x 3; quats: N x 4 unit (w, x, y, z); opacity_logits: N;
    sh: N x C x 3 with C in (1, 4, 9, 16), or N x 3 for degree 0; features: N x K or None;
    K: 3x3 intrinsics (or fx, fy, cx, cy) for a width x height image, pixel centres at integer
    coordinates; pose: 4x4 camera-to-world. sh_degree defaults to the degree sh holds.
    """
    means, sh = _f32(means), _f32(sh)
    if sh.ndim == 2:
        sh = sh[:, None, :]
    if sh_degree is None:
        sh_degree = int(round(np.sqrt(sh.shape[1]))) - 1 if sh.ndim == 3 else 0
    features = np.zeros((len(means), 0), np.float32) if features is None else _f32(features)
    core = _core.render(means, _f32(log_scales), _f32(quats), _f32(opacity_logits), sh, features,
                        _intrinsics(K), np.ascontiguousarray(pose, dtype=np.float64), int(width),
                        int(height), int(sh_degree), bool(color), bool(depth), bool(alpha))
    return Render(core)


def feature_basis(features: np.ndarray) -> np.ndarray:
    """K x 3: the first three principal directions of HxWxK features (from about 5000 pixels)."""
    x = features.reshape(-1, features.shape[-1]).astype(np.float64)
    centred = x - x.mean(0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(x) // 5000)], full_matrices=False)
    return vt[:3].T


def feature_rgb(features: np.ndarray, basis: np.ndarray | None = None) -> np.ndarray:
    """HxWxK features -> HxWx3 uint8: their projection on `basis` (default: their own first
    three principal directions) as colour."""
    h, w, k = features.shape
    x = features.reshape(-1, k).astype(np.float64)
    y = x @ (feature_basis(features) if basis is None else basis)
    lo, hi = np.percentile(y, 2, axis=0), np.percentile(y, 98, axis=0)
    y = np.clip((y - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return (y.reshape(h, w, 3) * 255).astype(np.uint8)
