"""`legslam eval RUN`: a run's trajectory and map against the sequence's ground truth: ATE,
RPE, PSNR / SSIM / depth L1 of the map rendered at estimated poses and, when the frames carry
class labels and the map language features, mIoU (see semantic_eval); a table and eval.json."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    from .text_cli import add_text_model_options

    p.add_argument("run", help="a `legslam run` output folder")
    p.add_argument("--sequence", default=None, help="the input sequence (default: as recorded in camera.json)")
    p.add_argument("--format", default="auto")
    p.add_argument("--every", type=int, default=5, help="evaluate the map at every N-th frame")
    p.add_argument("--semantic", choices=("auto", "text", "example", "off"), default="auto",
                   help="mIoU when the sequence has labels: by text queries of the class names "
                        "(open-vocabulary; needs the text model), by example (class prototypes "
                        "from a few labelled views; no text model), or auto: text when the "
                        "model loads, else by example")
    add_text_model_options(p)


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
    return seq


def _open_selection(path, fmt: str, selection: dict):
    """The frames the run saw (its stride, range and downscale, as camera.json records)."""
    from .cli import UserError
    from .datasets import DatasetError, open as open_dataset

    try:
        return open_dataset(path, format=fmt, frames=tuple(selection["frames"]),
                            stride=selection["stride"], downscale=selection["downscale"])
    except (DatasetError, FileNotFoundError, KeyError, TypeError) as e:
        raise UserError(f"cannot open the run's frames of {path} ({selection}): {e}") from e


def run(args) -> int:
    from .cli import UserError, at_least, load_map
    from .datasets import DatasetError
    from .eval import ViewScores, ate, read_tum, rpe

    run_dir = Path(args.run)
    for name in ("trajectory.txt", "map.ply", "camera.json"):
        if not (run_dir / name).is_file():
            raise UserError(f"{run_dir} has no {name}: give a `legslam run` output folder")
    at_least("--every", args.every)
    cam = json.loads((run_dir / "camera.json").read_text())
    seq_path = args.sequence or cam.get("sequence")
    if not seq_path:
        raise UserError("the run does not record its sequence: give --sequence PATH")
    K, w, h = np.array(cam["K"]), cam["width"], cam["height"]
    if cam.get("selection") and not args.sequence:
        seq = _open_selection(seq_path, args.format, cam["selection"])
    else:
        seq = _open_at_run_size(seq_path, args.format, w, h)
    if (seq.width, seq.height) != (w, h):
        raise UserError(f"the run's images are {w}x{h} but {seq_path}'s are {seq.width}x{seq.height}, "
                        "not an integer downscale of them (a different sequence? give --sequence)")
    if not np.allclose(seq.K, K, rtol=1e-4):
        raise UserError(f"the run's camera (fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}) is not {seq_path}'s as "
                        f"read now (fx {seq.K[0, 0]:.1f}, fy {seq.K[1, 1]:.1f}): a run by an older legslam, "
                        "which read 7-Scenes depth unregistered? run it again")
    _, poses = read_tum(run_dir / "trajectory.txt")
    if len(poses) > len(seq):
        raise UserError(f"the trajectory has {len(poses)} poses but {seq_path} only {len(seq)} frames "
                        "(was the run made with --stride or a different sequence?)")

    def frame(i):
        try:
            return seq[i]
        except DatasetError as e:  # e.g. a label image of the wrong size
            raise UserError(str(e)) from e

    report: dict = {"frames": len(poses)}
    gt, unreadable = {}, []
    for i in range(len(poses)):
        try:
            gt[i] = seq[i].pose
        except DatasetError as e:  # as the run did: left out, with a warning
            print(f"warning: frame {i} left out: {e}", file=sys.stderr)
            unreadable.append(i)
    if unreadable:
        report["unreadable_frames"] = unreadable
    if not gt:
        raise UserError(f"none of the run's {len(poses)} frames of {seq_path} can be read")
    if len(gt) >= 3 and all(g is not None for g in gt.values()):
        truth, estimate = np.stack(list(gt.values())), poses[list(gt)]
        a, r = ate(truth, estimate), rpe(truth, estimate)
        report.update(ate_rmse_cm=100 * a["rmse"], ate_mean_cm=100 * a["mean"],
                      rpe_trans_rmse_cm=100 * r["trans"]["rmse"], rpe_rot_rmse_deg=r["rot"]["rmse"])
    m = load_map(run_dir / "map.ply")
    # Every N-th readable frame (the first readable one when none of those is).
    views = [i for i in range(0, len(poses), args.every) if i in gt] or [next(iter(gt))]
    sem = _semantic_score(args, seq, run_dir, m, views, lambda i: frame(i).labels,
                          lambda i: m.render(poses[i], K, w, h, features=True).features)
    scores = ViewScores()
    for i in views:
        f = frame(i)
        out = m.render(poses[i], K, w, h, features=sem is not None)
        scores.add(np.clip(out.color, 0, 1), out.depth, f.rgb, f.depth)
        if sem is not None:
            sem.add(i, out.features, f.labels)
    report.update(scores.means(), views=len(views))
    report["gaussians"] = len(m)
    if sem is not None and sem.views == 0:
        print("note: no semantic metrics: every evaluated view is a support view (use a smaller --every)")
    elif sem is not None:
        report.update(sem.report())
    _print_table(report)
    (run_dir / "eval.json").write_text(json.dumps(report, indent=2))
    print(f"saved {run_dir / 'eval.json'}")
    return 0


def _semantic_score(args, seq, run_dir: Path, gmap, views: list, labels_of, features_of):
    """The semantic scorer --semantic asks for, or None when there is nothing to score: no
    labels (silently, unless asked for) or no language features (with a note)."""
    from .cli import UserError
    from .semantic_eval import NoPrototypes, by_example, by_text
    from .text_cli import run_text_queries

    if args.semantic == "off":
        return None
    asked = args.semantic != "auto"
    labels = labels_of(views[0])
    why = ("the sequence has no labels" if labels is None
           else f"{run_dir / 'map.ply'} has no language features" if gmap.num_features == 0 else None)
    if why:
        if asked:
            raise UserError(f"--semantic {args.semantic}: {why}")
        if labels is not None:
            print(f"note: no semantic metrics: {why}")
        return None
    if args.semantic != "example":
        try:
            if not seq.class_names:
                raise UserError(f"{seq.path} has no class list, which text queries are made from")
            return by_text(run_text_queries(run_dir, gmap.num_features, seq.class_names, args), seq.class_names)
        except UserError as e:
            if asked:
                raise
            print(f"note: no text queries, so mIoU is by example (NOT open-vocabulary): {e}")
    try:
        return by_example(views, labels_of, features_of, seq.class_names)
    except NoPrototypes as e:
        if asked:
            raise UserError(f"--semantic example: {e}") from e
        print(f"note: no semantic metrics: {e}")
        return None


def _print_table(report: dict) -> None:
    rows = []
    for k, v in report.items():
        # Per-class values get a row each; classes that occur nowhere (None) are left out.
        rows += [(f"{k}[{name}]", x) for name, x in v.items() if x is not None] if isinstance(v, dict) else [(k, v)]
    print("| metric | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {'n/a' if v is None else v} |")
