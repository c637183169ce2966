"""`legslam eval RUN`: a run's trajectory and map against the sequence's ground truth: ATE,
RPE, PSNR / SSIM / depth L1 of the map rendered at estimated poses; a table and eval.json."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a `legslam run` output folder")
    p.add_argument("--sequence", default=None, help="the input sequence (default: as recorded in camera.json)")
    p.add_argument("--format", default="auto")
    p.add_argument("--every", type=int, default=5, help="evaluate the map at every N-th frame")


def _open_at_run_size(path, fmt: str, width: int, height: int):
    """The sequence at the run's image size. camera.json records only the size a run worked
    at, so a run made with --downscale F is matched by recovering F from it."""
    from .cli import UserError
    from .datasets import DatasetError, open as open_dataset

    try:
        seq = open_dataset(path, format=fmt)
        f = max(1, seq.width // width)
        if f > 1 and (seq.width // f, seq.height // f) == (width, height):
            seq = open_dataset(path, format=fmt, downscale=f)
    except (DatasetError, FileNotFoundError) as e:
        raise UserError(str(e)) from e
    if (seq.width, seq.height) != (width, height):
        raise UserError(f"the run's images are {width}x{height} but {path}'s are {seq.width}x{seq.height}, "
                        "not an integer downscale of them (a different sequence? give --sequence)")
    return seq


def run(args) -> int:
    from .cli import UserError
    from .eval import ate, depth_l1_cm, psnr, read_tum, rpe, ssim
    from .map import GaussianMap

    run_dir = Path(args.run)
    for name in ("trajectory.txt", "map.ply", "camera.json"):
        if not (run_dir / name).is_file():
            raise UserError(f"{run_dir} has no {name}: give a `legslam run` output folder")
    if args.every < 1:
        raise UserError(f"--every must be at least 1, got {args.every}")
    cam = json.loads((run_dir / "camera.json").read_text())
    seq_path = args.sequence or cam.get("sequence")
    if not seq_path:
        raise UserError("the run does not record its sequence: give --sequence PATH")
    K, w, h = np.array(cam["K"]), cam["width"], cam["height"]
    seq = _open_at_run_size(seq_path, args.format, w, h)
    _, poses = read_tum(run_dir / "trajectory.txt")
    if len(poses) > len(seq):
        raise UserError(f"the trajectory has {len(poses)} poses but {seq_path} only {len(seq)} frames "
                        "(was the run made with --stride or a different sequence?)")
    report: dict = {"frames": len(poses)}
    gt = [seq[i].pose for i in range(len(poses))]
    if all(g is not None for g in gt):
        a = ate(np.stack(gt), poses)
        r = rpe(np.stack(gt), poses)
        report.update(ate_rmse_cm=100 * a["rmse"], ate_mean_cm=100 * a["mean"],
                      rpe_trans_rmse_cm=100 * r["trans"]["rmse"], rpe_rot_rmse_deg=r["rot"]["rmse"])
    m = GaussianMap.load(run_dir / "map.ply")
    vals = {"psnr": [], "ssim": [], "depth_l1_cm": []}
    for i in range(0, len(poses), args.every):
        f = seq[i]
        out = m.render(poses[i], K, w, h, features=False)
        color = np.clip(out.color, 0, 1)
        target = f.rgb.astype(np.float32) / 255
        vals["psnr"].append(psnr(color, target, data_range=1.0))
        vals["ssim"].append(ssim(color, target, data_range=1.0))
        vals["depth_l1_cm"].append(depth_l1_cm(out.depth, f.depth))
    report.update({k: float(np.mean(v)) for k, v in vals.items()}, views=len(vals["psnr"]))
    report["gaussians"] = len(m)
    print("| metric | value |\n|---|---|")
    for k, v in report.items():
        print(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |")
    (run_dir / "eval.json").write_text(json.dumps(report, indent=2))
    print(f"saved {run_dir / 'eval.json'}")
    return 0
