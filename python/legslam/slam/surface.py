"""The tracked frames' depth fused into a truncated signed distance volume (the engine's
`Tsdf`), and the reference a frame is tracked against first: the last frame's colour with the
fused surface's depth seen from the last frame's pose (frame-to-model, as KinectFusion).

The last frame's own depth carries its noise and its error into the next alignment, so frame
after frame the errors add up; the fused surface averages many frames and holds what was seen
before, so a camera that comes back aligns with it. A ray through a pixel the frame measured
starts two truncation distances in front of that depth; one through a hole covers only the
depths the frame measured (the engine's `raycast_near`). Where the volume has no surface, the
frame's own depth stays.

A pose-graph correction moves keyframes and frames; the volume stays where it was fused, and
poses reach it through the correction of the newest keyframe (`correct`), so around the
camera the volume and the poses agree.
"""

from __future__ import annotations

import numpy as np

from legslam import _core

from .trajectory import View

__all__ = ["Surface"]

#: A voxel's weight stops growing at this many frames, so that a surface can still move.
MAX_WEIGHT = 64.0


class Surface:
    """Fuses tracked views (at the tracking size, intrinsics `K`) and gives each back with the
    fused surface's depth."""

    def __init__(self, voxel: float, truncation: float, depth_range: tuple, K: np.ndarray):
        self._core = _core.TsdfCore(voxel, truncation, MAX_WEIGHT, *depth_range)
        self.K = K
        # World (as poses now are) to the volume's world.
        self._to_volume = np.eye(4)

    def fuse(self, view: View) -> View:
        """Fuses `view`'s depth at its pose; returns the view with the surface's depth."""
        pose = self._to_volume @ view.pose
        self._core.integrate(view.depth, self.K, pose)
        h, w = view.depth.shape
        surface = self._core.raycast(self.K, w, h, pose, view.depth)
        return View(view.pose, view.rgb, np.where(surface > 0, surface, view.depth).astype(np.float32))

    def correct(self, correction: np.ndarray) -> None:
        """The newest keyframe moved by `correction` (world to world): so does the way to the
        volume."""
        self._to_volume = self._to_volume @ np.linalg.inv(correction)

    @property
    def memory_bytes(self) -> int:
        return self._core.memory_bytes
