"""`legslam odometry PATH --out traj.txt`: frame-to-frame RGB-D odometry over a sequence.

Each frame is tracked against the previous one (dense point-to-plane + photometric alignment
in the engine) from a constant-velocity prediction. The trajectory is written in TUM format
(`t tx ty tz qx qy qz qw`, camera-to-world), one pose per frame; a frame whose alignment is
"lost" keeps the prediction and is counted, a frame that cannot be read is left out (warned).
Progress goes to stderr; the ATE against the ground truth is printed at the end when the
sequence has one.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from .. import datasets
from ..eval import ate_rmse, write_tum
from ..run_folder import replace_atomically
from ..tracking import Odometry, fitting_levels, odometry_finest_level
from .common import UserError, add_sequence_options, open_sequence, output_file


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="sequence folder or file the dataset loaders read")
    p.add_argument("--out", required=True, help="output trajectory (TUM format)")
    add_sequence_options(p)
    p.add_argument("--finest-level", type=int, default=None,
                   help="finest pyramid level used by the tracker (0 = full resolution)")
    p.add_argument("--levels", type=int, default=None, help="pyramid levels used")
    p.add_argument("--no-motion-prior", action="store_true",
                   help="start each alignment from the previous pose, not a "
                        "constant-velocity prediction")
    p.add_argument("--identity-start", action="store_true",
                   help="start at the identity even if the first frame has a GT pose")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _write(path: Path, stamps, poses) -> None:
    """The trajectory, whole or not at all (none when no frame was tracked)."""
    if poses:
        replace_atomically(path, lambda tmp: write_tum(tmp, stamps, poses))


def run(args: argparse.Namespace) -> int:
    out = output_file(args.out)
    seq = open_sequence(args)
    if out.exists() and Path(seq.path).resolve() in out.resolve().parents:
        raise UserError(f"--out {out} is a file of the input sequence {seq.path}: give another name")
    n = len(seq)
    if n == 0:
        raise UserError(f"no frames in {args.path}")

    try:
        first = seq[0]
    except datasets.DatasetError as e:
        raise UserError(f"cannot read the first frame: {e}")
    # Unless told: the finest level as odometry_finest_level says, and as many levels as the
    # image has room for.
    h, w = first.depth.shape
    finest = args.finest_level
    if finest is None:
        finest = odometry_finest_level(w)
    config = {"finest_level": finest}
    if args.levels is not None:
        config["levels"] = args.levels
        config["iterations"] = [4] * args.levels
    else:
        config["levels"] = fitting_levels(w, h, finest)
    start = first.pose if (first.pose is not None and not args.identity_start) else np.eye(4)
    try:
        odo = Odometry(initial_pose=start, motion_prior=not args.no_motion_prior, **config)
    except ValueError as e:
        raise UserError(str(e))

    stamps, poses, gt, times = [], [], [], []
    lost = 0
    progress = not args.quiet
    tty = sys.stderr.isatty()
    t_start = time.perf_counter()
    skipped = 0
    try:
        for i, f in datasets.each_readable(seq):
            if f is None:  # unreadable: left out of the trajectory, the next frame tracks on
                skipped += 1
                continue
            t0 = time.perf_counter()
            try:
                step = odo.step(f.rgb, f.depth, f.K)
            except ValueError as e:
                raise UserError(f"frame {i}: {e}")
            dt = (time.perf_counter() - t0) * 1e3
            if i > 0:
                times.append(dt)
            if step.lost:
                lost += 1
            stamps.append(f.timestamp)
            poses.append(step.pose)
            gt.append(f.pose)
            if progress and (tty or (i + 1) % 100 == 0 or i + 1 == n):
                med = statistics.median(times) if times else dt
                msg = f"frame {i + 1}/{n}  {dt:6.1f} ms  (median {med:.1f} ms/frame)  lost {lost}"
                print(("\r" + msg) if tty else msg, end="" if tty and i + 1 < n else "\n",
                      file=sys.stderr, flush=True)
    except datasets.DatasetError as e:  # too many unreadable in a row: keep what is done
        _write(out, stamps, poses)
        raise UserError(f"{e}; the trajectory of the frames before is in {out}")
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM: keep what is done
        _write(out, stamps, poses)
        print(f"stopped after {len(poses)} frames: their trajectory is in {out}", file=sys.stderr)
        raise

    _write(out, stamps, poses)
    total = time.perf_counter() - t_start
    med = statistics.median(times) if times else float("nan")
    print(f"{n} frames in {total:.1f} s, median {med:.1f} ms/frame (tracking only), "
          f"{lost} lost, {skipped} unreadable; trajectory written to {args.out}")
    if all(p is not None for p in gt) and len(gt) > 2:
        ate = float(ate_rmse(np.asarray(gt), np.asarray(poses)))
        print(f"ATE RMSE (SE(3)-aligned): {ate * 100:.2f} cm")
    return 0
