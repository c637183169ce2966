"""Language features of a finished run on a real sequence (default: a `bench_slam.py` run on
7-Scenes): how well the map's rendered 64-d features agree with the encoder's own compressed
features at frames that were not keyframes (never trained on), and whether a by-example query
picked on one frame lights up the same surface in another.

The by-example check: a pixel with valid depth in frame A is back-projected with the ground-truth
depth and pose and projected into frame B; the query (the feature rendered at that pixel of A)
is compared with the heat map rendered at B. Reported: the heat at the projected location and
its percentile among all of B's pixels (100 = the hottest pixel).

    python benches/bench_language.py RUN_DIR [SEQUENCE] [--frames N] [--pairs N]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("sequence", nargs="?", default=None)
    ap.add_argument("--frames", type=int, default=10, help="held-out frames compared with the encoder")
    ap.add_argument("--pairs", type=int, default=20, help="by-example (A, B) pairs")
    args = ap.parse_args()
    from legslam.datasets import open as open_dataset
    from legslam.eval import read_tum
    from legslam.features import PCA, Encoder
    from legslam.slam import SLAMConfig
    from legslam.map import GaussianMap
    from legslam.query import heatmap, query_from_pixel

    run = Path(args.run)
    cam = json.loads((run / "camera.json").read_text())
    seq = open_dataset(args.sequence or cam["sequence"])
    K, w, h = np.array(cam["K"]), cam["width"], cam["height"]
    _, poses = read_tum(run / "trajectory.txt")
    m = GaussianMap.load(run / "map.ply")
    pca = PCA.load(run / "pca.npz")
    cfg = json.loads((run / "config.json").read_text())
    enc = Encoder(SLAMConfig.from_dict(cfg).encoder_model, input_size=cfg["encoder_size"])
    keyframes = set(json.loads((run / "metrics.json").read_text()).get("keyframe_frames", []))
    rng = np.random.default_rng(0)
    n = len(poses)
    held = [i for i in np.linspace(0, n - 1, 4 * args.frames).astype(int) if i not in keyframes][: args.frames]

    cosines = []
    for i in held:
        grid = pca.transform(enc.encode(seq[i].rgb))
        f = m.render(poses[i], K, w, h).features
        gh, gw = grid.shape[:2]
        rows = ((np.arange(gh) + 0.5) * h / gh).astype(int)
        cols = ((np.arange(gw) + 0.5) * w / gw).astype(int)
        a = f[rows][:, cols].reshape(-1, f.shape[-1])
        b = grid.reshape(-1, grid.shape[-1])
        cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-9)
        cosines.append(float(cos.mean()))

    heats, pcts = [], []
    for _ in range(args.pairs):
        ia = int(rng.integers(0, n - 30))
        ib = ia + int(rng.integers(10, 30))
        fa, fb = seq[ia], seq[ib]
        ys, xs = np.nonzero(fa.depth > 0)
        k = int(rng.integers(len(ys)))
        x, y, z = xs[k], ys[k], fa.depth[ys[k], xs[k]]
        p_cam = np.array([(x - K[0, 2]) * z / K[0, 0], (y - K[1, 2]) * z / K[1, 1], z, 1.0])
        p_b = np.linalg.inv(fb.pose) @ (fa.pose @ p_cam)
        if p_b[2] <= 0:
            continue
        u = int(round(K[0, 0] * p_b[0] / p_b[2] + K[0, 2]))
        v = int(round(K[1, 1] * p_b[1] / p_b[2] + K[1, 2]))
        if not (0 <= u < w and 0 <= v < h):
            continue
        q = query_from_pixel(m.render(poses[ia], K, w, h).features, int(x), int(y), radius=2)
        heat = heatmap(m.render(poses[ib], K, w, h).features, q)
        heats.append(float(heat[v, u]))
        pcts.append(float((heat < heat[v, u]).mean() * 100))
    print(f"run {run}: {n} frames, {len(keyframes) or 'unknown'} keyframes")
    print(f"rendered vs encoder features at {len(held)} held-out frames: mean cosine "
          f"{np.mean(cosines):.3f} (min {np.min(cosines):.3f})")
    print(f"by-example queries over {len(heats)} frame pairs 10-30 frames apart: heat at the "
          f"reprojected point {np.mean(heats):.3f} (median percentile {np.median(pcts):.1f}; "
          f"{np.mean(np.array(pcts) >= 90) * 100:.0f}% of pairs in the top 10%)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
