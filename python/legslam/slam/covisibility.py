"""Covisibility edges of the keyframe pose graph: each new keyframe aligned with the older
keyframes that see most of the same surfaces.

A keyframe's pose is the end of a chain of alignments (frame to frame, frame to the map), each
a little off; a direct alignment with a keyframe that saw the same surfaces skips the chain,
and the pose graph (`LoopClosure`) weighs it against the odometry edges. The alignment is the
tracker's own (point-to-plane and photometric): with depth alone, a view of a few planes
(walls, floor) slides along them and still counts its points as inliers, and on 7-Scenes the
depth-only edges moved keyframes to where colour agreed worse (the map 1.5 dB worse), though
nearer the dataset's depth-fused ground truth.

Candidates are the older keyframes facing the same way (optical axes within 90 degrees) that
the new keyframe's depth lands in on at least `covisibility_min_overlap` of its pixels, except
the one it was tracked after (its odometry edge is there already); the `covisibility_edges`
with the most overlap are aligned. An alignment counts when the tracker does not call it lost
and at least `place_min_inlier_ratio` of the pixels both views see are its inliers, as for a
recognised place.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..tracking import Tracker
from .place_recognition import overlap, shared_inliers
from .pose_graph import relative
from .trajectory import View

__all__ = ["Covisibility", "Covisible"]

#: Overlap of candidates is estimated on every 4th pixel of every 4th row.
OVERLAP_STRIDE = 4


@dataclass(frozen=True)
class Covisible:
    """An alignment of keyframe `old` with keyframe `new`: `measurement` is old's pose in new's
    frame; the tracker's inliers among the pixels both see, and the share of old's view new
    sees."""

    new: int
    old: int
    measurement: np.ndarray
    inlier_ratio: float
    overlap: float


class Covisibility:
    """Keyframe views at the tracking size (intrinsics `K`), and their alignments. `config`:
    the SLAMConfig; `tracker`: the SLAM's tracker."""

    def __init__(self, config, tracker: Tracker, K: np.ndarray):
        self.config, self.tracker, self.K = config, tracker, K
        self._views: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, rgb: np.ndarray, depth: np.ndarray) -> int:
        """The next keyframe's view; returns its index."""
        self._views.append((rgb, depth))
        return len(self._views) - 1

    def candidates(self, new: int, poses: list[np.ndarray], exclude: Optional[int]) -> list[tuple[int, float]]:
        """(keyframe, overlap) of the older keyframes worth aligning with keyframe `new`, most
        overlap first, at most `covisibility_edges` of them."""
        c = self.config
        older = [k for k in range(new) if k != exclude]
        if not older or c.covisibility_edges == 0:
            return []
        pose, depth = poses[new], self._views[new][1]
        axes = np.stack([poses[k][:3, 2] for k in older])
        facing = [k for k, cos in zip(older, axes @ pose[:3, 2]) if cos > 0]
        seen = [(k, overlap(depth, self.K, pose, View(poses[k], *self._views[k]), OVERLAP_STRIDE))
                for k in facing]
        seen = [(k, o) for k, o in seen if o >= c.covisibility_min_overlap]
        return sorted(seen, key=lambda ko: -ko[1])[:c.covisibility_edges]

    def edges(self, new: int, poses: list[np.ndarray], exclude: Optional[int] = None) -> list[Covisible]:
        """Keyframe `new` (at poses[new]) aligned with its candidates (see `candidates`): the
        alignments that verify."""
        found = []
        candidates = self.candidates(new, poses, exclude)
        if not candidates:
            return found
        pose = poses[new]
        rgb, depth = self._views[new]
        reference = self.tracker.prepare_reference(rgb, depth, self.K, pose)
        for old, _ in candidates:
            old_rgb, old_depth = self._views[old]
            res = self.tracker.track(old_rgb, old_depth, self.K, init_pose=poses[old], reference=reference)
            if res.lost:
                continue
            seen, agree = shared_inliers(res, old_depth, self.K, View(pose, rgb, depth), OVERLAP_STRIDE)
            if agree < self.config.place_min_inlier_ratio:
                continue
            found.append(Covisible(new, old, relative(pose, res.pose), float(agree), seen))
        return found
