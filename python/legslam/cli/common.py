"""What the subcommands share: the error a user can act on, checks of options and of output
locations made before any work, and a run folder opened with those errors."""

from __future__ import annotations

from pathlib import Path

from ..run_folder import CAMERA, MAP, TRAJECTORY, RunFolder, RunFolderError

__all__ = ["UserError", "at_least", "output_dir", "output_file", "open_run"]


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
