"""`legslam query RUN ...`: heat maps and masks of text or by-example queries on a saved map,
rendered at any frame's estimated pose (or a given pose)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    from .text_cli import add_text_model_options

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


class RunFolder:
    """What a run folder holds, with errors that say what is missing."""

    def __init__(self, path: Path):
        from .cli import UserError, load_map
        from .eval import read_tum

        self.path = path
        for name in ("map.ply", "trajectory.txt", "camera.json"):
            if not (path / name).is_file():
                raise UserError(f"{path} has no {name}: give a `legslam run` output folder")
        self.map = load_map(path / "map.ply")
        if self.map.num_features == 0:
            raise UserError(f"{path / 'map.ply'} has no language features (run without --no-features)")
        cam = json.loads((path / "camera.json").read_text())
        self.K, self.width, self.height = np.array(cam["K"]), cam["width"], cam["height"]
        _, self.poses = read_tum(path / "trajectory.txt")

    def pose(self, frame: int) -> np.ndarray:
        from .cli import UserError

        if not 0 <= frame < len(self.poses):
            raise UserError(f"frame {frame} is out of range: the run has {len(self.poses)} frames")
        return self.poses[frame]

    def render(self, pose):
        return self.map.render(pose, self.K, self.width, self.height, features=True)


def _parse_example(text: str) -> tuple[int, int, int]:
    from .cli import UserError

    m = re.fullmatch(r"(\d+):(\d+),(\d+)", text.strip())
    if not m:
        raise UserError(f"--example takes N:X,Y (frame, pixel), got {text!r}")
    return int(m[1]), int(m[2]), int(m[3])


def _text_queries(run: RunFolder, labels: list[str], args) -> np.ndarray:
    from .text_cli import run_text_queries

    return run_text_queries(run.path, run.map.num_features, labels, args,
                            hint=" Query by example (--example N:X,Y) works without it.")


def _legend_image(labels_img: np.ndarray, names: list[str], rgb: np.ndarray) -> np.ndarray:
    import cv2

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
    import cv2

    from .cli import UserError, output_dir
    from .query import heatmap, mask, query_from_pixel, save_overlay, segment

    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise UserError(f"{run_dir} is not a folder")
    r = RunFolder(run_dir)
    if args.pose:
        try:
            pose = np.loadtxt(args.pose).reshape(4, 4)
        except (OSError, ValueError) as e:
            raise UserError(f"--pose {args.pose}: not a readable 4x4 matrix ({e})") from e
        where = "pose"
    else:
        pose = r.pose(args.frame)
        where = f"frame{args.frame:06d}"
    if not (args.texts or args.example or args.labels):
        raise UserError("nothing to query: give text queries, --example N:X,Y or --labels a,b,c")
    out = output_dir(Path(args.out) if args.out else run_dir / "queries")
    view = r.render(pose)
    rgb = (np.clip(view.color, 0, 1) * 255).astype(np.uint8)

    queries: list[tuple[str, np.ndarray]] = []
    for ex in args.example:
        n, x, y = _parse_example(ex)
        if not (0 <= x < r.width and 0 <= y < r.height):
            raise UserError(f"--example pixel {x},{y} is outside the {r.width}x{r.height} image")
        src = r.render(r.pose(n))
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
