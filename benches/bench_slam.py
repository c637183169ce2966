"""SLAM benchmark on a real sequence (default: the 1000-frame 7-Scenes sequence in
../shared/data, 640x480): the whole pipeline with language features, as `legslam run` does it,
and the tracker's own frame-to-frame odometry on the same frames in the same process.

Prints ATE RMSE (all frames, SE(3)-aligned, as `evo_ape -a`) and the median frame-to-frame
relative pose error of SLAM and of the odometry, how well the frames agree with each other
under the ground truth's poses and under SLAM's (`legslam.eval.view_agreement`), the same stretch
by stretch beside SLAM's error there (`--stretch`), relocalisations, loops
closed (time per closure) and covisibility edges, PSNR / SSIM / depth L1 of the
final map rendered at the estimated pose of every 5th frame and of every keyframe, the number
of Gaussians, peak memory, frames per second and the per-stage time table.

    python benches/bench_slam.py [PATH] [--max-frames N] [--stride S] [--no-features] [--out DIR]
                                 [--config FILE] [--pace [SPEED]] [--stretch FRAMES]

`--pace` plays the frames as their camera delivered them (`legslam run --pace`): with
`mapping_thread` the map then gets what a live camera's gaps between frames leave.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared" / "data" / "7scenes_tsdf_fusion" / "data"


def odometry(seq) -> tuple[np.ndarray, float]:
    """Poses and median ms/frame of the tracker alone, frame to frame, as `legslam odometry`
    tracks (its pyramid for the frame size)."""
    from legslam.tracking import Odometry, fitting_levels, odometry_finest_level

    h, w = seq[0].depth.shape
    finest = odometry_finest_level(w)
    odo = Odometry(finest_level=finest, levels=fitting_levels(w, h, finest))
    poses, times = [], []
    for i in range(len(seq)):
        f = seq[i]
        t0 = time.perf_counter()
        poses.append(odo.step(f.rgb, f.depth, f.K).pose)
        times.append(1e3 * (time.perf_counter() - t0))
    return np.stack(poses), float(np.median(times[1:]))


def by_stretch(seq, gt: np.ndarray, est: np.ndarray, length: int) -> list:
    """Per stretch of `length` frames: the estimate's mean error after the whole run's
    alignment, and how well the frames within the stretch agree under either trajectory
    (`view_agreement`, every 3rd frame). Where a pseudo ground truth is the one in error, the
    stretch it errs on shows the estimate both far from it and agreeing better with the frames."""
    from legslam.eval import ate, view_agreement

    errors = ate(gt, est)["errors"]
    bounds = [*range(0, len(seq), length), len(seq)]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] < length // 2:
        del bounds[-2]  # a short last stretch joins the one before
    rows = []
    for a, b in zip(bounds, bounds[1:]):
        agree = view_agreement(seq, {"gt": gt, "slam": est}, every=3, pairs=60, frames=range(a, b))
        if len(agree) < 2:
            continue
        rows.append({"frames": [a, b], "error_cm": float(100 * errors[a:b].mean()),
                     "pairs": agree["gt"][0], "ground_truth": list(agree["gt"][1:]),
                     "slam": list(agree["slam"][1:])})
    return rows


def median_rpe_cm(gt: np.ndarray, est: np.ndarray) -> float:
    """Median translation error (cm) of consecutive frames' relative poses."""
    from legslam.eval import rpe

    return 100 * rpe(gt, est, delta=1, all_pairs=True)["trans"]["median"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", nargs="?", default=str(DEFAULT))
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--stretch", type=int, default=100,
                    help="frames per stretch of the per-stretch error and agreement table")
    ap.add_argument("--no-features", action="store_true")
    ap.add_argument("--config", default=None, help="SLAM config file (.toml/.json)")
    ap.add_argument("--out", default="/tmp/legslam-bench-slam")
    ap.add_argument("--pace", type=float, nargs="?", const=1.0, default=None, metavar="SPEED",
                    help="hand frames over no faster than SPEED times their timestamps' rate")
    args = ap.parse_args()
    if not Path(args.path).exists():
        print(f"no sequence at {args.path} (the shared data folder beside the repository)")
        return 1
    from legslam.cli.progress import Progress
    from legslam.datasets import open as open_dataset
    from legslam.eval import view_agreement
    from legslam.pipeline import run
    from legslam.slam import SLAMConfig

    seq = open_dataset(args.path, stride=args.stride, max_frames=args.max_frames)
    overrides = {"features": False} if args.no_features else {}
    cfg = SLAMConfig.from_file(args.config, **overrides) if args.config else SLAMConfig(**overrides)
    print(f"{args.path}: {len(seq)} frames, {os.cpu_count()} cores, features {cfg.features}")
    result = run(seq, args.out, cfg, progress=Progress(len(seq)), pace=args.pace)
    m, t = result["metrics"], result["timings"]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    from legslam.eval import ate_rmse, read_tum

    gt = np.stack([seq[i].pose for i in range(len(seq))])
    odo_poses, odo_ms = odometry(seq)
    odo_ate = ate_rmse(gt, odo_poses)
    slam_poses = read_tum(Path(args.out, "trajectory.txt"))[1]
    rpe_slam, rpe_odo = median_rpe_cm(gt, slam_poses), median_rpe_cm(gt, odo_poses)
    relocs, loops = m.get("relocalisations", []), m.get("loop_closures", [])

    print("\n| | value |\n|---|---|")
    print(f"| frames / keyframes / lost | {m['frames']} / {m['keyframes']} / {m['lost_frames']} |")
    reasons = Counter(m.get("keyframe_reasons", []))
    print("| keyframes made for: " + ", ".join(f"{r} {n}" for r, n in reasons.items()) + " |")
    age = m.get("surface_reference_age")
    if age and age["mean"] is not None:
        counts = ", ".join(f"{a}: {n}" for a, n in age["frames"].items())
        print(f"| frames tracked against a fused-surface reference this many frames old | mean {age['mean']:.2f} ({counts}) |")
    print(f"| ATE RMSE, SLAM (all frames, SE(3)-aligned) | {m['ate_rmse_cm']:.2f} cm |")
    print(f"| ATE RMSE, tracker frame-to-frame odometry | {100 * odo_ate:.2f} cm ({odo_ms:.1f} ms/frame median) |")
    print(f"| frame-to-frame RPE median, SLAM / odometry | {rpe_slam:.3f} / {rpe_odo:.3f} cm |")
    agreement = view_agreement(seq, {"ground truth": gt, "SLAM": slam_poses})
    for name, (n, depth_cm, colour) in agreement.items():
        print(f"| frames' agreement under the {name} poses ({n} pairs): depth / colour (median) | "
              f"{depth_cm:.2f} cm / {colour:.1f} levels |")
    stretches = by_stretch(seq, gt, slam_poses, args.stretch)
    after = ", ".join(f"{r['frame']}: {r['lost_frames']}" for r in relocs)
    print(f"| relocalisations (frame: lost frames before) | {len(relocs)} ({after}) |")
    loop_ms = [e["ms"] for e in loops]
    held = sum(e["dropped_at_frame"] is None for e in loops)
    print(f"| loops closed (holding at the end) / rejected, ms per closure (median) | {len(loops)} "
          f"({held}) / {len(m.get('rejected_loops', []))}, {np.median(loop_ms) if loop_ms else 0:.0f} ms |")
    if "covisibility_edges" in m:
        print(f"| covisibility edges kept / rejected | {m['covisibility_edges']} / "
              f"{len(m['rejected_covisibility_edges'])} |")
    print(f"| places kept (keyframes' descriptors, keypoints, views) | {m.get('place_memory_mb', 0):.1f} MB |")
    for name, label in (("every_5", "every 5th frame"), ("at_keyframes", "keyframes")):
        v = m[name]
        print(f"| map at {label} ({v['count']} views): PSNR / SSIM / depth L1 | "
              f"{v['psnr']:.2f} dB / {v['ssim']:.3f} / {v['depth_l1_cm']:.2f} cm |")
        if "psnr_exposed" in v:
            print(f"| map at {label}, under each frame's keyframe exposure: PSNR | "
                  f"{v['psnr_exposed']:.2f} dB |")
    print(f"| Gaussians | {m['gaussians']} |")
    print(f"| peak memory (RSS) | {peak_mb:.0f} MB |")
    print(f"| frames per second, whole pipeline | {t['fps']:.2f} |")
    print(f"| frames per second while frames come in (before the final iterations) | {t['fps_live']:.2f} |")
    if "playback" in t:
        p = t["playback"]
        print(f"| played at the recorded pace x {p['speed']:g}: frames late (after the next was due), "
              f"latest | {p['late_frames']}, {p['max_lag_s']:.2f} s |")
    its = t["mapping_iterations"]
    print(f"| mapping iterations while frames came in / final | {its['while_frames_came_in']} / {its['final']} |")
    print(f"\n| frames | SLAM's error (mean, whole-run alignment) | agreement under the ground truth "
          f"(pairs): depth / colour | under SLAM |\n|---|---|---|---|")
    for r in stretches:
        print(f"| {r['frames'][0]}-{r['frames'][1] - 1} | {r['error_cm']:.2f} cm | ({r['pairs']}) "
              f"{r['ground_truth'][0]:.2f} cm / {r['ground_truth'][1]:.1f} | "
              f"{r['slam'][0]:.2f} cm / {r['slam'][1]:.1f} |")
    print("\n| stage | mean ms | median ms | p95 ms | max ms | total s |\n|---|---|---|---|---|---|")
    for k, v in t.items():
        if isinstance(v, dict) and "mean_ms" in v:
            print(f"| {k} | {v['mean_ms']:.1f} | {v['median_ms']:.1f} | {v['p95_ms']:.1f} | "
                  f"{v['max_ms']:.1f} | {v['total_s']:.1f} |")
        elif isinstance(v, dict) and "total_s" in v:
            print(f"| {k} | | | | | {v['total_s']:.1f} |")
    Path(args.out, "bench.json").write_text(json.dumps(
        {"metrics": m, "timings": t, "odometry_ate_m": odo_ate, "odometry_ms": odo_ms,
         "rpe_median_cm": {"slam": rpe_slam, "odometry": rpe_odo},
         "view_agreement": {k: {"pairs": n, "depth_cm": d, "colour_levels": c}
                            for k, (n, d, c) in agreement.items()},
         "stretches": stretches, "peak_mb": peak_mb}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
