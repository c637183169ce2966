"""Replica as rendered by NICE-SLAM / SplaTAM: <seq>/results/frame%06d.jpg, depth%06d.png
(scale 6553.5) and <seq>/traj.txt (one row-major 4x4 camera-to-world per line, OpenCV axes,
line i = frame i). cam_params.json is read from the sequence folder or its parent, where
NICE-SLAM's download keeps it; without one, Replica's standard camera scaled to the image size.
"""

from __future__ import annotations

from pathlib import Path

from ._io import read_depth, read_intrinsics, read_numbers, read_rgb
from .base import NOMINAL_FPS, DatasetError, DatasetNotFoundError, Sequence, check_pose, make_K, paths_sorted, scale_K

DEPTH_SCALE = 6553.5
STANDARD_SIZE = (1200, 680)
STANDARD_CAMERA = (600.0, 600.0, 599.5, 339.5)


def is_replica(path: Path) -> bool:
    return (path / "traj.txt").is_file() and any((path / "results").glob("frame*.jpg"))


def find_cam_params(path: Path):
    for p in (path / "cam_params.json", path.parent / "cam_params.json"):
        if p.is_file():
            return p
    return None


class ReplicaSequence(Sequence):
    format = "replica"

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name
        self._rgb = paths_sorted(list((p / "results").glob("frame*.jpg")))
        self._depth = paths_sorted(list((p / "results").glob("depth*.png")))
        if not self._rgb:
            raise DatasetNotFoundError(f"{p / 'results'}: no frame*.jpg images")
        if len(self._rgb) != len(self._depth) or [f.stem[5:] for f in self._rgb] != [f.stem[5:] for f in self._depth]:
            raise DatasetError(f"{p / 'results'}: {len(self._rgb)} frame*.jpg and {len(self._depth)} depth*.png "
                               "files whose numbers do not pair up")
        rows = read_numbers(p / "traj.txt", columns=(16,))
        # Line n of traj.txt is frame n; copies often hold only the first frames of the sequence.
        self._numbers = [int(f.stem[5:]) for f in self._rgb]
        if self._numbers and max(self._numbers) >= len(rows):
            raise DatasetError(f"{p / 'traj.txt'} has {len(rows)} poses, too few for frame {max(self._numbers)}")
        self._poses = rows.reshape(-1, 4, 4)
        h, w = read_rgb(self._rgb[0]).shape[:2]
        cam = find_cam_params(p)
        if cam is not None:
            K, scale, size = read_intrinsics(cam)
            if size is not None and size != (w, h):
                raise DatasetError(f"{cam} describes {size[0]}x{size[1]} images but {self._rgb[0]} is {w}x{h}")
            scale = DEPTH_SCALE if scale is None else scale
        else:
            K = scale_K(make_K(*STANDARD_CAMERA), w / STANDARD_SIZE[0], h / STANDARD_SIZE[1])
            scale = DEPTH_SCALE
        self.camera_file = cam
        self._setup(K, scale, (w, h))

    def _count(self):
        return len(self._rgb)

    def _read(self, i):
        return read_rgb(self._rgb[i]), read_depth(self._depth[i]), None

    def _timestamp(self, i):
        return self._numbers[i] / NOMINAL_FPS

    def _pose(self, i):
        n = self._numbers[i]
        return check_pose(self._poses[n], f"{self.path / 'traj.txt'} line {n + 1}")
