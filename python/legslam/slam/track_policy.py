"""Which reference a frame is tracked against, and what counts as tracked.

Every `map_every`-th frame the map rendered at the predicted pose comes first; where it covers
too little of the view, or the alignment against it fails, the last tracked frame, then the last
keyframe. The other frames come first against the last tracked frame, then the map, then the
last keyframe: a frame aligns more precisely with the frame before it than with a render of the
map (sharper, and measured a moment ago). With `map_every` 0 the map is never first: the chain
of frames runs from keyframe to keyframe, and the keyframe pose graph (covisibility edges, loops)
keeps it from drifting. A frame is lost only when all of them fail.

An alignment fails when the tracker calls it lost, and also when its residual jumps well
above the recent ones: a camera carried elsewhere can still align with
plenty of point-to-plane inliers (walls and floors are planes everywhere) but never with the
colours, so its residual is several times the usual (3x on the built-in scene).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Iterator, Optional

import numpy as np

from ..tracking import Reference, Tracker
from .trajectory import View

__all__ = ["Tracked", "TrackingPolicy"]


@dataclass(frozen=True)
class Tracked:
    """A frame's tracking outcome: its pose, "ok" or "lost" (the pose is then the prediction),
    the share of its measured pixels the map covers, and why it was lost."""

    pose: np.ndarray
    state: str
    coverage: float
    reason: Optional[str] = None


class TrackingPolicy:
    """Tracks frames (at the tracking size, with intrinsics `K`) against the map, falling back
    to recent views. `reference_alpha`: a rendered pixel is trusted where its alpha exceeds
    this; below `min_coverage` trusted pixels the render is no reference. `map_every`: the map
    comes first every this many frames (0: never), the last tracked frame first otherwise."""

    def __init__(self, tracker: Tracker, K: np.ndarray, reference_alpha: float, min_coverage: float,
                 jump_ratio: float = float("inf"), map_every: int = 1):
        self.tracker = tracker
        self.K = K
        self.reference_alpha, self.min_coverage = reference_alpha, min_coverage
        self.jump = ResidualJump(jump_ratio)
        self.map_every, self._tracked = map_every, 0
        # (render, trusted pixels, prepared reference or None until needed) of the last render
        # seen: a mapping thread's render serves many frames and is prepared once.
        self._prepared: Optional[tuple] = None
        # (view, prepared reference) of the last view prepared: the fused surface's reference
        # serves several frames in real time.
        self._view_prepared: Optional[tuple] = None

    def track(self, rgb: np.ndarray, depth: np.ndarray, predicted: np.ndarray,
              map_view: tuple, fallbacks: tuple[View, ...]) -> Tracked:
        """Tracks the frame from `predicted` against `map_view` ((pose, render), or (None,
        None) when there is none yet), then each of `fallbacks` in turn."""
        trusted = self._trusted(map_view[1])
        # What the map covers of what this frame measured: where it has no depth, a keyframe
        # could not add anything (7-Scenes' registered depth leaves the image border empty).
        measured = depth > 0
        coverage = 1.0 if trusted is None else float(trusted[measured].mean() if measured.any()
                                                     else trusted.mean())
        reason = None
        self._tracked += 1
        map_first = self.map_every > 0 and self._tracked % self.map_every == 0
        for ref in self._references(map_view, trusted, fallbacks, map_first):
            res = self.tracker.track(rgb, depth, self.K, init_pose=predicted, reference=ref)
            jumped = None if res.lost else self.jump.check(res.residual_rms)
            if not res.lost and jumped is None:
                return Tracked(res.pose, "ok", coverage)
            reason = reason or res.reason or jumped
        return Tracked(predicted, "lost", coverage, reason)

    def _references(self, map_view: tuple, trusted: Optional[np.ndarray],
                    fallbacks: tuple[View, ...], map_first: bool) -> Iterator[Reference]:
        """The references in order (the map first, or second after the first of `fallbacks`;
        never where it covers too little), each prepared only when the one before has failed:
        with the last frame first, the map's is rarely needed (preparing it costs ~5 ms)."""
        views = list(fallbacks)
        if not map_first and views:
            yield self._prepare(views.pop(0))
        if trusted is not None and trusted.mean() >= self.min_coverage:
            yield self._map_prepared(*map_view)
        for view in views:
            yield self._prepare(view)

    def _prepare(self, view: View) -> Reference:
        if self._view_prepared is None or self._view_prepared[0] is not view:
            ref = self.tracker.prepare_reference(view.rgb, view.depth, self.K, view.pose)
            self._view_prepared = (view, ref)
        return self._view_prepared[1]

    def _trusted(self, render) -> Optional[np.ndarray]:
        """The pixels where the render is trusted (None until the mapping thread's first)."""
        if render is None:
            return None
        if self._prepared is None or self._prepared[0] is not render:
            self._prepared = (render, render.alpha > self.reference_alpha, None)
        return self._prepared[1]

    def _map_prepared(self, pose, render) -> Reference:
        """The render (the one `_trusted` saw last) prepared as a reference, once."""
        _, trusted, reference = self._prepared
        if reference is None:
            alpha = render.alpha
            depth = np.where(trusted, render.depth / np.maximum(alpha, 1e-6), 0).astype(np.float32)
            rgb = np.clip(render.color / np.maximum(alpha, 1e-6)[..., None], 0, 1)
            reference = self.tracker.prepare_reference(rgb, depth, self.K, pose)
            self._prepared = (render, trusted, reference)
        return reference


class ResidualJump:
    """Whether an alignment's residual jumped above the recent ones: more than `ratio` times
    their median (of the last 30 accepted, once there are 5; against whichever reference:
    a frame aligns no worse than a render of the map). After 10 refusals in a row the
    history starts again (the scene, not the camera, changed)."""

    HISTORY, MIN_HISTORY, PATIENCE = 10, 5, 10

    def __init__(self, ratio: float):
        self.ratio = ratio
        self._history: deque = deque(maxlen=self.HISTORY)
        self._refused = 0

    def check(self, residual: float) -> Optional[str]:
        """None when `residual` is usual (and then remembered), else why not."""
        h = self._history
        if len(h) >= self.MIN_HISTORY:
            usual = float(np.median(h))
            if residual > self.ratio * usual:
                self._refused += 1
                if self._refused >= self.PATIENCE:
                    self._history.clear()
                    self._refused = 0
                return f"residual {residual:.2f} jumped above {self.ratio:g}x the recent {usual:.2f}"
        self._refused = 0
        h.append(residual)
        return None
