"""`legslam render RUN --trajectory FILE`: colour, depth and feature views of a saved map along
a camera path, as numbered PNGs (a video-friendly sequence)."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from ..map import GaussianMap
from ..render import feature_basis, feature_rgb
from ..run_folder import CAMERA, MAP, TRAJECTORY, read_camera, read_trajectory
from .common import UserError, at_least, available_memory, output_dir


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a `legslam run` output folder, or a map .ply (then give --intrinsics and --size)")
    p.add_argument("--trajectory", default=None,
                   help="TUM trajectory of camera-to-world poses (default: the run's trajectory.txt)")
    p.add_argument("--intrinsics", default=None, help="fx,fy,cx,cy (default: the run's camera.json)")
    p.add_argument("--size", default=None, help="WIDTHxHEIGHT (default: the run's camera.json)")
    p.add_argument("--every", type=int, default=1, help="render every N-th pose")
    p.add_argument("--no-features", action="store_true", help="skip the feature views")
    p.add_argument("--out", default=None, help="output folder (default: RUN/views)")


def _camera(args, run_dir: Path) -> tuple:
    """(K, width, height) from --intrinsics and --size, else from the run's camera.json."""
    if args.intrinsics and args.size:
        try:
            fx, fy, cx, cy = (float(v) for v in args.intrinsics.split(","))
            width, height = (int(v) for v in args.size.lower().split("x"))
        except ValueError as e:
            raise UserError(f"--intrinsics takes fx,fy,cx,cy and --size WIDTHxHEIGHT ({e})") from e
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), width, height
    if not (run_dir / CAMERA).is_file():
        raise UserError(f"no {CAMERA} beside the map in {run_dir}: give --intrinsics fx,fy,cx,cy "
                        "and --size WxH")
    return read_camera(run_dir / CAMERA)[:3]


def _check_memory(width: int, height: int, channels: int) -> None:
    """Refuses a view that would not fit in memory: the engine's images (colour, depth, alpha,
    features, per-pixel state) and the PNGs made of them."""
    need = width * height * (4 * (7 + channels) + 16)
    free = available_memory()
    if need > free:
        raise UserError(f"a {width}x{height} view needs about {need / 2**30:.1f} GiB, "
                        f"{free / 2**30:.1f} GiB are available: give a smaller --size")


def run(args) -> int:
    src = Path(args.run)
    map_path = src / MAP if src.is_dir() else src
    if not map_path.is_file():
        raise UserError(f"no map at {map_path}")
    run_dir = map_path.parent
    at_least("--every", args.every)
    try:
        K, width, height = _camera(args, run_dir)
        _, poses = read_trajectory(Path(args.trajectory) if args.trajectory else run_dir / TRAJECTORY)
        m = GaussianMap.load(map_path)
    except (OSError, ValueError) as e:  # RunFolderError is a ValueError
        raise UserError(str(e)) from e
    features = m.num_features > 0 and not args.no_features
    _check_memory(width, height, m.num_features if features else 0)
    out = output_dir(Path(args.out) if args.out else run_dir / "views")
    basis = None
    picked = range(0, len(poses), args.every)
    for n, i in enumerate(picked):
        r = m.render(poses[i], K, width, height, features=features)
        color = (np.clip(r.color, 0, 1) * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(out / f"{n:06d}_color.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        depth_mm = np.clip(r.depth / np.maximum(r.alpha, 1e-6) * 1000, 0, 65535)
        cv2.imwrite(str(out / f"{n:06d}_depth.png"), np.where(r.alpha > 0.5, depth_mm, 0).astype(np.uint16))
        if features:
            if basis is None:  # one colour basis for the whole sequence, so colours stay put
                basis = feature_basis(r.features)
            rgb = feature_rgb(r.features, basis)
            cv2.imwrite(str(out / f"{n:06d}_features.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        print(f"\rview {n + 1}/{len(picked)}", end="", flush=True)
    print(f"\nwrote {len(picked)} views to {out}/ (colour PNG, depth PNG in mm"
          f"{', features as colour' if features else ''})")
    return 0
