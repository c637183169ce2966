"""A run folder: what `legslam run` writes and `query`, `render` and `eval` read, in one place.

    trajectory.txt   one camera-to-world pose per input frame (TUM format)
    map.ply          the Gaussians (3DGS layout, language features as f_lang_*)
    pca.npz          the feature compression (for text queries)
    camera.json      the intrinsics and image size the run worked at, and its input
    config.json      the SLAMConfig of the run
    metrics.json     its figures; timings.json: per-stage times
    renders/         renders beside input frames, and rendered features as colour

Files are written whole or not at all (a temporary file renamed over the real name), so that a
run killed mid-write never leaves a truncated file under a real name.
"""

from __future__ import annotations

import json
import os
from functools import cached_property
from pathlib import Path
from typing import Optional

import numpy as np

from .eval import TrajectoryError, read_tum, write_tum
from .map import GaussianMap

__all__ = ["RunFolderError", "RunFolder", "write_json", "write_camera", "write_trajectory",
           "replace_atomically", "RUN_FILES", "RECORDING",
           "TRAJECTORY", "MAP", "PCA_FILE", "CAMERA", "CONFIG", "METRICS", "TIMINGS"]

TRAJECTORY, MAP, PCA_FILE = "trajectory.txt", "map.ply", "pca.npz"
CAMERA, CONFIG, METRICS, TIMINGS = "camera.json", "config.json", "metrics.json", "timings.json"
#: A live camera's frames, as the run took them (a folder dataset).
RECORDING = "recording"
#: Everything a run and the commands on its folder write there: what `--overwrite` replaces.
RUN_FILES = (TRAJECTORY, MAP, PCA_FILE, CAMERA, CONFIG, METRICS, TIMINGS, "summary.json",
             "eval.json", "renders", "queries", "views", RECORDING)


class RunFolderError(ValueError):
    """A run folder, or one of its files, is missing or not what a run writes; the message
    names the file (and the field)."""


def replace_atomically(path: Path, write) -> Path:
    """Calls `write(tmp_path)`, then renames the temporary file over `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_json(path, data) -> Path:
    """`data` as indented JSON, atomically. Non-finite numbers, which JSON cannot hold, are
    written as null (the figures that can be infinite carry a note saying why)."""
    text = json.dumps(_finite(data), indent=2, allow_nan=False)
    return replace_atomically(path, lambda tmp: Path(tmp).write_text(text))


def _finite(v):
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def write_camera(out: Path, K: np.ndarray, width: int, height: int, sequence: str,
                 selection: Optional[dict]) -> Path:
    return write_json(out / CAMERA, {"K": np.asarray(K).tolist(), "width": width, "height": height,
                                     "sequence": sequence, "selection": selection})


def write_trajectory(out: Path, stamps, poses) -> Path:
    return replace_atomically(out / TRAJECTORY, lambda tmp: write_tum(tmp, stamps, poses))


class RunFolder:
    """A run folder read back: its camera (`K`, `width`, `height`, `sequence`, `selection`),
    trajectory (`poses`, `stamps`) and, when first used, its `map`."""

    def __init__(self, path, need=(MAP, TRAJECTORY, CAMERA)):
        self.path = Path(path)
        if not self.path.is_dir():
            raise RunFolderError(f"{self.path} is not a folder: give a `legslam run` output folder")
        for name in need:
            if not (self.path / name).is_file():
                raise RunFolderError(f"{self.path} has no {name}: give a `legslam run` output folder")
        camera = self.path / CAMERA
        if camera.is_file():
            self.K, self.width, self.height, self.sequence, self.selection = read_camera(camera)
        trajectory = self.path / TRAJECTORY
        if trajectory.is_file():
            self.stamps, self.poses = read_trajectory(trajectory)

    @cached_property
    def map(self) -> GaussianMap:
        try:
            return GaussianMap.load(self.path / MAP)
        except (OSError, ValueError) as e:
            raise RunFolderError(str(e)) from e

    def metrics(self) -> dict:
        """metrics.json, or {} for a run that did not get to write it."""
        path = self.path / METRICS
        return _read_json(path) if path.is_file() else {}


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise RunFolderError(f"{path} cannot be read as JSON: {e}") from None
    if not isinstance(data, dict):
        raise RunFolderError(f"{path} must hold a JSON object, got {type(data).__name__}")
    return data


def read_camera(path: Path) -> tuple:
    """(K, width, height, sequence or None, selection or None) from a camera.json."""
    data = _read_json(path)
    try:
        K = np.asarray(data["K"], dtype=np.float64)
        width, height = int(data["width"]), int(data["height"])
    except KeyError as e:
        raise RunFolderError(f"{path} has no field {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise RunFolderError(f"{path}: K, width and height must be numbers ({e})") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise RunFolderError(f"{path}: field 'K' must be a finite 3x3 matrix, got {data['K']!r}")
    if width <= 0 or height <= 0:
        raise RunFolderError(f"{path}: fields 'width' and 'height' must be positive, got {width}x{height}")
    return K, width, height, data.get("sequence") or None, data.get("selection")


def read_trajectory(path: Path) -> tuple:
    """(timestamps, poses) of a TUM trajectory; non-finite values are an error naming the line."""
    try:
        stamps, poses = read_tum(path)
    except (OSError, TrajectoryError) as e:
        raise RunFolderError(f"cannot read the trajectory {path}: {e}") from e
    bad = ~np.isfinite(poses).all(axis=(1, 2)) | ~np.isfinite(stamps)
    if bad.any():
        raise RunFolderError(f"{path}: pose {int(np.argmax(bad))} has a non-finite value (NaN or inf)")
    return stamps, poses
