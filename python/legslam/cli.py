"""The `legslam` command. Each subcommand lives in its own module, which provides
`add_arguments(parser)` and `run(args) -> int` (the exit code); it is imported only when used,
so `legslam --help` stays fast and a broken optional dependency affects only its command."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

# subcommand -> (module, one-line help)
COMMANDS = {
    "demo": ("legslam.demo_cmd", "run SLAM on the built-in synthetic scene (no download)"),
    "run": ("legslam.run_cmd", "run SLAM with language features over an RGB-D sequence"),
    "query": ("legslam.query_cmd", "heat maps and masks of text or by-example queries on a saved map"),
    "render": ("legslam.render_cmd", "render colour/depth/feature views of a saved map along a trajectory"),
    "eval": ("legslam.eval_cmd", "ATE, RPE, PSNR/SSIM/depth L1 (and mIoU, given labels) of a run against ground truth"),
    "models": ("legslam.models", "fetch the default image encoder into the cache, or list cached models"),
    "export-models": ("legslam.features.export", "export DINOv2 ViT-B/14-reg and CLIP ViT-B/16 text to ONNX (needs torch)"),
    "odometry": ("legslam.odometry", "frame-to-frame RGB-D odometry over a sequence"),
}


class UserError(Exception):
    """An error the user can act on: printed without a traceback, exit code 2."""


def at_least(name: str, v, least: int = 1) -> None:
    """Rejects option `name`'s value `v` below `least` (None: not given, accepted)."""
    if v is not None and v < least:
        raise UserError(f"{name} must be at least {least}, got {v}")


def output_dir(path) -> Path:
    """Makes the output folder `path` (parents too) before any work is done; a UserError
    naming it when it cannot be made."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"the output folder {p} is a file")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot make the output folder {p}: {e.strerror or e}") from e
    return p


def output_file(path) -> Path:
    """Checks that the output file `path` can be made (its folder is made) before any work."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p} is a folder: give a file name to write")
    output_dir(p.parent)
    return p


def load_map(path):
    """The GaussianMap at `path`; a missing or unreadable file is a UserError naming it."""
    from .map import GaussianMap

    try:
        return GaussianMap.load(path)
    except (OSError, ValueError) as e:
        raise UserError(str(e)) from e


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="legslam",
        description="Language-enhanced Gaussian-splatting RGB-D SLAM on the CPU.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except UserError as e:
        print(f"legslam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
