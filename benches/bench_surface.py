"""The fused surface's cost per frame (legslam.slam.surface): a SLAM run fuses tracked frames
at the tracking size and ray-casts the surface from their poses, near the frame's depth (the
engine's `raycast_near`, the frame's holes in cells). Fuses the frames of an RGB-D sequence at
their ground-truth poses and times, per frame, the fusion, the ray-cast begun near the frame's
depth (what SLAM runs) and the full ray-cast from the camera (the baseline, in the same
process, alternating); medians and their ratio, and the volume's memory at the end.

    .venv/bin/python benches/bench_surface.py [SEQUENCE] [--frames 300] [--width 320]
        [--voxel 0.01] [--truncation 0.04] [--hole-cell 2]

SEQUENCE: any folder `legslam run` reads (default: the 7-Scenes sequence in ../shared/data).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from legslam import _core, datasets
from legslam.slam import SLAMConfig
from legslam.slam.surface import HOLE_CELL, MAX_WEIGHT

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "7scenes_tsdf_fusion" / "data"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path", nargs="?", default=str(DATA))
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--width", type=int, default=SLAMConfig.track_width, help="tracking width")
    ap.add_argument("--voxel", type=float, default=SLAMConfig.surface_voxel, help="voxel edge (m)")
    ap.add_argument("--hole-cell", type=int, default=HOLE_CELL,
                    help="pixels (a side) whose holes one ray serves (default: what SLAM uses)")
    ap.add_argument("--truncation", type=float, default=SLAMConfig.surface_truncation,
                    help="truncation distance (m)")
    args = ap.parse_args(argv)
    if not Path(args.path).exists():
        print(f"no sequence at {args.path}", file=sys.stderr)
        return 2
    seq = datasets.open(args.path, max_frames=args.frames)
    f0 = seq[0]
    h, w = f0.depth.shape
    c = SLAMConfig()
    K, tw, th = _core.scaled_intrinsics(f0.K, w, h, min(1.0, args.width / w))
    tsdf = _core.TsdfCore(args.voxel, args.truncation, MAX_WEIGHT, c.mapper.depth_min,
                          c.mapper.depth_max)
    fuse, near, full = [], [], []
    for i in range(len(seq)):
        f = seq[i]
        if f.pose is None:
            continue
        depth = cv2.resize(f.depth, (tw, th), interpolation=cv2.INTER_NEAREST)
        t0 = time.perf_counter()
        tsdf.integrate(depth, K, f.pose)
        t1 = time.perf_counter()
        # Alternating which ray-cast goes first, so that neither always meets a warm cache.
        casts = [("near", lambda: tsdf.raycast(K, tw, th, f.pose, depth, args.hole_cell)),
                 ("full", lambda: tsdf.raycast(K, tw, th, f.pose))]
        for name, cast in casts[:: 1 if i % 2 else -1]:
            a = time.perf_counter()
            cast()
            (near if name == "near" else full).append(time.perf_counter() - a)
        fuse.append(t1 - t0)
    ms = lambda v: 1e3 * float(np.median(v))  # noqa: E731
    print(f"{len(fuse)} frames of {args.path} at {tw}x{th}, voxel {args.voxel} m, "
          f"truncation {args.truncation} m, holes in cells of {args.hole_cell}")
    print(f"  fuse                      {ms(fuse):7.1f} ms (median)")
    print(f"  ray-cast near the depth   {ms(near):7.1f} ms (x{ms(full) / ms(near):.2f} faster)")
    print(f"  ray-cast from the camera  {ms(full):7.1f} ms (baseline)")
    print(f"  volume: {tsdf.blocks} blocks, {tsdf.memory_bytes / 1e6:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
