"""The tracked frames' depth fused into a truncated signed distance volume (the engine's
`Tsdf`), and the reference a frame is tracked against first: the last fused frame's colour
with the fused surface's depth seen from its pose (frame-to-model, as KinectFusion).

The last frame's own depth carries its noise and its error into the next alignment, so frame
after frame the errors add up; the fused surface averages many frames and holds what was seen
before, so a camera that comes back aligns with it. A ray through a pixel the frame measured
starts two truncation distances in front of that depth; one through a hole covers only the
depths the frame measured (the engine's `raycast_near`). Where the volume has no surface, the
frame's own depth stays.

Each tracked frame becomes the reference: the surface ray-cast from its own pose, near its own
depth. Every `every`-th is fused into the volume first (real time fuses fewer). What a frame
gains from the reference is its freshness, not the frames fused: synchronous 7-Scenes tracked
2.94 cm ATE ray-casting every frame whether it fused every frame or every 3rd, 3.50 fusing
every frame but ray-casting every 3rd (README, *What the rest of the 7-Scenes gap is*). A
relocalised frame is fused at once: the reference before it shows another place.

In real time (`background`) a worker thread fuses and ray-casts, so that a frame never waits
for the one before: the reference is the last frame the worker has finished, and a frame that
comes while it is busy is passed over (not queued), so the work never piles up when the frames
come faster than it. Its engine threads run at the tracker's priority: at the mapping threads'
lowered one, the reference a frame got was 4.8 frames old on average (2.4 at the tracker's),
and 7-Scenes tracked no better for ray-casting every frame.

A pose-graph correction moves keyframes and frames; the volume stays where it was fused, and
poses reach it through the correction of the newest keyframe (`correct`), so around the
camera the volume and the poses agree.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
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
    view, with the fused surface's depth from its pose, is the `reference` ((frame, View),
    None before the first). With `background`, a worker thread fuses and ray-casts (the
    module's docstring says how), on `threads` threads of the engine's own."""

    def __init__(self, voxel: float, truncation: float, depth_range: tuple, K: np.ndarray,
                 every: int = 1, background: bool = False, threads: Optional[int] = None):
        if every < 1:
            raise ValueError(f"a surface fuses every n-th frame, n >= 1; got {every}")
        self._core = _core.TsdfCore(voxel, truncation, MAX_WEIGHT, *depth_range,
                                    threads=threads if background else None)
        self.K, self.every = K, every
        # World (as poses now are) to the volume's world.
        self._to_volume = np.eye(4)
        # Tracked frames since the last one fused (None before the first).
        self._since: Optional[int] = None
        self._reference: Optional[tuple[int, View]] = None
        self._worker = (ThreadPoolExecutor(1, thread_name_prefix="legslam-surface")
                        if background else None)
        # The frame the worker is on and its job (fusing and ray-casting it: the worker alone
        # touches the volume meanwhile); that frame's pose if a correction moved it since.
        self._job: Optional[tuple[int, Future]] = None
        self._job_pose: Optional[np.ndarray] = None
        self._memory_bytes = 0

    @property
    def reference(self) -> Optional[tuple[int, View]]:
        if self._job is not None and self._job[1].done():
            self._wait()
        return self._reference

    def add(self, frame: int, view: View, now: bool = False) -> None:
        """Frame `frame` was tracked (`view` at its pose): its reference is made unless the
        worker is busy, fused first if one is due; `now`: made and fused at once (after the
        worker's), and the count to the next fusion starts again from it."""
        if not now and self._job is not None and not self._job[1].done():
            self._since += 1
            return
        self._wait()
        fuse = now or self._since is None or self._since + 1 >= self.every
        self._since = 0 if fuse else self._since + 1
        pose = self._to_volume @ view.pose
        if self._worker is None or now:
            self._reference = self._cast(frame, view, pose, fuse)
        else:
            self._job = (frame, self._worker.submit(self._cast, frame, view, pose, fuse))
            self._job_pose = None

    def _cast(self, frame: int, view: View, pose: np.ndarray, fuse: bool) -> tuple[int, View]:
        """The reference `view` seen from `pose` (in the volume's world) makes, fused first if
        `fuse`."""
        if fuse:
            self._core.integrate(view.depth, self.K, pose)
            self._memory_bytes = self._core.memory_bytes
        h, w = view.depth.shape
        surface = self._core.raycast(self.K, w, h, pose, view.depth, HOLE_CELL)
        depth = np.where(surface > 0, surface, view.depth).astype(np.float32)
        return frame, View(view.pose, view.rgb, depth)

    def _wait(self) -> None:
        """The worker's job finished (waited for), its reference taken at its frame's pose
        now (its error raised)."""
        if self._job is not None:
            (_, job), self._job = self._job, None
            frame, view = job.result()
            if self._job_pose is not None:
                view = View(self._job_pose, view.rgb, view.depth)
            self._reference = (frame, view)

    def correct(self, correction: np.ndarray, poses: list) -> None:
        """The newest keyframe moved by `correction` (world to world): so does the way to the
        volume; the reference takes its frame's pose in `poses` (every frame's, corrected), as
        does the frame being fused once it is (the fusion is in the volume's world: it goes on)."""
        if self._job is not None:
            self._job_pose = poses[self._job[0]]
        self._to_volume = self._to_volume @ np.linalg.inv(correction)
        if self._reference is not None:
            frame, view = self._reference
            self._reference = (frame, View(poses[frame], view.rgb, view.depth))

    def close(self) -> None:
        """Waits for the worker's job and stops the worker."""
        self._wait()
        if self._worker is not None:
            self._worker.shutdown()

    @property
    def memory_bytes(self) -> int:
        """What the voxels took after the last fusion (without waiting for the worker's: the
        progress line asks every frame)."""
        return self._memory_bytes
