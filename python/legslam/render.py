"""Rendering a Gaussian map with the engine's rasterizer, and its backward pass.

    out = legslam.render(means, log_scales, quats, opacity_logits, sh, K, pose, width, height,
                         features=feats)
    out.color, out.depth, out.alpha, out.features      # numpy images, float32
    grads = out.backward(d_color=dL_dcolor, d_depth=dL_ddepth)

Poses are camera-to-world 4x4 (OpenCV axes). The pose gradient is with respect to the twist
xi = (rho, phi) of a left perturbation of the *world-to-camera* pose, T_cw <- exp(xi^) T_cw.
"""

from __future__ import annotations

import numpy as np

from . import _core

__all__ = ["render", "Render"]


def _floats(name: str, a, shape: tuple) -> np.ndarray:
    """`a` as a C-contiguous float32 array of `shape` (None = any size), or ValueError."""
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be a numeric (real) array, got dtype {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _intrinsics(K) -> list[float]:
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        return [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    if K.shape == (4,):
        return list(K)
    raise ValueError(f"K must be a 3x3 intrinsics matrix or (fx, fy, cx, cy), got shape {K.shape}")


def _world_to_camera(pose) -> list[list[float]]:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 camera-to-world matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError("pose has a non-finite entry")
    if not np.allclose(pose[3], [0, 0, 0, 1]):
        raise ValueError(f"pose's last row must be [0, 0, 0, 1], got {pose[3]}")
    r, t = pose[:3, :3], pose[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = r.T
    w2c[:3, 3] = -r.T @ t
    return w2c.tolist()


class Render:
    """Images of one render (float32 numpy arrays; None when not requested) and its backward."""

    def __init__(self, core, n: int, k: int):
        self._core = core
        self._n = n
        self._k = k

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
        def grad(name, a, like):
            if a is None:
                return None
            if like is None:
                raise ValueError(f"{name} was given but that image was not rendered")
            return _floats(name, a, like.shape)

        return self._core.backward(
            d_color=grad("d_color", d_color, self.color),
            d_depth=grad("d_depth", d_depth, self.depth),
            d_alpha=grad("d_alpha", d_alpha, self.alpha),
            d_features=grad("d_features", d_features, self.features),
        )


def render(means, log_scales, quats, opacity_logits, sh, K, pose, width: int, height: int,
           features=None, sh_degree: int | None = None, color: bool = True, depth: bool = True,
           alpha: bool = True) -> Render:
    """Renders N Gaussians from a pinhole camera.

    means, log_scales: N x 3; quats: N x 4 unit (w, x, y, z); opacity_logits: N;
    sh: N x C x 3 with C in (1, 4, 9, 16), or N x 3 for degree 0; features: N x K or None;
    K: 3x3 intrinsics (or fx, fy, cx, cy) for a width x height image, pixel centres at integer
    coordinates; pose: 4x4 camera-to-world. sh_degree defaults to the degree sh holds.
    """
    means = np.asarray(means)
    n = means.shape[0] if means.ndim == 2 else -1
    means = _floats("means", means, (None, 3))
    log_scales = _floats("log_scales", log_scales, (n, 3))
    quats = _floats("quats", quats, (n, 4))
    opacity_logits = _floats("opacity_logits", opacity_logits, (n,))
    sh = np.asarray(sh)
    if sh.ndim == 2:
        sh = sh[:, None, :]
    sh = _floats("sh", sh, (n, None, 3))
    if sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"sh must hold 1, 4, 9 or 16 coefficients per channel, got {sh.shape[1]}")
    max_degree = int(round(np.sqrt(sh.shape[1]))) - 1
    if sh_degree is None:
        sh_degree = max_degree
    if not 0 <= sh_degree <= max_degree:
        raise ValueError(f"sh_degree must be in 0..{max_degree} for {sh.shape[1]} coefficients")
    if features is None:
        features = np.zeros((n, 0), np.float32)
    features = _floats("features", features, (n, None))
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    core = _core.render(means, log_scales, quats, opacity_logits, sh, features, _intrinsics(K),
                        _world_to_camera(pose), int(width), int(height), int(sh_degree),
                        bool(color), bool(depth), bool(alpha))
    return Render(core, n, features.shape[1])
