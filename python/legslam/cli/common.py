"""What the subcommands share: the error a user can act on, termination signals taken like
Ctrl-C, checks of options and of output locations made before any work, and a run folder
opened with those errors."""

from __future__ import annotations

import os
import signal
import tempfile
from contextlib import contextmanager
from pathlib import Path

from ..run_folder import CAMERA, MAP, TRAJECTORY, RunFolder, RunFolderError

__all__ = ["UserError", "Stopped", "stopping_on_signals", "at_least", "output_dir", "output_file",
           "open_run", "available_memory"]

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
