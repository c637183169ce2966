"""Open-vocabulary queries against a rendered feature map (H x W x K float32, any source).

A query is a K-vector in the same (PCA-compressed) space as the map: from text
(`text_queries`: CLIP text -> Talk2DINO projection -> mean over prompt templates -> L2 -> PCA)
or from an example (`query_from_pixel`, `query_from_box`: the map's own feature there). Scores
are cosine similarities; a pixel whose rendered feature is zero (nothing rendered) scores 0.
"""

from __future__ import annotations

import cv2
import numpy as np

from legslam.features.encoder import l2_normalize
from legslam.features.pca import PCA
from legslam.features.text import TEMPLATES


def _check_map(feature_map) -> np.ndarray:
    f = np.asarray(feature_map)
    if f.ndim != 3 or not np.issubdtype(f.dtype, np.floating):
        raise ValueError(f"expected a floating feature map H x W x K, got {f.dtype} {f.shape}")
    if not np.isfinite(f).all():
        raise ValueError("feature map contains NaN or inf")
    return f.astype(np.float32, copy=False)


def _check_queries(queries, k: int) -> np.ndarray:
    q = np.asarray(queries, dtype=np.float32)
    if q.ndim != 2 or q.shape[1] != k:
        raise ValueError(f"expected queries [C,{k}] matching the feature map's K={k}, got {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("queries contain NaN or inf")
    if (np.linalg.norm(q, axis=1) == 0).any():
        raise ValueError("a query vector is zero")
    return q


def scores(feature_map, queries) -> np.ndarray:
    """Cosine similarity of every pixel with every query: H x W x C float32."""
    f = _check_map(feature_map)
    q = l2_normalize(_check_queries(queries, f.shape[2]))
    return l2_normalize(f) @ q.T


def heatmap(feature_map, query) -> np.ndarray:
    """Cosine similarity of every pixel with one K-vector query: H x W float32 in [-1, 1]."""
    return scores(feature_map, np.asarray(query)[None, :])[:, :, 0]


def mask(heat, threshold: float) -> np.ndarray:
    """Boolean H x W: where the heat map reaches the threshold."""
    return np.asarray(heat) >= threshold


def segment(feature_map, queries, threshold: float = 0.0) -> np.ndarray:
    """Per-pixel argmax over C class queries [C,K]: int32 H x W labels, -1 where the best
    class scores below `threshold`."""
    s = scores(feature_map, queries)
    labels = s.argmax(axis=2).astype(np.int32)
    labels[s.max(axis=2) < threshold] = -1
    return labels


def query_from_box(feature_map, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """The normalised mean feature of the pixels x0 <= x < x1, y0 <= y < y1 (a K-vector)."""
    f = _check_map(feature_map)
    h, w = f.shape[:2]
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise ValueError(f"box x[{x0},{x1}) y[{y0},{y1}) is empty or outside the {w}x{h} map")
    mean = l2_normalize(f[y0:y1, x0:x1]).reshape(-1, f.shape[2]).mean(axis=0)
    if not np.linalg.norm(mean) > 0:
        raise ValueError("nothing is rendered in the chosen pixels (all features zero)")
    return l2_normalize(mean)


def query_from_pixel(feature_map, x: int, y: int, radius: int = 0) -> np.ndarray:
    """The feature at pixel (x, y), averaged over a (2r+1)^2 window clipped to the map."""
    f = np.asarray(feature_map)
    if f.ndim != 3 or not (0 <= x < f.shape[1] and 0 <= y < f.shape[0]):
        raise ValueError(f"pixel ({x}, {y}) is outside the map of shape {f.shape}")
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    return query_from_box(
        f, max(0, x - radius), max(0, y - radius), min(f.shape[1], x + radius + 1), min(f.shape[0], y + radius + 1)
    )


def text_queries(labels, text_encoder, projection=None, pca=None, templates=TEMPLATES) -> np.ndarray:
    """Label names -> query vectors [C, K] float32, unit length.

    Per label: one prompt per template, raw CLIP text features (`text_encoder.encode`), the
    Talk2DINO projection (if given) per prompt, the mean over prompts, L2 normalisation, then
    the map's PCA (if given: the map's features must have gone through the same PCA)."""
    if isinstance(labels, str):
        labels = [labels]
    if not labels or not templates:
        raise ValueError("need at least one label and one template")
    prompts = [t.format(label) for label in labels for t in templates]
    emb = text_encoder.encode(prompts)
    if projection is not None:
        emb = projection(emb)
    emb = l2_normalize(emb.reshape(len(labels), len(templates), -1).mean(axis=1))
    if pca is not None:
        emb = pca.transform(emb)
    return l2_normalize(emb)


def fit_text_pca(
    labels, text_encoder, projection=None, n_components: int = 64, copies: int = 32, min_cos: float = 0.95, seed: int = 0
) -> PCA:
    """The paper's PCA: fitted on the (projected) text embeddings of a label list, each with
    `copies` random perturbations whose cosine to it is uniform in [min_cos, 1]."""
    emb = text_queries(labels, text_encoder, projection).astype(np.float64)  # [C, D], unit
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((len(emb), copies, emb.shape[1]))
    noise -= (noise @ emb[:, :, None]) * emb[:, None, :]  # orthogonal to each embedding
    noise /= np.linalg.norm(noise, axis=2, keepdims=True)
    angle = rng.uniform(0, np.arccos(min_cos), (len(emb), copies, 1))
    samples = np.cos(angle) * emb[:, None, :] + np.sin(angle) * noise  # unit, cos = cos(angle)
    return PCA(n_components).fit(np.concatenate([emb, samples.reshape(-1, emb.shape[1])]))


def overlay(rgb, heat, alpha: float = 0.5, vmin: float | None = None, vmax: float | None = None, where=None):
    """The heat map colour-mapped (jet) over a uint8 RGB image; returns uint8 RGB.

    Heat is scaled from [vmin, vmax] (default: its own range) to the colour map; if `where`
    (boolean H x W) is given, only those pixels are tinted."""
    rgb = np.asarray(rgb)
    heat = np.asarray(heat, dtype=np.float32)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected a uint8 RGB image HxWx3, got {rgb.dtype} {rgb.shape}")
    if heat.shape != rgb.shape[:2]:
        raise ValueError(f"heat map {heat.shape} does not match the image {rgb.shape[:2]}")
    lo = float(np.nanmin(heat)) if vmin is None else vmin
    hi = float(np.nanmax(heat)) if vmax is None else vmax
    scaled = np.clip((np.nan_to_num(heat, nan=lo) - lo) / max(hi - lo, 1e-12), 0, 1)
    colour = cv2.cvtColor(cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)
    blended = cv2.addWeighted(rgb, 1 - alpha, colour, alpha, 0)
    if where is not None:
        blended = np.where(np.asarray(where, bool)[:, :, None], blended, rgb)
    return blended


def save_overlay(path, rgb, heat, **kwargs) -> None:
    """Writes `overlay(rgb, heat, **kwargs)` as an image file (PNG by the path's extension)."""
    if not cv2.imwrite(str(path), cv2.cvtColor(overlay(rgb, heat, **kwargs), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
