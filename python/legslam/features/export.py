"""The paper's models as ONNX, for machines with torch and the internet (`legslam
export-models`). Written into a folder (by default the model cache, so the names resolve):
  dinov2_vitb14_reg.onnx  DINOv2 ViT-B/14 with registers (torch.hub facebookresearch/dinov2):
                          input `input_image` [B,3,S,S] (S = --input-size, fixed; the paper: 518),
                          output `x_norm_patchtokens` [B,(S/14)^2,768]
  clip_vitb16_text.onnx   OpenAI CLIP ViT-B/16 text tower (open_clip, pretrained="openai"):
                          input `input_ids` int64 [B,77], output `text_embeds` [B,512], raw
and a manifest.json with the sha256 of each, the source, and the max abs difference between
onnxruntime and torch on a test input. Needs `torch` and `open_clip_torch` (pip install torch
open_clip_torch); neither is a legslam dependency. Batch is dynamic; the image size is fixed at
export because DINOv2's position-embedding interpolation is traced with constant sizes.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from legslam import models

log = logging.getLogger("legslam")

OPSET = 17


def _export(model, forward, example, out: Path, filename: str, io: tuple, meta: dict, **info) -> None:
    """torch.onnx.export of `forward(model, x)` with a dynamic batch into out/filename, checked
    against torch with onnxruntime on `example`, and recorded in out/manifest.json."""
    import inspect

    import onnx
    import torch

    from legslam.features.encoder import session

    class Forward(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, x):
            return forward(self.model, x)

    module = Forward().eval()
    input_name, output_name = io
    tmp = out / (filename + ".partial")
    # The TorchScript exporter (dynamo=False): dynamic_axes is its API; older torch lacks the flag.
    legacy = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
    torch.onnx.export(
        module,
        (example,),
        str(tmp),
        input_names=[input_name],
        output_names=[output_name],
        dynamic_axes={input_name: {0: "batch"}, output_name: {0: "batch"}},
        opset_version=OPSET,
        **legacy,
    )
    onnx_model = onnx.load(str(tmp))
    onnx.helper.set_model_props(onnx_model, meta)
    onnx.save(onnx_model, str(tmp))
    expected = module(example).numpy()
    got = session(tmp, None).run([output_name], {input_name: example.numpy()})[0]
    err = float(np.abs(got - expected).max())
    tmp.replace(out / filename)
    models.record_in_manifest(out, filename, torch_version=torch.__version__, max_abs_diff_vs_torch=err, **info)
    log.info("%s: max |onnxruntime - torch| = %.2e", filename, err)


def export_dinov2(out: Path, input_size: int) -> None:
    import torch

    log.info("loading dinov2_vitb14_reg from torch.hub ...")
    dino = torch.hub.load("facebookresearch/dinov2", "dinov2_vitb14_reg").eval()
    _export(
        dino,
        lambda m, x: m.forward_features(x)["x_norm_patchtokens"],
        torch.randn(1, 3, input_size, input_size),
        out,
        "dinov2_vitb14_reg.onnx",
        ("input_image", "x_norm_patchtokens"),
        {"patch_size": "14", "legslam_model": "dinov2_vitb14_reg"},
        source="torch.hub facebookresearch/dinov2 dinov2_vitb14_reg (Apache-2.0)",
        input=f"input_image float32 [B,3,{input_size},{input_size}], ImageNet-normalised RGB",
        output=f"x_norm_patchtokens float32 [B,{(input_size // 14) ** 2},768]",
    )


def export_clip_text(out: Path) -> None:
    import open_clip
    import torch

    from legslam.features.tokenizer import tokenize

    log.info("loading OpenAI CLIP ViT-B/16 with open_clip ...")
    clip = open_clip.create_model("ViT-B-16", pretrained="openai").eval()
    _export(
        clip,
        # Raw features at the <|endoftext|> token (argmax id): what Talk2DINO was trained on.
        lambda m, ids: m.encode_text(ids, normalize=False),
        torch.from_numpy(tokenize(["a photo of a chair.", "a plant"])),
        out,
        "clip_vitb16_text.onnx",
        ("input_ids", "text_embeds"),
        {"legslam_model": "clip_vitb16_text", "context_length": "77"},
        source="open_clip ViT-B-16 pretrained=openai (OpenAI CLIP, MIT): text tower",
        input="input_ids int64 [B,77], CLIP BPE token ids (legslam.features.tokenize)",
        output="text_embeds float32 [B,512], raw (not normalised) text features",
        open_clip_version=open_clip.__version__,
    )
