"""Stray Scanner (iOS, LiDAR) exports: a folder with

    rgb.mp4              the colour camera's video (1920x1440 on recent iPhones), one frame a saved frame
    depth/000000.png     16-bit depth in millimetres at the LiDAR's resolution (256x192), frame by number
    confidence/*.png     ARKit's confidence of each depth pixel: 0 low, 1 medium, 2 high
    camera_matrix.csv    3x3 K of the video's frames
    odometry.csv         `timestamp, frame, x, y, z, qx, qy, qz, qw` a frame (older exports:
                         `x, y, z, qx, qy, qz, qw` without a header, line n = frame n)

odometry.csv holds ARKit's tracking, which is the ground truth of the figures. The app writes
it already in OpenCV's camera axes: its quaternion is ARKit's camera rotation times a half
turn about x (the app's OdometryEncoder, q_WA * q_AC), so the poses are read as they are.
The video is read in its stored (landscape) orientation, the one the depth and K describe,
whatever rotation its metadata asks players for. Frames come at the depth's resolution (see
_phone) and keep the odometry's timestamps; frames without an odometry row are left out.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ._io import poses_from_rows, read_depth, read_intrinsics, read_labels, read_numbers
from ._phone import PhoneSequence
from .base import NOMINAL_FPS, DatasetError, DatasetNotFoundError, check_pose, scale_K

log = logging.getLogger("legslam")

DEPTH_SCALE = 1000.0
# Frames skipped by decoding forward rather than seeking (a seek decodes from a key frame).
MAX_FORWARD = 30


def is_stray(path: Path) -> bool:
    return (path / "rgb.mp4").is_file() and (path / "depth").is_dir()


class VideoFrames:
    """The frames of a video by number, decoded going forward; going back or far ahead seeks."""

    def __init__(self, path: Path):
        import cv2

        self.path = path
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            raise DatasetError(f"cannot open the video {path} (missing codec, or not a video)")
        self._cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
        self.count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self._next = 0

    def __getitem__(self, n: int) -> np.ndarray:
        import cv2

        if not self._next <= n <= self._next + MAX_FORWARD:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, n)
            self._next = n
        while self._next < n and self._cap.grab():
            self._next += 1
        ok, bgr = self._cap.read()
        if not ok or self._next != n:
            self._next = -MAX_FORWARD - 1  # unknown: seek next time
            raise DatasetError(f"cannot decode frame {n} of the video {self.path} ({self.count} frames)")
        self._next = n + 1
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class StraySequence(PhoneSequence):
    format = "stray"

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name
        depth = {int(f.stem): f for f in (p / "depth").iterdir() if f.suffix == ".png" and f.stem.isdigit()}
        if not depth:
            raise DatasetNotFoundError(f"{p / 'depth'}: no depth images (000000.png, ...)")
        rows, lines = read_numbers(p / "odometry.csv", columns=(7, 9), line_numbers=True, header=True)
        numbers = rows[:, 1].astype(int) if rows.shape[1] == 9 else np.arange(len(rows))
        body = rows[:, 2:] if rows.shape[1] == 9 else rows
        odometry = {int(n): k for k, n in enumerate(numbers)}
        self._video = VideoFrames(p / "rgb.mp4")
        self._numbers = [n for n in sorted(depth) if n in odometry]
        left_out = len(depth) - len(self._numbers)
        if left_out:
            log.warning("%s: %d of %d depth images have no row in odometry.csv and are left out", p, left_out,
                        len(depth))
        if not self._numbers:
            raise DatasetError(f"{p}: no depth image has a row in odometry.csv")
        if self._video.count and self._numbers[-1] >= self._video.count:
            raise DatasetError(f"{p / 'rgb.mp4'} has {self._video.count} frames, too few for depth frame "
                               f"{self._numbers[-1]} (a cut-short export?)")
        self._depth = [depth[n] for n in self._numbers]
        conf_dir = p / "confidence"
        self._confidence = [conf_dir / f"{n:06d}.png" for n in self._numbers] if conf_dir.is_dir() else None
        if self._confidence is None:
            log.warning("%s: no confidence/ folder, so all depth is used", p)
        where = p / "odometry.csv"
        self._rows = [odometry[n] for n in self._numbers]
        self._stamps = rows[:, 0] if rows.shape[1] == 9 else None
        poses = poses_from_rows(body, where, lines)[1]
        self._poses = [check_pose(poses[k], f"{where}:{lines[k]}") for k in self._rows]
        K = read_intrinsics(p / "camera_matrix.csv")[0]
        vh, vw = self._video[self._numbers[0]].shape[:2]
        dh, dw = read_depth(self._depth[0]).shape
        self._setup(scale_K(K, dw / vw, dh / vh), DEPTH_SCALE, (dw, dh))

    def _count(self):
        return len(self._numbers)

    def _frame(self, i):
        confidence = None if self._confidence is None else read_labels(self._confidence[i])
        return self._video[self._numbers[i]], read_depth(self._depth[i]), confidence

    def _pose(self, i):
        return self._poses[i]

    def _timestamp(self, i):
        return self._stamps[self._rows[i]] if self._stamps is not None else self._numbers[i] / NOMINAL_FPS

