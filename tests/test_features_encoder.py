"""legslam.features.Encoder on tiny stand-in models, and on the real default encoder when cached."""

from __future__ import annotations

import numpy as np
import pytest
from test_features_tiny_models import SHARED, encoder_reference, make_encoder

from legslam import models
from legslam.features import Encoder
from legslam.features.encoder import IMAGENET_MEAN, IMAGENET_STD


def _frame(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _normalised(rgb):
    x = (rgb.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return x.transpose(2, 0, 1)[None]


def test_encode_matches_reference_and_is_unit_length(tmp_path):
    enc = Encoder(make_encoder(tmp_path / "e.onnx"), input_size=(28, 42))
    rgb = _frame(28, 42)  # already at the input size: no resampling
    f = enc.encode(rgb)
    assert f.shape == (2, 3, 8) and f.dtype == np.float32
    ref = encoder_reference(_normalised(rgb))[0]
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    np.testing.assert_allclose(f, ref, rtol=1e-4, atol=1e-5)


def test_grid_layout_output_gives_the_same_features(tmp_path):
    rgb = _frame(50, 70)
    a = Encoder(make_encoder(tmp_path / "t.onnx"), input_size=56).encode(rgb)
    b = Encoder(make_encoder(tmp_path / "g.onnx", layout="grid"), input_size=56).encode(rgb)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_input_size_is_rounded_to_patch_multiples_and_frames_resized(tmp_path):
    enc = Encoder(make_encoder(tmp_path / "e.onnx"), input_size=100)
    assert enc.input_size == (98, 98) and enc.grid == (7, 7) and not enc.fixed_size
    assert enc.encode(_frame(480, 640)).shape == (7, 7, 8)


def test_fixed_size_model_overrides_input_size(tmp_path):
    enc = Encoder(make_encoder(tmp_path / "f.onnx", size=(28, 56)), input_size=224)
    assert enc.fixed_size and enc.input_size == (28, 56)
    assert enc.encode(_frame(100, 100)).shape == (2, 4, 8)


@pytest.mark.parametrize("batch", ["batch", 1])
def test_batch_equals_single_frames(tmp_path, batch):
    enc = Encoder(make_encoder(tmp_path / "e.onnx", batch=batch), input_size=42)
    frames = [_frame(60, 80, s) for s in range(3)]
    out = enc.encode_batch(frames)  # a model with a fixed batch of 1 runs frame by frame
    assert out.shape == (3, 3, 3, 8)
    for f, one in zip(frames, out):
        np.testing.assert_allclose(enc.encode(f), one, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((28, 28, 3), np.float32), np.zeros((28, 28), np.uint8), np.zeros((28, 28, 4), np.uint8), [[1, 2, 3]]],
)
def test_bad_frames_are_rejected(tmp_path, bad):
    enc = Encoder(make_encoder(tmp_path / "e.onnx"), input_size=28)
    with pytest.raises(ValueError, match="uint8 RGB"):
        enc.encode(bad)


def test_missing_model_says_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.setenv("LEGSLAM_CACHE", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="legslam models fetch"):
        Encoder("default")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        Encoder(tmp_path / "nope.onnx")


def test_model_with_other_io_names_is_rejected(tmp_path):
    from test_features_tiny_models import make_text_encoder

    with pytest.raises(ValueError, match="not a dense encoder"):
        Encoder(make_text_encoder(tmp_path / "t.onnx"))


# ---- the real default encoder (cached by scripts/setup.sh) ----------------------------------

FRAMES = SHARED / "data" / "7scenes_tsdf_fusion" / "data"


@pytest.fixture(scope="module")
def real_encoder():
    try:
        return Encoder("default", input_size=224)
    except FileNotFoundError as e:
        pytest.skip(f"default encoder not cached ({e})")


def _real_frame(i):
    import cv2

    path = FRAMES / f"frame-{i:06d}.color.jpg"
    if not path.exists():
        pytest.skip(f"{path} absent (the shared data folder is needed)")
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def test_real_encoder_gives_unit_384d_features_on_a_16x16_grid(real_encoder):
    f = real_encoder.encode(_real_frame(0))
    assert f.shape == (16, 16, 384) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-5)
    assert models.resolve("default").name == models.DEFAULT_MODEL


def test_real_encoder_is_stable_across_nearby_frames_and_sizes(real_encoder):
    a, b = real_encoder.encode(_real_frame(0)), real_encoder.encode(_real_frame(2))
    same_patch = (a * b).sum(-1).mean()
    shuffled = (a * b.reshape(-1, 384)[::-1].reshape(a.shape)).sum(-1).mean()
    # DINOv2 patch features share a large common component: random pairs score ~0.75 here.
    assert same_patch > 0.95 and same_patch > shuffled + 0.1, (same_patch, shuffled)
    # The cut graph interpolates its position embeddings: other multiples of 14 work.
    big = Encoder("default", input_size=280).encode(_real_frame(0))
    assert big.shape == (20, 20, 384)


def test_int8_encoder_agrees_with_the_full_precision_one(real_encoder):
    try:
        int8 = Encoder("dinov2_vits14_int8", input_size=224)
    except FileNotFoundError as e:
        pytest.skip(f"int8 encoder not cached ({e})")
    frame = _real_frame(0)
    a, b = real_encoder.encode(frame), int8.encode(frame)
    cos = (a * b).sum(-1)
    assert cos.mean() > 0.99 and cos.min() > 0.95, (cos.mean(), cos.min())
    assert not np.array_equal(a, b)
