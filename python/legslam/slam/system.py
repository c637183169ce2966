"""The SLAM loop: per frame, track (`TrackingPolicy`), decide keyframes (`KeyframePolicy`),
hand keyframes to the map (`InlineMapping` or `ThreadedMapping`) and their language features
(`FeatureFeed`, asynchronous) as targets; at the end, the final mapping iterations.

    slam = SLAM(SLAMConfig(), K, width, height)
    for frame in legslam.datasets.open(path):
        step = slam.step(frame.rgb, frame.depth)
    slam.finish()
    slam.gaussian_map().save("map.ply")
"""

from __future__ import annotations

import logging
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from .. import _core
from ..datasets.base import warn_unusual_camera
from ..map import GaussianMap
from ..tracking import Tracker
from .config import SLAMConfig
from .feature_feed import FeatureFeed
from .keyframes import KeyframePolicy
from .mapping import InlineMapping, ThreadedMapping
from .track_policy import Tracked, TrackingPolicy
from .trajectory import KeyframeView, Trajectory, View

__all__ = ["SLAM", "StepResult"]

log = logging.getLogger("legslam")

# The final mapping iterations run in batches of this many: progress, and Ctrl-C, in between.
FINAL_BATCH = 25


@dataclass
class StepResult:
    index: int
    pose: np.ndarray
    #: "init" (first frame), "ok", or "lost" (pose is the motion-model prediction).
    state: str
    keyframe: bool
    reason: Optional[str] = None


