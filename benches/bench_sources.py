"""The user's own recordings against the folder they were made from: the 7-Scenes sequence in
../shared/data written as a ROS1 bag (raw rgb8 colour; depth as the Kinect's depth camera
saw it, 16UC1 with its own CameraInfo and the colour-from-depth transform in /tf_static, so
that the bag reader registers it as the folder reader does) and as a Stray Scanner export
(colour as an mp4v video, depth registered at 640x480 in millimetre PNGs, confidence 2,
odometry.csv from the ground truth as the app writes it).

Prints what reading a frame costs in each (median ms, one process, the three read in turn
frame by frame), what opening costs, how far the video's colour is from the folder's, and,
unless --no-runs, runs `legslam run` on the three (same frames, no language features) and
compares trajectories and figures.

    python benches/bench_sources.py [--max-frames 200] [--out /tmp/legslam-bench-sources] [--no-runs]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared" / "data" / "7scenes_tsdf_fusion" / "data"
sys.path.insert(0, str(ROOT / "tests"))  # the recorders' writers (tests/recordings.py)


def write_recordings(folder: Path, out: Path, n: int) -> tuple[Path, Path]:
    import cv2

    from legslam.datasets import open as open_dataset
    from legslam.datasets import sevenscenes as S
    from recordings import STAMP0, Shot, write_bag, write_stray

    seq = open_dataset(folder, max_frames=n)
    shots, raw_depth = [], []
    for k in range(len(seq)):
        f = seq[k]
        shots.append(Shot(f.rgb, f.depth, STAMP0 + f.timestamp, f.pose))
        raw = cv2.imread(str(folder / f"frame-{f.index:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
        raw_depth.append(np.where(raw == 65535, 0, raw).astype(np.float32) / 1000.0)
    bag = write_bag(out / "7scenes.bag", shots, seq.K,
                    depth_camera=(S.DEFAULT_K, raw_depth, np.eye(4), S.COLOR_FROM_DEPTH))
    confidence = [np.full(s.depth.shape, 2, np.uint8) for s in shots]
    stray = write_stray(out / "7scenes-stray", shots, seq.K, shots, confidence)
    return bag, stray


def reading_costs(paths: dict, n: int) -> dict:
    from legslam.datasets import open as open_dataset

    opened, open_s = {}, {}
    for name, p in paths.items():
        t0 = time.perf_counter()
        opened[name] = open_dataset(p, max_frames=n)
        open_s[name] = time.perf_counter() - t0
    ms = {name: [] for name in paths}
    frames = {}
    for k in range(n):
        for name, seq in opened.items():
            t0 = time.perf_counter()
            frames[name] = seq[k]
            ms[name].append(1e3 * (time.perf_counter() - t0))
        f, b, s = frames["folder"], frames["bag"], frames["stray"]
        assert np.array_equal(f.rgb, b.rgb), f"frame {k}: the bag's colour is not the folder's"
        assert np.abs(f.depth - b.depth).max() <= 0.0011, f"frame {k}: the bag's depth is not the folder's"
        ms.setdefault("video_psnr", []).append(_psnr(f.rgb, s.rgb))
    return {"open_s": open_s, "median_ms": {k: statistics.median(v) for k, v in ms.items() if k in paths},
            "video_psnr_db": statistics.mean(ms["video_psnr"])}


def _psnr(a, b) -> float:
    mse = np.mean((a.astype(np.float64) - b) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse)) if mse else float("inf")


def run(path: Path, out: Path, n: int) -> None:
    cmd = [str(ROOT / ".venv" / "bin" / "legslam"), "run", str(path), "--out", str(out), "--max-frames", str(n),
           "--no-features", "--quiet", "--overwrite"]
    print("$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def compare(folder: Path, runs: dict) -> None:
    """The runs' figures, ATE against the folder's ground truth (the bag has none of its own),
    and how far each trajectory is from the folder run's."""
    from legslam.datasets import open as open_dataset
    from legslam.eval import ate_rmse, read_tum

    poses = {name: read_tum(out / "trajectory.txt")[1] for name, out in runs.items()}
    truth = open_dataset(folder, max_frames=len(poses["folder"])).gt_trajectory()[1]
    for name, out in runs.items():
        m, t = (json.loads((out / f).read_text()) for f in ("metrics.json", "timings.json"))
        e = m["every_5"]
        dt = np.linalg.norm(poses[name][:, :3, 3] - poses["folder"][:, :3, 3], axis=1).max()
        print(f"{name:7s} ATE {100 * ate_rmse(truth, poses[name]):.2f} cm  PSNR {e['psnr']:.2f} dB  SSIM "
              f"{e['ssim']:.3f}  depth L1 {e['depth_l1_cm']:.2f} cm  keyframes {m['keyframes']}  gaussians "
              f"{m['gaussians']}  {t['fps']:.2f} fps  max position difference from the folder's run {100 * dt:.3f} cm")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", nargs="?", default=str(DEFAULT))
    ap.add_argument("--max-frames", type=int, default=200)
    ap.add_argument("--out", default="/tmp/legslam-bench-sources")
    ap.add_argument("--no-runs", action="store_true")
    args = ap.parse_args()
    folder = Path(args.path)
    if not folder.exists():
        print(f"no sequence at {folder} (the shared data folder beside the repository)")
        return 1
    out = Path(args.out)
    shutil.rmtree(out / "7scenes.bag", ignore_errors=True)
    shutil.rmtree(out / "7scenes-stray", ignore_errors=True)
    (out / "7scenes.bag").unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    n = args.max_frames
    t0 = time.perf_counter()
    bag, stray = write_recordings(folder, out, n)
    print(f"wrote {bag} ({bag.stat().st_size / 1e6:.0f} MB) and {stray} in {time.perf_counter() - t0:.0f} s")
    costs = reading_costs({"folder": folder, "bag": bag, "stray": stray}, n)
    print(f"reading a frame, median over {n} (ms): " + "  ".join(f"{k} {v:.1f}" for k, v in costs["median_ms"].items()))
    print("opening (s): " + "  ".join(f"{k} {v:.2f}" for k, v in costs["open_s"].items()))
    print(f"video colour against the folder's: {costs['video_psnr_db']:.1f} dB PSNR (mp4v)")
    if args.no_runs:
        return 0
    runs = {name: out / f"run-{name}" for name in ("folder", "bag", "stray")}
    for name, p in (("folder", folder), ("bag", bag), ("stray", stray)):
        run(p, runs[name], n)
    compare(folder, runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
