"""`legslam models fetch|list`: the default image encoder into the cache, and what the cache
holds."""

from __future__ import annotations

import argparse

from ..models import KNOWN_MODELS, fetch_default, models_dir, read_manifest
from .common import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    fetch = sub.add_parser("fetch", help="download and prepare the default image encoder (cached)")
    fetch.add_argument("--force", action="store_true", help="rebuild even if the cache is valid")
    sub.add_parser("list", help="show the cache directory and which models are present")


def run(args) -> int:
    if args.action == "fetch":
        try:
            fetch_default(force=args.force)
        except RuntimeError as e:
            raise UserError(str(e)) from e
        return 0
    directory = models_dir()
    manifest = read_manifest(directory)
    print(f"cache: {directory}")
    for name, (filename, how) in KNOWN_MODELS.items():
        path = directory / filename
        state = "present" if path.is_file() else f"missing ({how})"
        sha = manifest.get(filename, {}).get("sha256", "")[:12]
        print(f"  {name:28s} {filename:34s} {state} {sha}")
    return 0
