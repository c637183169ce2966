"""What the subcommands share: the error a user can act on, termination signals taken like
Ctrl-C, checks of options and of output locations made before any work, and a run folder
opened with those errors."""

from __future__ import annotations

import argparse
import os
import signal
import tempfile
from contextlib import contextmanager
from pathlib import Path

from ..datasets import DatasetError, open as open_dataset
from ..run_folder import CAMERA, MAP, TRAJECTORY, RunFolder, RunFolderError

__all__ = ["UserError", "Stopped", "stopping_on_signals", "at_least", "output_dir", "output_file",
           "open_run", "available_memory", "add_sequence_options", "open_sequence"]

#: Signals that stop a command like Ctrl-C: `timeout`, `kill`, `docker stop`, job schedulers,
#: a closed terminal.
SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class UserError(Exception):
    """An error the user can act on: printed without a traceback, exit code 2."""


class Stopped(KeyboardInterrupt):
    """A termination signal, taken like Ctrl-C: the work stops at the next safe point and what
    is done is saved on the way out."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextmanager
def stopping_on_signals():
    """Within: SIGTERM and SIGHUP raise Stopped in the main thread. After the first, further
    ones are ignored, so that saving the work done is not cut short."""

    def stop(signum, frame):
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        raise Stopped(signum)

    previous = {s: signal.signal(s, stop) for s in SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def add_sequence_options(p) -> None:
    """How to read the sequence at the command's PATH (run, odometry)."""
    p.add_argument("--format", default="auto", help="dataset format (default: detected)")
    p.add_argument("--stride", type=int, default=1, help="use every N-th frame")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--downscale", type=int, default=1, help="shrink images by this integer factor")
    p.add_argument("--intrinsics", type=_intrinsics, default=None, metavar="FX,FY,CX,CY",
                   help="the camera's focal lengths and principal point in pixels, for a recording "
                        "without them (a bag without CameraInfo), or instead of its own (the images "
                        "are then taken as they are, without undistortion)")
    p.add_argument("--rgb-topic", default=None,
                   help="a bag's colour image topic (default: the only one, or the one a recorder names)")
    p.add_argument("--depth-topic", default=None, help="a bag's depth image topic (default: likewise)")
    p.add_argument("--min-confidence", type=int, choices=(0, 1, 2), default=None,
                   help="phone captures: keep depth of at least this ARKit confidence (0 low, 1 medium, "
                        "2 high; default 2)")


def _intrinsics(text: str) -> tuple:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy (four numbers), got {text!r}")
    return values


def open_sequence(args, path=None):
    """The sequence at `path` (default args.path) as add_sequence_options' options ask."""
    at_least("--stride", args.stride)
    at_least("--max-frames", args.max_frames)
    at_least("--downscale", args.downscale)
    try:
        return open_dataset(args.path if path is None else path, format=args.format, stride=args.stride,
                            max_frames=args.max_frames, downscale=args.downscale, intrinsics=args.intrinsics,
                            rgb_topic=args.rgb_topic, depth_topic=args.depth_topic,
                            min_confidence=args.min_confidence)
    except (DatasetError, FileNotFoundError) as e:
        raise UserError(str(e)) from e


def at_least(name: str, v, least: int = 1) -> None:
    """Rejects option `name`'s value `v` below `least` (None: not given, accepted)."""
    if v is not None and v < least:
        raise UserError(f"{name} must be at least {least}, got {v}")


def output_dir(path) -> Path:
    """Makes the output folder `path` (parents too) before any work is done, and checks that
    files can be written in it; a UserError naming it when not."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"the output folder {p} is a file")
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=p, prefix=".legslam-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise UserError(f"cannot write into the output folder {p}: {e.strerror or e}") from e
    return p


def output_file(path) -> Path:
    """Checks that the output file `path` can be made (its folder is made) before any work."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p} is a folder: give a file name to write")
    output_dir(p.parent)
    return p


def open_run(path, need=(MAP, TRAJECTORY, CAMERA)) -> RunFolder:
    """The run folder at `path` with the files `need` read (see RunFolder); what is wrong with
    it is a UserError."""
    try:
        run = RunFolder(path, need)
        if MAP in need:
            run.map  # noqa: B018  (read now, so that a bad map is this error)
        return run
    except RunFolderError as e:
        raise UserError(str(e)) from e


def available_memory() -> int:
    """Bytes of memory available to a new allocation (MemAvailable; free pages elsewhere)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
