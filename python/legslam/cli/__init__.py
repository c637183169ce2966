"""The `legslam` command: one module per subcommand, each with `add_arguments(parser)` and
`run(args) -> exit code`. The only package that parses arguments or prints; the library
reports through the "legslam" logger, which `main` shows on stderr."""

from __future__ import annotations

import argparse
import logging
import sys

from . import demo, eval, export_models, models, odometry, query, render, run
from .common import Stopped, UserError, stopping_on_signals

# subcommand -> (module, one-line help)
COMMANDS = {
    "demo": (demo, "run SLAM on the built-in synthetic scene (no download)"),
    "run": (run, "run SLAM with language features over an RGB-D sequence"),
    "query": (query, "heat maps and masks of text or by-example queries on a saved map"),
    "render": (render, "render colour/depth/feature views of a saved map along a trajectory"),
    "eval": (eval, "ATE, RPE, PSNR/SSIM/depth L1 (and mIoU, given labels) of a run against ground truth"),
    "models": (models, "fetch the default image encoder into the cache, or list cached models"),
    "export-models": (export_models, "export DINOv2 ViT-B/14-reg and CLIP ViT-B/16 text to ONNX (needs torch)"),
    "odometry": (odometry, "frame-to-frame RGB-D odometry over a sequence"),
}

__all__ = ["main", "build_parser", "COMMANDS", "UserError"]


class _Stderr(logging.StreamHandler):
    """The library's log lines on whatever sys.stderr is when they come, as the command prints
    its own: "warning: ..." for warnings."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _):
        pass

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        return f"{record.levelname.lower()}: {text}" if record.levelno >= logging.WARNING else text


def _show_log() -> None:
    log = logging.getLogger("legslam")
    if not any(isinstance(h, _Stderr) for h in log.handlers):
        log.addHandler(_Stderr())
    log.setLevel(logging.INFO)
    log.propagate = False


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="legslam",
        description="Language-enhanced Gaussian-splatting RGB-D SLAM on the CPU.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_run=module.run)
        module.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _show_log()
    try:
        with stopping_on_signals():
            return int(args._run(args) or 0)
    except UserError as e:
        print(f"legslam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Stopped as e:
        print(f"stopped by {e}", file=sys.stderr)
        return 128 + e.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