class SLAM:
    """Online SLAM over frames of one camera (K for a width x height image)."""

    def __init__(self, config: SLAMConfig, K, width: int, height: int, encoder=None):
        config.check()  # again: a config's fields may have been set after it was made
        self.config = c = config
        self.K = np.asarray(K, dtype=np.float64)
        if self.K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {self.K.shape}")
        self.width, self.height = int(width), int(height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        warn_unusual_camera(self.K, self.width, self.height, "SLAM")
        self.timings: dict[str, list[float]] = {
            "preprocessing": [], "tracking": [], "mapping": [], "frame": []}
        self.feature_timings: dict[str, list[float]] = {"extraction": [], "compression": []}
        # The encoder first: it checks feature_dim before the map is sized by it.
        self._features = (FeatureFeed(c, lambda kf, grid: self._mapping.set_features(kf, grid),
                                      self.feature_timings, encoder) if c.features else None)
        self.depth_range = (c.mapper.depth_min, c.mapper.depth_max)
        #: Frames without any depth measurement, and frames whose depth lay mostly outside
        #: `depth_range` (dropped: see `_prepare`).
        self.frames_without_depth = self.frames_depth_out_of_range = 0
        s = min(1.0, c.track_width / self.width)
        self.K_track, *size = _core.scaled_intrinsics(self.K, self.width, self.height, s)
        self.track_size = tuple(size)
        threads = (c.mapping_threads or os.cpu_count() or 2) if c.mapping_thread else None
        self.mapper = _core.MapperCore(c.mapper_options(self.width), threads=threads)
        tracker = Tracker(threads=1 if c.mapping_thread else None,
                          **c.tracker_options(*self.track_size))
        self.tracking = TrackingPolicy(tracker, self.K_track, c.reference_alpha, c.min_reference_coverage)
        self.keyframes = KeyframePolicy(c)
        self.trajectory = Trajectory()
        self.keyframe_frames: list[int] = []
        self._last_keyframe: Optional[KeyframeView] = None
        self._last_tracked: Optional[View] = None
        self._mapping = (ThreadedMapping(self.mapper, self.K_track, self.track_size, c.mapping_batch)
                         if c.mapping_thread else self._inline_mapping())
        self._final_stats: list = []

    def _inline_mapping(self) -> InlineMapping:
        c = self.config
        return InlineMapping(self.mapper, self.K_track, self.track_size, c.map_iters_keyframe,
                             c.map_iters_frame)

    # --- per frame ---------------------------------------------------------------------------

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> StepResult:
        i = len(self.trajectory)
        with self._timed("frame"):
            with self._timed("preprocessing"):
                rgb, depth, small = self._prepare(i, rgb, depth)
            with self._timed("tracking"):
                tracked = self._track(small)
            with self._timed("mapping"):
                keyframe = self._map(i, rgb, depth, small, tracked)
            self._record(tracked.pose, tracked.state)
        return StepResult(i, tracked.pose, tracked.state, keyframe, tracked.reason)

    def skip(self) -> StepResult:
        """Records a frame that could not be read as lost: the motion model's pose, no mapping."""
        if not self.trajectory.poses:
            raise ValueError("the first frame cannot be skipped: it places the map")
        pose = self.trajectory.predict(self._last_tracked.pose)
        self._record(pose, "lost")
        return StepResult(len(self.trajectory) - 1, pose, "lost", False, "unreadable")

    @contextmanager
    def _timed(self, stage: str):
        t0 = time.perf_counter()
        yield
        self.timings[stage].append(1e3 * (time.perf_counter() - t0))

    def _prepare(self, i: int, rgb, depth) -> tuple:
        """The frame checked, its depth kept only within `depth_range` (everything downstream
        sees the same valid depth), and a View of it at the tracking size (posed once tracked)."""
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"frame {i}: rgb must be {self.height}x{self.width}x3 uint8, got "
                             f"{rgb.dtype} {rgb.shape}")
        if depth.shape != (self.height, self.width):
            raise ValueError(f"frame {i}: depth must be {self.height}x{self.width}, got {depth.shape}")
        if depth.dtype.kind != "f":
            raise ValueError(f"frame {i}: depth must be float metres, got {depth.dtype} (sensor "
                             "units: divide by the depth scale, e.g. 1000 for millimetres)")
        depth = self._depth_in_range(i, depth.astype(np.float32))
        size = self.track_size
        small = View(None, cv2.resize(rgb, size, interpolation=cv2.INTER_AREA),
                     cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST))
        return rgb, depth, small

    def _depth_in_range(self, i: int, depth: np.ndarray) -> np.ndarray:
        """Depth outside `depth_range` (and NaN, inf, <= 0) as 0. A frame whose measured depth
        lies mostly outside the range is dropped whole: its scale is likely wrong, and a map
        grown from it would be ruined."""
        low, high = self.depth_range
        measured = np.isfinite(depth) & (depth > 0)
        kept = measured & (depth >= low) & (depth <= high)
        n = int(measured.sum())
        if n == 0:
            if not self.frames_without_depth:
                log.warning("frame %d has no valid depth, so it cannot grow the map (frames like it "
                            "are counted in metrics.json)", i)
            self.frames_without_depth += 1
        elif kept.sum() < 0.5 * n:
            median = float(np.median(depth[measured]))
            if not self.frames_depth_out_of_range:
                why = ("it looks like millimetres, not metres" if median > high and low <= median / 1000 <= high
                       else "check the depth's unit and scale")
                log.warning("frame %d: %.0f%% of its depth (median %.4g m) lies outside depth_min..depth_max "
                            "= %g..%g m: %s. Frames like it are kept out of the map (counted in "
                            "metrics.json)", i, 100 * (1 - kept.sum() / n), median, low, high, why)
            self.frames_depth_out_of_range += 1
            kept[:] = False
        return np.where(kept, depth, 0).astype(np.float32)

    def _track(self, small: View) -> Tracked:
        if self._mapping.empty:
            # Nothing to track against yet (first frame, or no valid depth so far): this frame
            # starts the map where the camera last was.
            poses = self.trajectory.poses
            return Tracked(poses[-1] if poses else np.eye(4), "init", 0.0)
        predicted = self.trajectory.predict(self._last_tracked.pose)
        fallbacks = (self._last_tracked, self._last_keyframe)
        return self.tracking.track(small.rgb, small.depth, predicted,
                                   self._mapping.reference(predicted), fallbacks)

    def _map(self, i: int, rgb, depth, small: View, tracked: Tracked) -> bool:
        """Adds a keyframe if the policy wants one and trains (or lets the thread train);
        nothing from a lost frame. Returns whether the frame became a keyframe."""
        if tracked.state == "lost":
            if self._features is not None:
                self._features.collect()
            return False
        keyframe = self.keyframes.wants(
            i, tracked.pose, tracked.coverage, self._last_keyframe, self._mapping.empty,
            coverage_counts=self._mapping.keeps_up(self.config.map_iters_keyframe))
        if keyframe:
            kf_id = self._mapping.add_keyframe(rgb.astype(np.float32) / 255.0, depth, self.K,
                                               tracked.pose)
            self._last_keyframe = KeyframeView(tracked.pose, small.rgb, small.depth, frame=i)
            self.keyframe_frames.append(i)
            if self._features is not None:
                self._features.submit(kf_id, rgb)
        if self._features is not None:
            self._features.collect()
        self._mapping.after_frame(tracked.pose, keyframe)
        self._last_tracked = View(tracked.pose, small.rgb, small.depth)
        return keyframe

    def _record(self, pose: np.ndarray, state: str) -> None:
        self.trajectory.record(pose, state, len(self.keyframe_frames) - 1, self._last_keyframe.pose)

    # --- state ---------------------------------------------------------------------------------

    @property
    def poses(self) -> list[np.ndarray]:
        return self.trajectory.poses

    @property
    def states(self) -> list[str]:
        return self.trajectory.states

    @property
    def mapping(self):
        """Where keyframes go: the mapping thread while it runs, else inline mapping."""
        return self._mapping

    @property
    def mapping_in_thread(self) -> bool:
        """Whether a mapping thread owns the map now (until `finish`)."""
        return isinstance(self._mapping, ThreadedMapping)

    @property
    def mapping_stats(self) -> list:
        """The engine's report of every training call, the final iterations' last."""
        return self._mapping.stats + self._final_stats

    @property
    def reference_render_s(self) -> float:
        """With a mapping thread: seconds it spent rendering tracking references."""
        return self._mapping.reference_s

    @property
    def num_gaussians(self) -> int:
        return self._mapping.num_gaussians

    # --- end of sequence ---------------------------------------------------------------------

    def finish(self, train: bool = True, progress=None) -> None:
        """Stops the mapping thread, waits for outstanding keyframe features and runs the final
        mapping iterations (unless `train` is false: a run cut short keeps the map it has), in
        batches, calling `progress(done, total)` after each; Ctrl-C stops between batches."""
        if self.mapping_in_thread:
            threaded = self._mapping
            threaded.stop()
            self._mapping = self._inline_mapping()
            self._mapping.stats, self._mapping.reference_s = threaded.stats, threaded.reference_s
        if self._features is not None:
            self._features.drain()
        total = self.config.final_iters if train else 0
        for done in range(0, total, FINAL_BATCH):
            # Over every keyframe: the map is used (and evaluated) over the whole sequence.
            n = min(FINAL_BATCH, total - done)
            self._final_stats.append(self.mapper.train(n, window=self.mapper.num_keyframes))
            if progress is not None:
                progress(done + n, total)
        self.trajectory.follow(self.mapper.keyframe_poses())

    def frame_exposures(self) -> Optional[np.ndarray]:
        """Per frame, the exposure (n x 2 x 3: per channel gain and bias, from the map's
        colour to the camera's) of the keyframe it was tracked after; None when exposures are
        not trained (mapper option `exposure_lr`)."""
        self._check_idle()
        if not self.mapper.config()["exposure_lr"]:
            return None
        kf = self.mapper.keyframe_exposures()
        n = len(self.trajectory)
        return np.stack([kf[self.trajectory.keyframe_of(i)] for i in range(n)]) if n else None

    def _check_idle(self) -> None:
        if self.mapping_in_thread:
            raise RuntimeError("the mapping thread owns the map while SLAM runs: call finish() first")

    def gaussian_map(self) -> GaussianMap:
        self._check_idle()
        return GaussianMap(**self.mapper.export())

    @property
    def pca(self):
        return None if self._features is None else self._features.pca

    def render(self, pose, K=None, width=None, height=None, features=False) -> dict:
        """Renders the live map: a dict of colour, depth, alpha (and features if asked)."""
        self._check_idle()
        K = self.K if K is None else np.asarray(K, dtype=np.float64)
        r = self.mapper.render(np.asarray(pose, dtype=np.float64), K, width or self.width,
                               height or self.height, features)
        out = {"color": r.color, "depth": r.depth, "alpha": r.alpha}
        if r.features is not None:
            out["features"] = r.features
        return out
