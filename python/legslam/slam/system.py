"""The SLAM loop: per frame, track (`TrackingPolicy`; a lost frame is placed again by the
`Relocaliser`), decide keyframes (`KeyframePolicy`), hand keyframes to the map
(`InlineMapping` or `ThreadedMapping`) and their language features (`FeatureFeed`,
asynchronous) as targets; each keyframe is aligned with the older ones that see the same
surfaces (`Covisibility`), and keyframes' patch tokens become places (`PlaceIndex`) that close
loops, both edges of the keyframe pose graph (`LoopClosure`: the map and the trajectory move
with the corrected keyframes); at the end, the final mapping iterations.

    slam = SLAM(SLAMConfig(), K, width, height)
    for frame in legslam.datasets.open(path):
        step = slam.step(frame.rgb, frame.depth)
    slam.finish()
    slam.gaussian_map().save("map.ply")
"""

from __future__ import annotations

import logging
import math
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
from .covisibility import Covisibility
from .feature_feed import FeatureFeed
from .keyframes import KeyframePolicy
from .loop_closure import LoopClosure
from .mapping import InlineMapping, ThreadedMapping
from .place_recognition import Place, PlaceIndex
from .relocalise import Relocaliser
from .surface import Surface
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
    #: "init" (first frame), "ok", "relocalised" (placed again after a loss), or "lost" (pose
    #: is the motion-model prediction).
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
            "preprocessing": [], "tracking": [], "relocalisation": [], "mapping": [], "frame": []}
        #: Per keyframe: ms spent aligning it with covisible keyframes (within "mapping").
        self.covisibility_ms: list[float] = []
        self.feature_timings: dict[str, list[float]] = {"extraction": [], "compression": []}
        # The encoder first: it checks feature_dim before the map is sized by it.
        self._features = self._feature_feed(encoder)
        places = self._features is not None and c.place_recognition
        self.depth_range = (c.mapper.depth_min, c.mapper.depth_max)
        #: Frames without any depth measurement, and frames whose depth lay mostly outside
        #: `depth_range` (dropped: see `_prepare`).
        self.frames_without_depth = self.frames_depth_out_of_range = 0
        #: The frame at which the map first held `mapper.max_gaussians` (None: never).
        self.map_full_at: Optional[int] = None
        s = min(1.0, c.track_width / self.width)
        self.K_track, *size = _core.scaled_intrinsics(self.K, self.width, self.height, s)
        self.track_size = tuple(size)
        threads = (c.mapping_threads or os.cpu_count() or 2) if c.mapping_thread else None
        # In real time the mapping threads give way to the tracker: a frame waits less.
        self.mapper = _core.MapperCore(c.mapper_options(self.width), threads=threads,
                                       background=c.mapping_thread)
        tracker = Tracker(threads=1 if c.mapping_thread else None,
                          **c.tracker_options(*self.track_size))
        self.tracking = TrackingPolicy(tracker, self.K_track, c.reference_alpha, c.min_reference_coverage,
                                       c.jump_residual_ratio if c.relocalise else float("inf"),
                                       c.map_reference_every)
        self.places = PlaceIndex(c, tracker, self.K_track) if places else None
        self.relocaliser = (Relocaliser(self.places, self._features.encoder, self.K_track)
                            if places and c.relocalise else None)
        self.covisibility = (Covisibility(c, Tracker(threads=1 if c.mapping_thread else None,
                                                     **c.covisibility_tracker_options(*self.track_size)),
                                          self.K_track) if c.covisibility_edges else None)
        loops = places and c.loop_closure
        self.loops = (LoopClosure(c, self.places if loops else None)
                      if loops or self.covisibility is not None else None)
        # Keyframe views waiting for their patch tokens to become places; the keyframe the
        # next one is tracked after (the pose graph's odometry edge).
        self._unplaced: dict[int, KeyframeView] = {}
        self._tracked_after: Optional[int] = None
        self._corrections: Optional[np.ndarray] = None  # of loops closed, not applied yet
        self.surface = (Surface(c.surface_voxel, c.surface_truncation, self.depth_range, self.K_track,
                                c.realtime_surface_every if c.mapping_thread else c.surface_every,
                                background=c.mapping_thread, threads=threads)
                        if c.surface_voxel > 0 and (c.surface_realtime or not c.mapping_thread) else None)
        self.keyframes = KeyframePolicy(c)
        self.trajectory = Trajectory()
        self.keyframe_frames: list[int] = []
        #: Why each keyframe was made (`keyframes.REASONS`), as `keyframe_frames`.
        self.keyframe_reasons: list[str] = []
        #: Per frame tracked against the fused surface: how many frames old its reference was
        #: (1: the frame before's; more where the real-time worker was still busy).
        self.reference_ages: list[int] = []
        self._last_keyframe: Optional[KeyframeView] = None
        self._last_tracked: Optional[View] = None
        self._mapping = (ThreadedMapping(self.mapper, self.K_track, self.track_size, c.mapping_batch,
                                         c.realtime_lr_scales(), c.map_iters_keyframe)
                         if c.mapping_thread else self._inline_mapping())
        self._final_stats: list = []
        self._first_frame_at: Optional[float] = None

    def _feature_feed(self, encoder) -> Optional[FeatureFeed]:
        """The keyframes' encoder: language features, place recognition, or both. Without
        language features a missing encoder only turns place recognition off (warned)."""
        c = self.config
        sink = (lambda kf, grid: self._mapping.set_features(kf, grid)) if c.features else None
        tokens = self._place_seen if c.place_recognition else None
        if not (c.features or c.place_recognition):
            return None
        try:
            return FeatureFeed(c, sink, self.feature_timings, encoder, tokens=tokens, settled=not c.mapping_thread)
        except FileNotFoundError as e:
            if c.features:
                raise
            log.warning("no relocalisation or loop closure: they need the image encoder (%s)", e)
            return None

    def _inline_mapping(self) -> InlineMapping:
        c = self.config
        return InlineMapping(self.mapper, self.K_track, self.track_size, c.map_iters_keyframe,
                             c.map_iters_frame)

    # --- per frame ---------------------------------------------------------------------------

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> StepResult:
        i = len(self.trajectory)
        if self._first_frame_at is None:
            self._first_frame_at = time.perf_counter()
        with self._timed("frame"):
            with self._timed("preprocessing"):
                rgb, depth, small = self._prepare(i, rgb, depth)
            with self._timed("tracking"):
                tracked = self._track(small)
            if tracked.state == "lost" and self.relocaliser is not None:
                with self._timed("relocalisation"):
                    tracked = self._relocalise(i, rgb, small, tracked)
            with self._timed("mapping"):
                keyframe = self._map(i, rgb, depth, small, tracked)
                # The pose graph's corrections (loops, covisibility) come before training:
                # trained at a keyframe's old pose, the map would fit it there and then move.
                self._record(tracked.pose, tracked.state)
                self._correct()
                if tracked.state != "lost":
                    self._mapping.after_frame(self.trajectory.poses[i], keyframe)
        return StepResult(i, self.trajectory.poses[i], tracked.state, keyframe, tracked.reason)

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
        fused = None if self.surface is None else self.surface.reference
        if fused is not None:
            self.reference_ages.append(len(self.trajectory) - fused[0])
        last = self._last_tracked if fused is None else fused[1]
        fallbacks = (last, self._last_keyframe)
        return self.tracking.track(small.rgb, small.depth, predicted,
                                   self._mapping.reference(predicted), fallbacks)

    def _relocalise(self, i: int, rgb, small: View, tracked: Tracked) -> Tracked:
        found = self.relocaliser.lost(i, rgb, small)
        if found is None:
            return tracked
        self._tracked_after = found.keyframe
        return Tracked(found.pose, "relocalised", tracked.coverage)

    def _map(self, i: int, rgb, depth, small: View, tracked: Tracked) -> bool:
        """Adds a keyframe if the policy wants one (never from a lost frame). Returns whether
        the frame became a keyframe."""
        if tracked.state == "lost":
            if self._features is not None:
                self._features.collect()
            return False
        if self.relocaliser is not None:
            self.relocaliser.tracked()
        why = self.keyframes.wants(
            i, tracked.pose, tracked.coverage, self._last_keyframe, self._mapping.empty,
            coverage_counts=self._mapping.keeps_up())
        keyframe = why is not None
        if keyframe:
            kf_id = self._mapping.add_keyframe(rgb.astype(np.float32) / 255.0, depth, self.K,
                                               tracked.pose)
            self._last_keyframe = KeyframeView(tracked.pose, small.rgb, small.depth, frame=i)
            self.keyframe_frames.append(i)
            self.keyframe_reasons.append(why)
            encoded = self._features is not None and self._encodes(len(self.keyframe_frames) - 1)
            self._keyframe_made(kf_id, self._last_keyframe, encoded)
            if encoded:
                self._features.submit(kf_id, rgb)
        if self._features is not None:
            self._features.collect()
        self._check_map_full(i)
        self._last_tracked = View(tracked.pose, small.rgb, small.depth)
        if self.surface is not None:
            self.surface.add(i, self._last_tracked, now=tracked.state == "relocalised")
        return keyframe

    def _check_map_full(self, i: int) -> None:
        """Says once when the map reaches its cap: from then on, new keyframes seed Gaussians
        only where pruning has freed room, so a camera walking on into new rooms leaves them
        nearly empty."""
        cap = self.config.mapper.max_gaussians
        if self.map_full_at is None and self._mapping.num_gaussians >= cap:
            self.map_full_at = i
            log.warning("frame %d: the map holds its maximum of %d Gaussians (mapper option "
                        "max_gaussians), so surfaces seen from now on get new Gaussians only where "
                        "pruning frees room; for a larger scene raise it (each 100k Gaussians take "
                        "about 200 MB and lengthen every mapping iteration)", i, cap)

    def _encodes(self, n: int) -> bool:
        """Whether the `n`-th keyframe (from 0) is encoded: every one synchronously, every
        `realtime_feature_every`-th in real time."""
        c = self.config
        return not c.mapping_thread or n % c.realtime_feature_every == 0

    def _keyframe_made(self, kf_id: int, view: KeyframeView, encoded: bool) -> None:
        """A new keyframe: a node of the pose graph with edges to the keyframes that see the same
        surfaces, and a place once its tokens come (if it is `encoded`)."""
        if self.places is not None and encoded:
            self._unplaced[kf_id] = view
        if self.loops is not None:
            self.loops.add_keyframe(view.frame, view.pose, self._tracked_after)
        if self.covisibility is not None:
            t0 = time.perf_counter()
            if self.covisibility.add(view.rgb, view.depth) != kf_id:
                raise RuntimeError("covisibility views out of step with the keyframes")
            found = self.covisibility.edges(kf_id, self.loops.poses, exclude=self._tracked_after)
            self._will_correct(self.loops.add_covisible(found))
            self.covisibility_ms.append(1e3 * (time.perf_counter() - t0))
        self._tracked_after = kf_id

    def _place_seen(self, kf_id: int, tokens: np.ndarray) -> None:
        """A keyframe's patch tokens came: its place, and a loop it closes, if any."""
        view = self._unplaced.pop(kf_id)
        pose = view.pose if self.loops is None else self.loops.poses[kf_id]
        self.places.add(Place.of(kf_id, tokens, View(pose, view.rgb, view.depth), self.K_track))
        if self.loops is None:
            return
        t0 = time.perf_counter()
        found = self.loops.detect(kf_id)
        if found is not None:
            self._will_correct(self.loops.close(kf_id, found, 1e3 * (time.perf_counter() - t0)))

    def _will_correct(self, corrections: Optional[np.ndarray]) -> None:
        """Keyframe corrections of the pose graph, applied once the frame is recorded."""
        if corrections is not None:
            self._corrections = (corrections if self._corrections is None
                                 else corrections @ self._corrections)

    def _correct(self) -> None:
        """Moves keyframes by the pose graph's corrections (the map's Gaussians with them),
        and every frame and view with its keyframe."""
        if self._corrections is None:
            return
        corrections, self._corrections = self._corrections, None
        self._mapping.correct_keyframes(corrections)
        poses = np.stack(self.loops.poses)
        for k in self.places.places if self.places is not None else ():
            self.places.set_pose(k, poses[k])
        self.trajectory.follow(poses)
        if self.surface is not None:
            self.surface.correct(corrections[-1], self.trajectory.poses)
        last = self._last_keyframe
        self._last_keyframe = KeyframeView(poses[-1], last.rgb, last.depth, frame=last.frame)
        tracked = max(i for i, s in enumerate(self.trajectory.states) if s != "lost")
        self._last_tracked = View(self.trajectory.poses[tracked], self._last_tracked.rgb,
                                  self._last_tracked.depth)

    def _record(self, pose: np.ndarray, state: str) -> None:
        self.trajectory.record(pose, state, len(self.keyframe_frames) - 1, self._last_keyframe.pose)

    # --- state ---------------------------------------------------------------------------------

    @property
    def poses(self) -> list[np.ndarray]:
        return self.trajectory.poses

    @property
    def states(self) -> list[str]:
        return self.trajectory.states

    def trajectory_events(self) -> dict:
        """For metrics.json: the relocalisations, the loops closed and the loop edges rejected
        (frame, keyframes, correction size), what the keyframes' places and the fused surface
        take in memory, and how old the fused surface's references were (`frames`: how many
        frames were tracked against a reference of each age)."""
        out = {}
        if self.relocaliser is not None:
            out["relocalisations"] = [e.as_dict() for e in self.relocaliser.events]
        if self.loops is not None and self.loops.places is not None:
            out["loop_closures"] = [e.as_dict() for e in self.loops.events]
            out["rejected_loops"] = list(self.loops.rejected)
        if self.covisibility is not None:
            out["covisibility_edges"] = self.loops.covisible
            out["rejected_covisibility_edges"] = list(self.loops.rejected_covisible)
        if self.places is not None:
            out["place_memory_mb"] = round(self.places.nbytes / 2 ** 20, 2)
        if self.surface is not None:
            out["surface_memory_mb"] = round(self.surface.memory_bytes / 2 ** 20, 2)
            ages, counts = np.unique(self.reference_ages, return_counts=True)
            out["surface_reference_age"] = {
                "mean": round(float(np.mean(self.reference_ages)), 3) if self.reference_ages else None,
                "frames": {str(a): int(n) for a, n in zip(ages, counts)}}
        return out

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
    def final_mapping_stats(self) -> list:
        """The engine's report of the final iterations' training calls."""
        return self._final_stats

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
        mapping iterations (unless `train` is false: a run cut short keeps the map it has):
        `final_iters`, plus `final_iters_per_frame` a frame when synchronous or, in real time, as
        long as `final_time` allows and as many as `realtime_iters_floor` asks, each group's
        learning rate annealed from where the frames left it (the mapper's; in real time, its
        real-time scale of it) to `final_lr_factor` times that; in batches, calling
        `progress(done, total)` after each (total None while a real-time run trains on for
        `final_time`, then (done, done) once); Ctrl-C stops between batches."""
        in_thread = self.mapping_in_thread
        if in_thread:
            threaded = self._mapping
            threaded.stop()
            self._mapping = self._inline_mapping()
            self._mapping.stats, self._mapping.reference_s = threaded.stats, threaded.reference_s
        if self.surface is not None:
            self.surface.close()
        if self._features is not None:
            self._features.drain()
            self._correct()
        c = self.config
        # Synchronous: the iterations deferred from the frames, too.
        total = (c.final_iters if in_thread else self._synchronous_final_iterations()) if train else 0
        if train and in_thread:
            # Real time: at least the floor's share of a synchronous run's iterations in all.
            live = sum(s.iterations for s in self._mapping.stats)
            total = max(total, math.ceil(c.realtime_iters_floor * self._synchronous_iterations()) - live)
        # Real time: as many more as fit in `final_time` of the time the frames took.
        budget = (c.final_time * (time.perf_counter() - self._first_frame_at)
                  if train and in_thread and self._first_frame_at is not None else 0.0)
        # Then the count is known only once the time is spent.
        open_ended = budget > 0
        began, done = time.perf_counter(), 0
        # Each group's learning rate anneals from the scale the frames trained it with to
        # `final_lr_factor` times that scale.
        start = self.config.realtime_lr_scales()
        if not in_thread:
            start = dict.fromkeys(start, 1.0)
        factor = self.config.final_lr_factor
        while done < total or time.perf_counter() - began < budget:
            # Over every keyframe: the map is used (and evaluated) over the whole sequence.
            n = min(FINAL_BATCH, total - done) if done < total else FINAL_BATCH
            # How far along (below 1 inside the loop, which ends once both the count and the
            # time are spent).
            parts = ([done / total] if total else []) + \
                ([(time.perf_counter() - began) / budget] if open_ended else [])
            scale = {g: s * factor ** min(parts) for g, s in start.items()}
            self._final_stats.append(self.mapper.train(n, window=self.mapper.num_keyframes,
                                                       lr_scale=scale))
            done += n
            if progress is not None:
                progress(done, None if open_ended else total)
        if progress is not None and open_ended:
            progress(done, done)
        self.trajectory.follow(self.mapper.keyframe_poses())

    def _synchronous_final_iterations(self) -> int:
        """The final mapping iterations of a synchronous run over the frames so far."""
        c = self.config
        return c.final_iters + round(c.final_iters_per_frame * len(self.trajectory))

    def _synchronous_iterations(self) -> int:
        """The mapping iterations a synchronous run over the frames so far would make."""
        c, frames, keyframes = self.config, len(self.trajectory), len(self.keyframe_frames)
        return (c.map_iters_keyframe * keyframes + c.map_iters_frame * (frames - keyframes)
                + self._synchronous_final_iterations())

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
