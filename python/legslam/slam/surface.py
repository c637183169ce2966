"""The tracked frames' depth fused into a truncated signed distance volume (the engine's
`Tsdf`), and the reference a frame is tracked against first: the last fused frame's colour
with the fused surface's depth seen from its pose (frame-to-model, as KinectFusion).

The last frame's own depth carries its noise and its error into the next alignment, so frame
after frame the errors add up; the fused surface averages many frames and holds what was seen
before, so a camera that comes back aligns with it. A ray through a pixel the frame measured
starts two truncation distances in front of that depth; one through a hole covers only the
depths the frame measured (the engine's `raycast_near`). Where the volume has no surface, the
frame's own depth stays.

Every `every`-th tracked frame is fused and becomes the reference (real time fuses fewer: the
work runs on the tracking thread); the frames between are tracked against the last one fused.
A relocalised frame is fused at once: the reference before it shows another place.

A pose-graph correction moves keyframes and frames; the volume stays where it was fused, and
poses reach it through the correction of the newest keyframe (`correct`), so around the
camera the volume and the poses agree.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from legslam import _core

from .trajectory import View

__all__ = ["Surface"]

#: A voxel's weight stops growing at this many frames, so that a surface can still move.
MAX_WEIGHT = 64.0
#: A frame's holes are ray-cast one ray per cell of this many pixels a side (the engine's
#: `raycast` with `hole_cell`): on 7-Scenes (28% holes, its registered depth's border) the
#: ray-cast took 15.5 instead of 24.3 ms a frame, ATE 2.93 against 2.98 cm synchronous (cells
#: of 4, with the first version's 32-bit voxels: 3.47 against 3.10).
HOLE_CELL = 2


class Surface:
    """Fuses every `every`-th tracked view (at the tracking size, intrinsics `K`); the last
    one fused, with the fused surface's depth, is the `reference` ((frame, View), None before
    the first)."""

    def __init__(self, voxel: float, truncation: float, depth_range: tuple, K: np.ndarray,
                 every: int = 1):
        if every < 1:
            raise ValueError(f"a surface fuses every n-th frame, n >= 1; got {every}")
        self._core = _core.TsdfCore(voxel, truncation, MAX_WEIGHT, *depth_range)
        self.K, self.every = K, every
        # World (as poses now are) to the volume's world.
        self._to_volume = np.eye(4)
        # Tracked frames since the last one fused (None before the first).
        self._since: Optional[int] = None
        self.reference: Optional[tuple[int, View]] = None

    def add(self, frame: int, view: View, now: bool = False) -> None:
        """Frame `frame` was tracked (`view` at its pose): fused if it is due or `now`; the
        count to the next one starts again from it."""
        if not now and self._since is not None and self._since + 1 < self.every:
            self._since += 1
            return
        self._since = 0
        pose = self._to_volume @ view.pose
        self._core.integrate(view.depth, self.K, pose)
        h, w = view.depth.shape
        surface = self._core.raycast(self.K, w, h, pose, view.depth, HOLE_CELL)
        depth = np.where(surface > 0, surface, view.depth).astype(np.float32)
        self.reference = (frame, View(view.pose, view.rgb, depth))

    def correct(self, correction: np.ndarray, poses: list) -> None:
        """The newest keyframe moved by `correction` (world to world): so does the way to the
        volume; the reference takes its frame's pose in `poses` (every frame's, corrected)."""
        self._to_volume = self._to_volume @ np.linalg.inv(correction)
        if self.reference is not None:
            frame, view = self.reference
            self.reference = (frame, View(poses[frame], view.rgb, view.depth))

    @property
    def memory_bytes(self) -> int:
        return self._core.memory_bytes
