"""`legslam export-models`: DINOv2 ViT-B/14-reg and the CLIP ViT-B/16 text tower as ONNX (see
legslam.features.export), on a machine with torch and the internet."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import models
from ..features import export
from .common import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: the model cache)")
    parser.add_argument("--input-size", type=int, default=518, help="DINOv2 input size, a multiple of 14 (default 518)")
    parser.add_argument("--only", choices=["dinov2", "clip"], help="export only one of the two models")


def run(args) -> int:
    if args.input_size % 14 or args.input_size < 14:
        raise UserError(f"--input-size must be a positive multiple of 14, got {args.input_size}")
    try:
        import torch  # optional: only this command needs it
    except ImportError as e:
        raise UserError("export-models needs torch (pip install torch open_clip_torch) and the internet") from e
    out = args.out or models.models_dir()
    out.mkdir(parents=True, exist_ok=True)
    torch.set_grad_enabled(False)
    try:
        if args.only in (None, "dinov2"):
            export.export_dinov2(out, args.input_size)
        if args.only in (None, "clip"):
            export.export_clip_text(out)
    except ImportError as e:
        raise UserError(f"{e} (pip install torch open_clip_torch)") from e
    print(f"models and manifest.json written to {out}")
    return 0
