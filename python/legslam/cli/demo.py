"""`legslam demo`: the built-in synthetic room, end to end, no download (beyond what the
set-up step cached)."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    from .run_cmd import add_run_options

    add_run_options(p)
    p.add_argument("--frames", type=int, default=60, help="frames of the built-in scene")


def run(args) -> int:
    from .datasets import open as open_dataset
    from .datasets.synthetic import default_scene
    from .cli import at_least
    from .run_cmd import run_config, run_sequence

    at_least("--frames", args.frames)
    config = run_config(args)
    path = default_scene(n_frames=args.frames)
    print(f"built-in scene: {path}")
    return run_sequence(open_dataset(path), "demo", args, config)
