"""Tracking benchmark: frame-to-frame RGB-D odometry on a 7-Scenes sequence, legslam's tracker
side by side with Open3D's RGB-D odometry (hybrid term) and Open3D's dense SLAM (frame to a TSDF
model, depth alone) on the same frames in the same run.

Prints, per method: ATE RMSE (SE(3) Umeyama alignment, as `evo_ape --align` computes it),
median and mean ms per frame, and lost frames.

    python benches/bench_tracking.py [PATH] [--max-frames N] [--variants] [--no-open3d]

PATH defaults to ../shared/data/7scenes_tsdf_fusion/data (relative to the repository root).
Open3D (`pip install open3d`) is a benchmark-only dependency; without it its rows are skipped.
Timing covers everything from the decoded frame to the pose (pyramid construction included),
excluding JPEG/PNG decoding, which is shared by both methods.

Measured 2026-11-22 with `python benches/bench_tracking.py --variants` on the 1000-frame
7-Scenes redkitchen snapshot, 2 cores shared with other builds (load average 5-7), so the
times are pessimistic:

    method                             ATE RMSE [cm]  median ms  mean ms  lost
    legslam (default: levels 2-4)               6.51      12.49    13.01     0
    legslam finest_level=1 (levels 1-3)         6.92      33.56    35.02     0
    legslam finest_level=0 (levels 0-3)         7.47     108.40   109.52     0
    legslam geometric only                     11.92      10.51     9.95     0
    open3d hybrid (default option)              7.19     794.18   980.88     0

Open3D's dense SLAM, measured on its own on 2026-11-25 (same 1000 frames, depth registered to
the colour camera as legslam reads them): ATE 3.29 cm, median 173 ms a frame, none lost; with
a 1 cm voxel instead of its example's 3/512 m, 2.87 cm. legslam's SLAM on the same frames
(`benches/bench_slam.py`) ends at 3.69 cm synchronous.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

from legslam import datasets
from legslam.eval import ate_rmse, write_tum
from legslam.tracking import Odometry

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_PATH = os.path.join(ROOT, "..", "shared", "data", "7scenes_tsdf_fusion", "data")


# ---------------------------------------------------------------------------------------------
# Methods


def run_legslam(frames, label, **config):
    odo = Odometry(initial_pose=frames[0].pose, **config)
    poses, times = [], []
    for f in frames:
        t0 = time.perf_counter()
        step = odo.step(f.rgb, f.depth, f.K)
        times.append((time.perf_counter() - t0) * 1e3)
        poses.append(step.pose)
    return label, poses, times[1:], odo.lost_frames


def run_open3d(frames):
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    h, w = frames[0].depth.shape
    K = frames[0].K
    intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = o3d.pipelines.odometry.OdometryOption()
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(f):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(f.rgb), o3d.geometry.Image(f.depth),
            depth_scale=1.0, depth_trunc=option.depth_max, convert_rgb_to_intensity=True,
        )

    pose = frames[0].pose.copy()
    poses, times, lost = [pose.copy()], [], 0
    prev = rgbd(frames[0])
    for f in frames[1:]:
        t0 = time.perf_counter()
        cur = rgbd(f)
        # Open3D returns the transform mapping source (current) points into the target
        # (previous) camera: T_prev_cur.
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            cur, prev, intr, np.eye(4), jac, option
        )
        times.append((time.perf_counter() - t0) * 1e3)
        if ok:
            pose = pose @ T
        else:
            lost += 1
        poses.append(pose.copy())
        prev = cur
    return "open3d hybrid (default option)", poses, times, lost


def run_open3d_dense(frames):
    """Open3D's dense RGB-D SLAM (`t.pipelines.slam`): each frame aligned with depth alone to
    a raycast of the TSDF volume it fuses, with the settings of Open3D's own dense_slam.py
    example (voxel 3/512 m, depth up to 3 m)."""
    import open3d as o3d
    import open3d.core as o3c

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    h, w = frames[0].depth.shape
    dev = o3c.Device("CPU:0")
    intr = o3c.Tensor(np.asarray(frames[0].K, dtype=np.float64))
    depth_scale, depth_min, depth_max, trunc = 1000.0, 0.1, 3.0, 8.0
    model = o3d.t.pipelines.slam.Model(3.0 / 512, 16, 40000, o3c.Tensor(np.eye(4)), dev)
    cur = o3d.t.pipelines.slam.Frame(h, w, intr, dev)
    ray = o3d.t.pipelines.slam.Frame(h, w, intr, dev)
    T = np.eye(4)
    poses, times, lost = [], [], 0
    for i, f in enumerate(frames):
        t0 = time.perf_counter()
        mm = np.nan_to_num(np.rint(f.depth * depth_scale), posinf=0.0).clip(0, 65535)
        cur.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(mm.astype(np.uint16))))
        rgb = o3c.Tensor(np.ascontiguousarray(f.rgb))
        cur.set_data_from_image("color", o3d.t.geometry.Image(rgb))
        if i > 0:
            try:
                r = model.track_frame_to_model(cur, ray, depth_scale, depth_max, 0.07)
                T = T @ r.transformation.numpy()
            except RuntimeError:  # a singular system: the frame keeps the last pose
                lost += 1
        model.update_frame_pose(i, o3c.Tensor(T))
        model.integrate(cur, depth_scale, depth_max, trunc)
        model.synthesize_model_frame(ray, depth_scale, depth_min, depth_max, trunc, False)
        if i > 0:
            times.append((time.perf_counter() - t0) * 1e3)
        poses.append(frames[0].pose @ T)
    return "open3d dense SLAM (TSDF model)", poses, times, lost


# ---------------------------------------------------------------------------------------------


def _parse_config(spec):
    opts = {}
    for item in spec.split(","):
        k, v = item.split("=")
        if v.lower() in ("true", "false"):
            opts[k] = v.lower() == "true"
        elif "/" in v:
            opts[k] = [int(x) for x in v.split("/")]
        else:
            try:
                opts[k] = int(v)
            except ValueError:
                opts[k] = float(v)
    return opts


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path", nargs="?", default=DEFAULT_PATH)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--variants", action="store_true",
                    help="also run our config variants (finest level 1 / 0, geometry only)")
    ap.add_argument("--no-open3d", action="store_true", help="skip the Open3D rows")
    ap.add_argument("--config", action="append", default=[], metavar="K=V,K=V",
                    help="an extra legslam row with these tracker options "
                         "(lists with '/', e.g. iterations=2/4/8); repeatable")
    ap.add_argument("--out", default=None, metavar="DIR",
                    help="write each method's trajectory (TUM format) and the GT into DIR")
    ap.add_argument("--threads", type=int, default=None,
                    help="RAYON_NUM_THREADS for our engine (default: all cores)")
    args = ap.parse_args(argv)
    if args.threads:
        os.environ["RAYON_NUM_THREADS"] = str(args.threads)
    if not os.path.isdir(args.path):
        print(f"no data at {args.path}", file=sys.stderr)
        return 2

    seq = datasets.open(args.path, max_frames=args.max_frames)
    t0 = time.perf_counter()
    frames = [seq[i] for i in range(len(seq))]
    print(f"{len(frames)} frames {frames[0].depth.shape[1]}x{frames[0].depth.shape[0]} from "
          f"{args.path} (decoded in {time.perf_counter() - t0:.1f} s)")
    gt = [f.pose for f in frames]
    if any(p is None for p in gt):
        print("sequence has no ground-truth poses", file=sys.stderr)
        return 2
    try:
        load = os.getloadavg()[0]
        print(f"cpu cores {os.cpu_count()}, load average {load:.2f} at start")
    except OSError:
        pass

    runs = [lambda: run_legslam(frames, "legslam (default: levels 2-4)")]
    if args.variants:
        runs += [
            lambda: run_legslam(frames, "legslam finest_level=1 (levels 1-3)", finest_level=1,
                                levels=3, iterations=[4, 6, 10]),
            lambda: run_legslam(frames, "legslam finest_level=0 (levels 0-3)", finest_level=0,
                                levels=4, iterations=[3, 4, 6, 10]),
            lambda: run_legslam(frames, "legslam geometric only", photometric_weight=0.0),
        ]
    for spec in args.config:
        opts = _parse_config(spec)
        runs.append(lambda spec=spec, opts=opts: run_legslam(frames, f"legslam {spec}", **opts))
    if not args.no_open3d:
        try:
            import open3d  # noqa: F401

            runs.append(lambda: run_open3d(frames))
            runs.append(lambda: run_open3d_dense(frames))
        except ImportError:
            print("open3d not installed: its rows are skipped (pip install open3d)")

    rows = []
    stamps = [f.timestamp for f in frames]
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        write_tum(os.path.join(args.out, "groundtruth.txt"), stamps, gt)
    for run in runs:
        label, poses, times, lost = run()
        ate = float(ate_rmse(np.asarray(gt), np.asarray(poses)))
        if args.out:
            name = "".join(c if c.isalnum() or c in "=._-" else "_" for c in label)
            write_tum(os.path.join(args.out, name + ".txt"), stamps, poses)
        rows.append((label, ate, statistics.median(times), statistics.fmean(times), lost))
        print(f"  done: {label}: ATE {ate * 100:.2f} cm, median {rows[-1][2]:.2f} ms/frame",
              flush=True)

    print()
    print(f"{'method':<34} {'ATE RMSE [cm]':>13} {'median ms':>10} {'mean ms':>8} {'lost':>5}")
    for label, ate, med, mean, lost in rows:
        print(f"{label:<34} {ate * 100:>13.2f} {med:>10.2f} {mean:>8.2f} {lost:>5}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
