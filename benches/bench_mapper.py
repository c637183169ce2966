"""Mapping iterations through the Python extension, as SLAM runs them: a map grown from every
12th frame of a sequence (default: the 7-Scenes one in ../shared/data) at its ground-truth pose,
with SLAM's mapper options (`SLAMConfig`, K = 64 features on a smooth random grid) and 10
iterations after each keyframe; then `MapperCore.train(1)` timed, median over `--iters`.

`cargo bench --bench mapper` times the engine's own binary; a change to the engine can gain
there and lose here, on a map grown the same way (2026-11-27: a shorter exponential, 13% faster
there and 9% slower here), so engine changes are measured here too, the old and the new build
alternating (`PYTHONPATH=OLD/python` runs another checkout's build).

`--bench-map` grows the engine bench's map instead (7-Scenes only): its options (the engine's
defaults with 4 levels, SH degree 3, grow stride 2) and the depth as the sensor wrote it, not
registered to the colour camera, as that bench reads it.

    python benches/bench_mapper.py [SEQUENCE] [--iters N] [--every N] [--bench-map]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared" / "data" / "7scenes_tsdf_fusion" / "data"


def feature_grid(rng: np.random.Generator, k: int) -> np.ndarray:
    """A smooth unit-norm 16x16 grid of `k` channels: random values on a 4x4 grid, upsampled."""
    coarse = rng.normal(size=(4, 4, k)).astype(np.float32)
    grid = np.kron(coarse, np.ones((4, 4, 1), np.float32))
    return grid / np.linalg.norm(grid, axis=2, keepdims=True)


#: The options `cargo bench --bench mapper` grows its map with (beside the engine's defaults).
BENCH_OPTIONS = {"levels": 4, "sh_degree": 3, "num_features": 64, "grow_stride": 2}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", default=str(DEFAULT))
    ap.add_argument("--iters", type=int, default=40, help="timed iterations")
    ap.add_argument("--every", type=int, default=12, help="every this many frames a keyframe")
    ap.add_argument("--bench-map", action="store_true",
                    help="the map `cargo bench --bench mapper` grows (7-Scenes only)")
    args = ap.parse_args()
    if not Path(args.sequence).exists():
        print(f"no sequence at {args.sequence} (the shared data folder beside the repository)")
        return 1
    from legslam import _core
    from legslam.datasets import open as open_dataset
    from legslam.datasets import sevenscenes
    from legslam.slam import SLAMConfig

    cfg = SLAMConfig()
    # The bench reads 7-Scenes as the sensor wrote it: given the depth camera's intrinsics, the
    # loader takes the folder as registered and leaves depth and poses the depth camera's.
    ds = open_dataset(args.sequence, stride=args.every,
                      intrinsics=sevenscenes.DEFAULT_K if args.bench_map else None)
    if args.bench_map and ds.format != sevenscenes.SevenScenesSequence.format:
        print(f"--bench-map grows the engine bench's 7-Scenes map; {args.sequence} is {ds.format}")
        return 1
    options = BENCH_OPTIONS if args.bench_map else cfg.mapper_options(ds[0].depth.shape[1])
    mapper = _core.MapperCore(options, threads=2)
    rng = np.random.default_rng(1)
    began = time.perf_counter()
    for f in ds:
        if f.pose is None:
            continue
        kf, _ = mapper.add_keyframe(f.rgb.astype(np.float32) / 255, f.depth, f.K, f.pose)
        mapper.set_features(kf, feature_grid(rng, cfg.feature_dim))
        mapper.train(10)
    grown = time.perf_counter() - began
    times = []
    for _ in range(args.iters):
        t0 = time.perf_counter()
        mapper.train(1)
        times.append(1e3 * (time.perf_counter() - t0))
    print(f"{_core.__file__}: {mapper.num_gaussians} Gaussians from {mapper.num_keyframes} keyframes "
          f"(grown in {grown:.0f} s); train(1) median {statistics.median(times):.1f} ms over {len(times)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
