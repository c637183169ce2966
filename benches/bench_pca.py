"""PCA compression quality and per-keyframe feature cost on a real RGB-D sequence.

Extracts default-encoder features from frames spread over the 7-Scenes sequence in
../shared/data, fits the PCA on the patches of every other frame and reports, on the patches of
the remaining frames, the mean cosine similarity between each feature and its compressed-then-
restored version, for each K (the paper's Table: 0.957-0.988 at K=64 for ViT-B/14 at 518).
Also the per-frame costs: extraction, PCA compression, feature-target upsampling.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benches/bench_pca.py [--frames 40] [--input-size 224] [--threads 2]

Without OPENBLAS_NUM_THREADS=1, numpy's BLAS thread pool competes with onnxruntime's on a
2-core machine and the 0.5 ms compression takes 8-16 ms.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from legslam.features import PCA, Encoder, feature_target

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "7scenes_tsdf_fusion" / "data"
KS = (3, 6, 12, 16, 32, 64, 128)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="folder of frame-XXXXXX.color.jpg")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--model", default="default")
    args = parser.parse_args()

    paths = sorted(args.data.glob("frame-*.color.jpg"))
    if len(paths) < 2:
        print(f"no frames in {args.data}", file=sys.stderr)
        return 2
    picks = [paths[i] for i in np.linspace(0, len(paths) - 1, min(args.frames, len(paths))).astype(int)]
    enc = Encoder(args.model, input_size=args.input_size, threads=args.threads)
    enc.encode(np.zeros((*enc.input_size, 3), np.uint8))  # warm-up (session initialisation)

    feats, extract_ms = [], []
    for p in picks:
        rgb = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
        t0 = time.perf_counter()
        feats.append(enc.encode(rgb))
        extract_ms.append((time.perf_counter() - t0) * 1e3)
    h, w, d = feats[0].shape
    fit = np.concatenate([f.reshape(-1, d) for f in feats[0::2]])
    test = np.concatenate([f.reshape(-1, d) for f in feats[1::2]])

    print(f"model {enc.path.name}, input {enc.input_size[0]}x{enc.input_size[1]} -> {h}x{w}x{d} patches; "
          f"{len(picks)} frames of {args.data.parent.name}: PCA fitted on {len(fit)} patches "
          f"(every other frame), evaluated on {len(test)} patches of the other frames; "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}\n")
    print("| K | mean cos(restored, original) | min | 5th percentile |")
    print("| ---: | ---: | ---: | ---: |")
    full = PCA(max(KS)).fit(fit)
    for k in KS:
        pca = PCA(k).fit(fit) if k != max(KS) else full
        restored = pca.inverse_transform(pca.transform(test))
        cos = (restored * test).sum(1) / np.linalg.norm(restored, axis=1)  # test rows are unit length
        print(f"| {k} | {cos.mean():.4f} | {cos.min():.4f} | {np.percentile(cos, 5):.4f} |")

    pca64 = PCA(64).fit(fit)
    pca64.transform(feats[0])  # warm-up
    compress_ms, target_ms = [], []
    for f in feats:
        t0 = time.perf_counter()
        y = pca64.transform(f)
        t1 = time.perf_counter()
        feature_target(y, 480, 640)
        compress_ms.append((t1 - t0) * 1e3)
        target_ms.append((time.perf_counter() - t1) * 1e3)
    print("\n| per keyframe | median ms | mean ms |")
    print("| --- | ---: | ---: |")
    for name, v in (
        (f"extraction ({enc.input_size[0]}x{enc.input_size[1]}, {enc.session.get_session_options().intra_op_num_threads} threads)", extract_ms),
        (f"PCA compression {d}->64 ({h}x{w} patches)", compress_ms),
        ("feature target 64ch -> 480x640 (bilinear)", target_ms),
    ):
        print(f"| {name} | {np.median(v):.2f} | {np.mean(v):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
