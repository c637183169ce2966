"""Tiny ONNX stand-ins with the real models' input/output names and layouts, built with
onnx.helper, plus shared fixtures for the feature tests. The tests here check the stand-ins."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx", reason="building the tiny test models needs the onnx package")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared"
SHARED = Path(os.environ.get("LEGSLAM_SHARED", SHARED)).resolve()
PATCH = 14


def _save(graph, path: Path, meta: dict | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if meta:
        helper.set_model_props(model, meta)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def encoder_weights(dim: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((dim, 3, PATCH, PATCH)).astype(np.float32) * 0.05, rng.standard_normal(dim).astype(
        np.float32
    )


def make_encoder(path: Path, dim: int = 8, size: tuple | None = None, layout: str = "tokens", batch="batch") -> Path:
    """A ViT stand-in: a stride-14 patch projection (Conv). Input `input_image` [B,3,H,W]
    (H, W symbolic unless `size`; B symbolic unless `batch` is an int), output
    `x_norm_patchtokens` [B,N,D] ("tokens") or [B,h,w,D] ("grid")."""
    w, b = encoder_weights(dim)
    hw = list(size) if size else ["height", "width"]
    inp = helper.make_tensor_value_info("input_image", TensorProto.FLOAT, [batch, 3, *hw])
    nodes = [helper.make_node("Conv", ["input_image", "w", "b"], ["conv"], kernel_shape=[PATCH, PATCH], strides=[PATCH, PATCH])]
    if layout == "tokens":
        nodes += [
            helper.make_node("Reshape", ["conv", "shape"], ["flat"]),  # [B, D, N]
            helper.make_node("Transpose", ["flat"], ["x_norm_patchtokens"], perm=[0, 2, 1]),
        ]
        out = helper.make_tensor_value_info("x_norm_patchtokens", TensorProto.FLOAT, ["batch", "patches", dim])
    else:
        nodes += [helper.make_node("Transpose", ["conv"], ["x_norm_patchtokens"], perm=[0, 2, 3, 1])]
        out = helper.make_tensor_value_info("x_norm_patchtokens", TensorProto.FLOAT, ["batch", "h", "w", dim])
    inits = [
        numpy_helper.from_array(w, "w"),
        numpy_helper.from_array(b, "b"),
        numpy_helper.from_array(np.array([0, dim, -1], dtype=np.int64), "shape"),
    ]
    return _save(helper.make_graph(nodes, "tiny_encoder", [inp], [out], inits), path, {"patch_size": str(PATCH)})


def encoder_reference(x_nchw: np.ndarray, dim: int = 8) -> np.ndarray:
    """numpy patch projection of a preprocessed [B,3,H,W] input -> [B,h,w,D], not normalised."""
    w, b = encoder_weights(dim)
    bsz, _, hh, ww = x_nchw.shape
    h, wd = hh // PATCH, ww // PATCH
    patches = x_nchw.reshape(bsz, 3, h, PATCH, wd, PATCH).transpose(0, 2, 4, 1, 3, 5).reshape(bsz, h, wd, -1)
    return patches @ w.reshape(dim, -1).T + b


TEXT_VOCAB, TEXT_DIM = 49408, 8


def text_table(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((TEXT_VOCAB, TEXT_DIM)).astype(np.float32)


def make_text_encoder(path: Path) -> Path:
    """A CLIP text-tower stand-in: input `input_ids` int64 [B,77], output `text_embeds` [B,D],
    the embedding of the token at the argmax id (the <|endoftext|> position, as CLIP reads)."""
    inp = helper.make_tensor_value_info("input_ids", TensorProto.INT64, ["batch", 77])
    out = helper.make_tensor_value_info("text_embeds", TensorProto.FLOAT, ["batch", TEXT_DIM])
    nodes = [
        helper.make_node("ReduceMax", ["input_ids"], ["eot"], axes=[1], keepdims=0),  # the EOT id
        helper.make_node("Gather", ["table", "eot"], ["eot_emb"], axis=0),  # [B, D]
        helper.make_node("Gather", ["table", "input_ids"], ["emb"], axis=0),  # [B, 77, D]
        helper.make_node("ReduceMean", ["emb"], ["mean"], axes=[1], keepdims=0),
        helper.make_node("Add", ["eot_emb", "mean"], ["text_embeds"]),
    ]
    inits = [numpy_helper.from_array(text_table(), "table")]
    return _save(helper.make_graph(nodes, "tiny_text", [inp], [out], inits), path)


def text_reference(ids: np.ndarray) -> np.ndarray:
    table = text_table()
    return table[ids.max(axis=1)] + table[ids].mean(axis=1)


@pytest.fixture(scope="session")
def tiny_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("tiny_models")


def test_tiny_encoder_matches_its_numpy_reference(tiny_dir):
    import onnxruntime as ort

    x = np.random.default_rng(2).standard_normal((2, 3, 28, 42)).astype(np.float32)
    for layout in ("tokens", "grid"):
        path = make_encoder(tiny_dir / f"check_{layout}.onnx", layout=layout)
        y = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"input_image": x})[0]
        np.testing.assert_allclose(y.reshape(2, 2, 3, 8), encoder_reference(x), rtol=1e-4, atol=1e-5)


def test_tiny_text_encoder_matches_its_numpy_reference(tiny_dir):
    import onnxruntime as ort

    ids = np.zeros((2, 77), dtype=np.int64)
    ids[0, :4] = [49406, 320, 1929, 49407]
    ids[1, :3] = [49406, 320, 49407]
    path = make_text_encoder(tiny_dir / "check_text.onnx")
    y = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"input_ids": ids})[0]
    np.testing.assert_allclose(y, text_reference(ids), rtol=1e-5, atol=1e-6)
