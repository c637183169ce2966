"""`legslam eval RUN`: a run's trajectory and map against the sequence's ground truth: ATE,
RPE, PSNR / SSIM / depth L1 of the map rendered at estimated poses and, when the frames carry
class labels and the map language features, mIoU; a table and eval.json."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..datasets import DatasetError, open as open_dataset
from ..eval import NoPrototypes, by_example, by_text, evaluate_run
from ..run_folder import CONFIG, RunFolder, write_json
from ..slam import SLAMConfig
from .common import UserError, at_least, open_run
from .text_model import add_text_model_options, run_text_queries


def add_arguments(p: argparse.ArgumentParser) -> None:
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
    try:
        return open_dataset(path, format=fmt, **{**selection, "frames": tuple(selection["frames"])})
    except (DatasetError, FileNotFoundError, KeyError, TypeError) as e:
        raise UserError(f"cannot open the run's frames of {path} ({selection}): {e}") from e


def _sequence(run: RunFolder, args):
    """The run's frames, checked against the camera it recorded."""
    seq_path = args.sequence or run.sequence
    if not seq_path:
        raise UserError("the run does not record its sequence: give --sequence PATH")
    if run.selection and not args.sequence:
        seq = _open_selection(seq_path, args.format, run.selection)
    else:
        seq = _open_at_run_size(seq_path, args.format, run.width, run.height)
    w, h, K = run.width, run.height, run.K
    if (seq.width, seq.height) != (w, h):
        raise UserError(f"the run's images are {w}x{h} but {seq_path}'s are {seq.width}x{seq.height}, "
                        "not an integer downscale of them (a different sequence? give --sequence)")
    if not np.allclose(seq.K, K, rtol=1e-4):
        raise UserError(f"the run's camera (fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}) is not {seq_path}'s as "
                        f"read now (fx {seq.K[0, 0]:.1f}, fy {seq.K[1, 1]:.1f}): a run by an older legslam, "
                        "which read 7-Scenes depth unregistered? run it again")
    if len(run.poses) > len(seq):
        raise UserError(f"the trajectory has {len(run.poses)} poses but {seq_path} only {len(seq)} frames "
                        "(was the run made with --stride or a different sequence?)")
    return seq


def run(args) -> int:
    at_least("--every", args.every)
    run_dir = Path(args.run)
    r = open_run(run_dir)
    seq = _sequence(r, args)
    poses = r.poses
    # The frames the run could not read are left out, as the run's own figures were; and
    # those that cannot be read now (their labels, say), by name.
    skip = set(r.metrics().get("unreadable_frames", []))
    for i in range(0, len(poses), args.every):
        if i not in skip:
            try:
                seq[i]
            except DatasetError as e:
                print(f"warning: frame {i} left out: {e}", file=sys.stderr)
                skip.add(i)

    def render(pose, features: bool):
        return r.map.render(pose, r.K, r.width, r.height, features=features)

    views = [i for i in range(0, len(poses), args.every) if i not in skip]
    if not views:
        raise UserError(f"none of the run's {len(poses)} frames of {seq.path} can be read")
    sem = _semantic_score(args, seq, r, views, lambda i: seq[i].labels,
                          lambda i: render(poses[i], True).features)
    report = evaluate_run(seq, poses, render, every=args.every, skip=skip,
                          depth_range=_depth_range(r), semantic=sem)
    report["gaussians"] = len(r.map)
    if sem is not None and sem.views == 0:
        print("note: no semantic metrics: every evaluated view is a support view (use a smaller --every)")
    _print_table(report)
    write_json(run_dir / "eval.json", report)
    print(f"saved {run_dir / 'eval.json'}")
    return 0


def _depth_range(run: RunFolder) -> tuple:
    """The depth range (m) the run kept, from its config.json (the defaults without one)."""
    try:
        config = SLAMConfig.from_file(run.path / CONFIG) if (run.path / CONFIG).is_file() else SLAMConfig()
    except (OSError, ValueError) as e:
        raise UserError(f"{run.path / CONFIG}: {e}") from e
    return config.mapper.depth_min, config.mapper.depth_max


def _semantic_score(args, seq, run: RunFolder, views: list, labels_of, features_of):
    """The semantic scorer --semantic asks for, or None when there is nothing to score: no
    labels (silently, unless asked for) or no language features (with a note)."""
    if args.semantic == "off":
        return None
    asked = args.semantic != "auto"
    labels = labels_of(views[0])
    why = ("the sequence has no labels" if labels is None
           else f"{run.path / 'map.ply'} has no language features" if run.map.num_features == 0 else None)
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
            return by_text(run_text_queries(run, seq.class_names, args), seq.class_names)
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
        # Each view set's figures and per-class values get a row each; classes that occur
        # nowhere (None) are left out.
        if isinstance(v, dict):
            rows += [(f"{k}[{name}]", x) for name, x in v.items() if x is not None or not k.startswith("iou")]
        else:
            rows.append((k, v))
    print("| metric | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {'n/a' if v is None else v} |")
