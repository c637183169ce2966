"""`legslam demo`: the built-in synthetic room, end to end, no download (beyond what the
set-up step cached)."""

from __future__ import annotations

import argparse

from ..datasets import open as open_dataset
from ..datasets.synthetic import default_scene
from .common import at_least
from .run import add_run_options, run_config, run_sequence


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_run_options(p)
    p.add_argument("--frames", type=int, default=60, help="frames of the built-in scene")


def run(args) -> int:
    at_least("--frames", args.frames)
    config = run_config(args)
    path = default_scene(n_frames=args.frames)
    print(f"built-in scene: {path}")
    return run_sequence(open_dataset(path), "demo", args, config)
