"""`legslam query RUN ...`: heat maps and masks of text or by-example queries on a saved map,
rendered at any frame's estimated pose (or a given pose)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import cv2
import numpy as np

from ..query import heatmap, mask, query_from_pixel, save_overlay, segment
from ..run_folder import RunFolder
from .common import UserError, open_run, output_dir
from .text_model import add_text_model_options, run_text_queries


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a `legslam run` output folder (map.ply, trajectory.txt, camera.json)")
    p.add_argument("texts", nargs="*", help='text queries, e.g. "chair" "plant" (need the text model)')
    p.add_argument("--frame", type=int, default=0, help="show the queries at this frame's pose")
    p.add_argument("--pose", default=None, help="a 4x4 camera-to-world matrix (text file) instead of --frame")
    p.add_argument("--example", action="append", default=[], metavar="N:X,Y",
                   help="query by example: the feature rendered at pixel X,Y of frame N")
    p.add_argument("--labels", default=None, help="comma-separated labels: a segmentation image")
    p.add_argument("--threshold", type=float, default=0.7, help="cosine similarity of the mask (default 0.7)")
    add_text_model_options(p)
    p.add_argument("--out", default=None, help="output folder (default: RUN/queries)")


def _render(run: RunFolder, pose):
    return run.map.render(pose, run.K, run.width, run.height, features=True)


def _pose(run: RunFolder, frame: int) -> np.ndarray:
    if not 0 <= frame < len(run.poses):
        raise UserError(f"frame {frame} is out of range: the run has {len(run.poses)} frames")
    return run.poses[frame]


def _parse_example(text: str) -> tuple[int, int, int]:
    m = re.fullmatch(r"(\d+):(\d+),(\d+)", text.strip())
    if not m:
        raise UserError(f"--example takes N:X,Y (frame, pixel), got {text!r}")
    return int(m[1]), int(m[2]), int(m[3])


def _text_queries(run: RunFolder, labels: list[str], args) -> np.ndarray:
    return run_text_queries(run, labels, args,
                            hint=" Query by example (--example N:X,Y) works without it.")


def _legend_image(labels_img: np.ndarray, names: list[str], rgb: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(0)
    colours = rng.integers(40, 255, (len(names), 3)).astype(np.uint8)
    seg = rgb.copy()
    hit = labels_img >= 0
    seg[hit] = (0.4 * rgb[hit] + 0.6 * colours[labels_img[hit]]).astype(np.uint8)
    legend = np.full((rgb.shape[0], 160, 3), 255, np.uint8)
    for i, name in enumerate(names):
        y = 20 + 22 * i
        cv2.rectangle(legend, (8, y - 12), (24, y + 4), colours[i].tolist(), -1)
        cv2.putText(legend, name[:18], (30, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return np.concatenate([seg, legend], axis=1)


def run(args) -> int:
    run_dir = Path(args.run)
    r = open_run(run_dir)
    if r.map.num_features == 0:
        raise UserError(f"{run_dir / 'map.ply'} has no language features (run without --no-features)")
    if args.pose:
        try:
            pose = np.loadtxt(args.pose).reshape(4, 4)
        except (OSError, ValueError) as e:
            raise UserError(f"--pose {args.pose}: not a readable 4x4 matrix ({e})") from e
        where = "pose"
    else:
        pose = _pose(r, args.frame)
        where = f"frame{args.frame:06d}"
    if not (args.texts or args.example or args.labels):
        raise UserError("nothing to query: give text queries, --example N:X,Y or --labels a,b,c")
    out = output_dir(Path(args.out) if args.out else run_dir / "queries")
    view = _render(r, pose)
    rgb = (np.clip(view.color, 0, 1) * 255).astype(np.uint8)

    queries: list[tuple[str, np.ndarray]] = []
    for ex in args.example:
        n, x, y = _parse_example(ex)
        if not (0 <= x < r.width and 0 <= y < r.height):
            raise UserError(f"--example pixel {x},{y} is outside the {r.width}x{r.height} image")
        src = _render(r, _pose(r, n))
        queries.append((f"example_{n}_{x}_{y}", query_from_pixel(src.features, x, y, radius=2)))
    if args.texts:
        q = _text_queries(r, args.texts, args)
        queries += [(re.sub(r"\W+", "_", t), q[i]) for i, t in enumerate(args.texts)]
    written = []
    for name, q in queries:
        heat = heatmap(view.features, q)
        m = mask(heat, args.threshold)
        heat_path, mask_path = out / f"{name}_{where}_heat.png", out / f"{name}_{where}_mask.png"
        save_overlay(heat_path, rgb, heat, vmin=0.0, vmax=1.0)
        cv2.imwrite(str(mask_path), m.astype(np.uint8) * 255)
        written += [heat_path, mask_path]
        print(f"{name}: max cosine {heat.max():.3f}, {100 * m.mean():.1f}% of pixels >= {args.threshold}")
    if args.labels:
        names = [s.strip() for s in args.labels.split(",") if s.strip()]
        labels_img = segment(view.features, _text_queries(r, names, args), threshold=0.0)
        seg_path = out / f"labels_{where}.png"
        cv2.imwrite(str(seg_path), cv2.cvtColor(_legend_image(labels_img, names, rgb), cv2.COLOR_RGB2BGR))
        written.append(seg_path)
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
