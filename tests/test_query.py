"""Queries on a rendered feature map given as a numpy array."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_features_tiny_models import make_text_encoder, text_reference

from legslam import query
from legslam.features import PCA, Talk2DinoProjection, TextEncoder, tokenize


def _map(h=12, w=16, k=5, seed=0):
    return np.random.default_rng(seed).standard_normal((h, w, k)).astype(np.float32)


def test_heatmap_is_per_pixel_cosine_and_zero_where_nothing_rendered():
    f = _map()
    f[0, 0] = 0
    q = np.random.default_rng(1).standard_normal(5).astype(np.float32)
    heat = query.heatmap(f, q * 3)
    expected = (f @ q) / (np.linalg.norm(f, axis=2) * np.linalg.norm(q) + 1e-30)
    np.testing.assert_allclose(heat, expected, atol=1e-5)
    assert heat.shape == (12, 16) and heat[0, 0] == 0
    np.testing.assert_array_equal(query.mask(heat, 0.5), heat >= 0.5)


def test_segment_takes_the_best_class_above_threshold():
    classes = np.eye(3, 5, dtype=np.float32)
    f = np.zeros((2, 3, 5), np.float32)
    f[0, 0] = [1, 0.2, 0, 0, 0]  # class 0
    f[0, 1] = [0, 0.1, 2, 0, 0]  # class 2
    f[0, 2] = [0, 1, 0, 0, 0.1]  # class 1
    f[1, 0] = [0, 0, 0, 1, 1]  # scores 0: below a positive threshold
    f[1, 1] = [0.3, 0.3, 0, 1, 0]  # best ~0.27
    labels = query.segment(f, classes, threshold=0.5)
    assert labels.dtype == np.int32
    np.testing.assert_array_equal(labels, [[0, 2, 1], [-1, -1, -1]])
    assert query.segment(f, classes, threshold=0.2)[1, 1] in (0, 1)


def test_query_from_pixel_and_box():
    f = _map()
    q = query.query_from_pixel(f, 3, 4)
    np.testing.assert_allclose(q, f[4, 3] / np.linalg.norm(f[4, 3]), atol=1e-6)
    assert query.heatmap(f, q)[4, 3] == pytest.approx(1.0, abs=1e-5)
    # A window clipped at the corner equals the box it covers.
    np.testing.assert_allclose(query.query_from_pixel(f, 0, 0, radius=2), query.query_from_box(f, 0, 0, 3, 3), atol=1e-6)
    unit = f / np.linalg.norm(f, axis=2, keepdims=True)
    mean = unit[2:5, 1:4].reshape(-1, 5).mean(0)
    np.testing.assert_allclose(query.query_from_box(f, 1, 2, 4, 5), mean / np.linalg.norm(mean), atol=1e-6)


@pytest.mark.parametrize(
    "call,msg",
    [
        (lambda f: query.query_from_pixel(f, 16, 0), "outside"),
        (lambda f: query.query_from_pixel(f, 1, 1, radius=-1), "radius"),
        (lambda f: query.query_from_box(f, 3, 3, 3, 5), "empty"),
        (lambda f: query.query_from_box(np.zeros_like(f), 0, 0, 2, 2), "nothing is rendered"),
        (lambda f: query.heatmap(f, np.ones(4)), "K=5"),
        (lambda f: query.heatmap(f, np.zeros(5)), "zero"),
        (lambda f: query.heatmap(f[..., 0], np.ones(5)), "H x W x K"),
        (lambda f: query.heatmap(np.where(f > 0, np.nan, f), np.ones(5)), "NaN"),
        (lambda f: query.segment(f, np.ones((2, 5)) * np.nan), "NaN"),
    ],
)
def test_bad_input_is_rejected(call, msg):
    with pytest.raises(ValueError, match=msg):
        call(_map())


def test_text_queries_pipeline(tmp_path):
    enc = TextEncoder(make_text_encoder(tmp_path / "t.onnx"))
    rng = np.random.default_rng(0)
    proj = Talk2DinoProjection(rng.standard_normal((6, 8)), rng.standard_normal(6), rng.standard_normal((7, 6)), rng.standard_normal(7))
    pca = PCA(4).fit(rng.standard_normal((50, 7)))
    templates = ("a photo of a {}.", "this is a {}.")
    q = query.text_queries(["chair", "sky"], enc, proj, pca, templates)
    assert q.shape == (2, 4) and q.dtype == np.float32
    # By hand: project each prompt, average over templates, normalise, compress, normalise.
    raw = text_reference(tokenize(["a photo of a chair.", "this is a chair."]))
    mean = proj(raw).mean(axis=0)
    expected = pca.transform(mean / np.linalg.norm(mean))
    np.testing.assert_allclose(q[0], expected / np.linalg.norm(expected), atol=1e-5)
    assert query.text_queries("chair", enc, templates=templates).shape == (1, 8)
    with pytest.raises(ValueError, match="at least one"):
        query.text_queries([], enc)


def test_fit_text_pca_on_perturbed_label_embeddings(tmp_path):
    enc = TextEncoder(make_text_encoder(tmp_path / "t.onnx"))
    labels = ["chair", "sky", "plant", "table", "lamp"]
    pca = query.fit_text_pca(labels, enc, n_components=4, copies=10, min_cos=0.95)
    assert pca.n_samples == 5 * 11 and pca.components.shape == (4, 8)
    # The label embeddings themselves are well represented by the fitted components.
    emb = query.text_queries(labels, enc)
    restored = pca.inverse_transform(pca.transform(emb))
    cos = (restored * emb).sum(1) / np.linalg.norm(restored, axis=1)
    assert cos.min() > 0.9


def test_overlay_and_png(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    heat = np.linspace(-1, 1, 12 * 16, dtype=np.float32).reshape(12, 16)
    out = query.overlay(rgb, heat)
    assert out.shape == rgb.shape and out.dtype == np.uint8 and not np.array_equal(out, rgb)
    where = heat > 0.5
    tinted = query.overlay(rgb, heat, where=where)
    np.testing.assert_array_equal(tinted[~where], rgb[~where])
    # The hottest pixel is red-dominant in RGB (jet), the coldest blue-dominant.
    full = query.overlay(np.zeros_like(rgb), heat, alpha=1.0)
    assert full[-1, -1, 0] > full[-1, -1, 2] and full[0, 0, 2] > full[0, 0, 0]
    query.save_overlay(tmp_path / "o.png", rgb, heat)
    back = cv2.cvtColor(cv2.imread(str(tmp_path / "o.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, out)
    with pytest.raises(ValueError, match="does not match"):
        query.overlay(rgb, heat[:5])
