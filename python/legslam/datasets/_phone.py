"""What phone captures (Stray Scanner, Record3D) share: LiDAR depth at a lower resolution than
the colour camera, with a confidence per depth pixel (ARKit's 0 low, 1 medium, 2 high), and
ARKit's camera poses.

Frames come at the depth's resolution: the colour image is shrunk to it (area averaging) and
the intrinsics scaled with it. So every depth pixel and its confidence are the sensor's own,
never interpolated (upsampling a 256x192 depth map to 1920x1440 would invent 55 of every 56
depth pixels), and a frame is small enough for a CPU to keep up with the phone (`--downscale`
shrinks further). Depth below `min_confidence` is dropped (0, invalid).
"""

from __future__ import annotations

import numpy as np

from .base import DatasetError, Sequence

# ARKit's camera axes (x right, y up, z backward: OpenGL's) to ours (x right, y down, z forward):
# a camera-to-world pose in ARKit's axes times this is the same pose in OpenCV's.
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
CONFIDENCE_LEVELS = (0, 1, 2)
DEFAULT_MIN_CONFIDENCE = 2


class PhoneSequence(Sequence):
    """A phone capture: formats implement `_frame(i)` -> (colour at the colour camera's size,
    raw depth, confidence or None), and call _setup with the intrinsics scaled to the depth."""

    options = ("min_confidence",)

    def __init__(self, path, min_confidence: int = DEFAULT_MIN_CONFIDENCE, **kw):
        super().__init__(path, **kw)
        if min_confidence not in CONFIDENCE_LEVELS:
            raise DatasetError(f"min_confidence must be one of {CONFIDENCE_LEVELS} (ARKit's low, medium, "
                               f"high), got {min_confidence!r}")
        self.min_confidence = int(min_confidence)

    def _frame(self, i: int) -> tuple:
        raise NotImplementedError

    def _read(self, i):
        import cv2

        rgb, depth, confidence = self._frame(i)
        h, w = depth.shape
        if rgb.shape[:2] != (h, w):
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        if confidence is not None:
            if confidence.shape != depth.shape:
                raise DatasetError(f"{self.path} frame {i}: confidence is {confidence.shape[1]}x{confidence.shape[0]} "
                                   f"and depth {w}x{h}")
            depth = np.where(confidence >= self.min_confidence, depth, 0).astype(depth.dtype)
        return rgb, depth, None
