"""TUM RGB-D: rgb.txt, depth.txt and groundtruth.txt (`timestamp file` and
`timestamp tx ty tz qx qy qz qw` lines), depth PNGs scaled by 5000.

Colour and depth are paired by nearest timestamp (as TUM's associate.py, 0.02 s), and each
pair takes the ground-truth pose nearest to its colour timestamp, or None when there is none
within the tolerance. The freiburg1/2 cameras have lens distortion; both images are undistorted
to the same pinhole K (colour bilinear, depth nearest) so the engine sees a pinhole camera.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ._io import poses_from_rows, read_depth, read_numbers, read_rgb, read_text
from .base import DatasetError, DatasetNotFoundError, Sequence, check_pose, make_K
from .undistort import undistortion

DEPTH_SCALE = 5000.0
# Calibrations from the dataset's web page: fx fy cx cy and k1 k2 p1 p2 k3.
CAMERAS = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
DEFAULT_CAMERA = ((525.0, 525.0, 319.5, 239.5), (0.0,) * 5)  # the ROS default TUM recommends


def is_tum(path: Path) -> bool:
    return (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()


def read_file_list(path: Path) -> tuple:
    """(timestamps, file names) from a TUM `timestamp filename` list."""
    stamps, names = [], []
    for n, line in enumerate(read_text(path).splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        try:
            stamps.append(float(parts[0]))
        except ValueError:
            raise DatasetError(f"{path}:{n}: expected 'timestamp filename', got {line!r}") from None
        if len(parts) < 2:
            raise DatasetError(f"{path}:{n}: no file name after the timestamp")
        names.append(parts[1])
    if not stamps:
        raise DatasetError(f"{path} lists no files")
    return np.array(stamps), names


# Colour and depth further apart than this are not a pair (seconds; TUM's associate.py default).
MAX_TIME_DIFF = 0.02


def associate(a: np.ndarray, b: np.ndarray, max_diff: float) -> list:
    """Pairs (i, j) of a[i] and b[j] closest in time, each used once, |a[i]-b[j]| <= max_diff,
    found greedily by smallest difference as TUM's associate.py does; sorted by i."""
    order = np.argsort(a)
    b_sorted = np.argsort(b)
    cands = []
    bs = b[b_sorted]
    for i in order:  # only the neighbours in sorted b can be the closest
        k = np.searchsorted(bs, a[i])
        for kk in (k - 1, k, k + 1):
            if 0 <= kk < len(b):
                j = b_sorted[kk]
                d = abs(a[i] - b[j])
                if d <= max_diff:
                    cands.append((d, int(i), int(j)))
    cands.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def camera_for(path: Path) -> tuple:
    """The calibration of the camera named in the sequence's path (freiburg1/2/3)."""
    name = str(path.resolve()).lower()
    for key, cam in CAMERAS.items():
        if key in name:
            return cam
    warnings.warn(f"{path}: no freiburg1/2/3 in the path, so TUM's default camera (fx = fy = 525, no "
                  "distortion) is assumed; pass intrinsics=(fx, fy, cx, cy) if that is wrong", stacklevel=4)
    return DEFAULT_CAMERA


class TUMSequence(Sequence):
    format = "tum"

    def __init__(self, path, max_time_diff: float = MAX_TIME_DIFF, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name
        rgb_t, rgb_f = read_file_list(p / "rgb.txt")
        dep_t, dep_f = read_file_list(p / "depth.txt")
        pairs = associate(rgb_t, dep_t, max_time_diff)
        if not pairs:
            raise DatasetError(f"{p}: no colour and depth images are within {max_time_diff} s of each other")
        self._rgb = [p / rgb_f[i] for i, _ in pairs]
        self._depth = [p / dep_f[j] for _, j in pairs]
        self._stamps = rgb_t[[i for i, _ in pairs]]
        self._poses = [None] * len(pairs)
        gt = p / "groundtruth.txt"
        if gt.is_file():
            rows, lines = read_numbers(gt, columns=(8,), line_numbers=True)
            _, poses = poses_from_rows(rows, gt, lines)
            for k, j in associate(self._stamps, rows[:, 0], max_time_diff):
                self._poses[k] = check_pose(poses[j], f"{gt}:{lines[j]}")
        # Given intrinsics are taken to describe the images as they are: no undistortion.
        (fx, fy, cx, cy), dist = camera_for(p) if self._K_override is None else (DEFAULT_CAMERA[0], ())
        K = make_K(fx, fy, cx, cy)
        h, w = read_rgb(self._rgb[0]).shape[:2]
        self._undistort = undistortion(K, dist, (w, h))
        self._setup(K, DEPTH_SCALE, (w, h))

    def _count(self):
        return len(self._rgb)

    def _read(self, i):
        rgb, depth = read_rgb(self._rgb[i]), read_depth(self._depth[i])
        u = self._undistort
        if u is not None and u.fits(rgb) and u.fits(depth):  # other sizes: an error later
            rgb, depth = u.colour(rgb), u.depth(depth)
        return rgb, depth, None

    def _pose(self, i):
        return self._poses[i]

    def _timestamp(self, i):
        return self._stamps[i]
