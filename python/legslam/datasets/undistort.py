"""Lens distortion removed on load, so that the engine sees a pinhole camera: images are
remapped to the same K without distortion, colour bilinearly and depth by the nearest pixel
(interpolated depth would blend a foreground and a background surface into one that exists
nowhere)."""

from __future__ import annotations

from typing import Optional

import numpy as np


class Undistortion:
    """The remapping of one camera's images (size (width, height)) to its K without distortion.
    dist: OpenCV's coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]), as ROS' plumb_bob and
    rational_polynomial models give them."""

    def __init__(self, K: np.ndarray, dist, size: tuple):
        import cv2

        self.size = (int(size[0]), int(size[1]))
        self._maps = cv2.initUndistortRectifyMap(K, np.asarray(dist, dtype=np.float64), None, K,
                                                 self.size, cv2.CV_32FC1)

    def fits(self, img: np.ndarray) -> bool:
        """Whether img has the camera's size (one that has not is left for the caller to report)."""
        return img.shape[:2] == self.size[::-1]

    def colour(self, img: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(img, *self._maps, cv2.INTER_LINEAR)

    def depth(self, img: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(img, *self._maps, cv2.INTER_NEAREST)


def undistortion(K: np.ndarray, dist, size: tuple) -> Optional[Undistortion]:
    """The Undistortion of a camera, or None when it has no distortion (all coefficients 0)."""
    return Undistortion(K, dist, size) if np.any(np.asarray(dist, dtype=np.float64)) else None
