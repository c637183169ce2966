"""When a frame becomes a keyframe: the camera moved or turned far enough since the last one,
the map covers too little of what the frame measured, or too many frames passed."""

from __future__ import annotations

from typing import Optional

import numpy as np

from .trajectory import KeyframeView

__all__ = ["KeyframePolicy", "REASONS", "rotation_deg"]

#: Why a frame became a keyframe: the first of a run (or of the map), the camera moved or
#: turned past its threshold, the map covered too little of the frame, or too many frames passed.
REASONS = ("first", "moved", "turned", "coverage", "gap")


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle (degrees) between the rotations of two poses."""
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


class KeyframePolicy:
    """Thresholds from the config: `keyframe_translation` (m), `keyframe_rotation` (degrees),
    `keyframe_overlap` (share of the frame's measured pixels the map covers) and
    `keyframe_max_gap` (frames); with a mapping thread, none within `realtime_keyframe_min_gap`
    frames of the last."""

    def __init__(self, config):
        self.config = config

    def wants(self, frame: int, pose: np.ndarray, coverage: float, last: Optional[KeyframeView],
              map_empty: bool, coverage_counts: bool) -> Optional[str]:
        """Why frame number `frame`, tracked at `pose` with the map covering `coverage`,
        becomes a keyframe after `last` (one of `REASONS`, the first that holds), or None if it
        does not. `coverage_counts`: whether the map is trained enough for low coverage to
        mean a gap (fresh Gaussians are faint until trained: behind a mapping thread,
        counting it would flood the mapper with keyframes)."""
        c = self.config
        if last is None or map_empty:
            return "first"
        if c.mapping_thread and frame - last.frame < c.realtime_keyframe_min_gap:
            return None
        if np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]) > c.keyframe_translation:
            return "moved"
        if rotation_deg(last.pose, pose) > c.keyframe_rotation:
            return "turned"
        if coverage_counts and coverage < c.keyframe_overlap:
            return "coverage"
        if frame - last.frame >= c.keyframe_max_gap:
            return "gap"
        return None
