"""Recognising a place the map has seen, from what the pipeline computes anyway: the DINOv2
patch tokens of keyframes.

- Retrieval: a global descriptor per view (the mean of its unit patch tokens, normalised),
  nearest keyframes by cosine.
- Coarse alignment, wide basin: mutually nearest patch tokens between two views, each patch
  lifted to 3D with the median depth under it, then RANSAC over 3-point rigid fits (Umeyama)
  gives the pose of one view in the other's camera.
- Dense verification: the tracker refines that pose against the keyframe's own view; a place
  is recognised only when the tracker does not call it lost, its inlier ratio is high enough
  and enough patches agreed.

Per keyframe it keeps the tokens (float16), one 3D point per patch and the keyframe's view at
the tracking size (colour and depth): see `Place.nbytes`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..eval.trajectory import umeyama
from ..tracking import Tracker
from .trajectory import View

__all__ = ["Place", "PlaceIndex", "Recognised", "global_descriptor", "patch_points",
           "mutual_matches", "ransac_rigid"]


def global_descriptor(tokens: np.ndarray) -> np.ndarray:
    """The mean of the unit patch tokens (h, w, D) of a view, of unit length."""
    t = tokens.reshape(-1, tokens.shape[-1]).astype(np.float32)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    d = t.mean(0)
    return d / max(float(np.linalg.norm(d)), 1e-12)


def patch_points(depth: np.ndarray, K: np.ndarray, grid: tuple) -> np.ndarray:
    """(h*w, 3) camera points of a (h, w) patch grid laid over the whole image (as the encoder
    resizes the whole frame): each patch's centre at the median valid depth under it; NaN
    where under a third of the patch has depth (an edge, a hole: no reliable point)."""
    gh, gw = grid
    H, W = depth.shape
    ys = np.linspace(0, H, gh + 1).round().astype(int)
    xs = np.linspace(0, W, gw + 1).round().astype(int)
    pts = np.full((gh, gw, 3), np.nan)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for r in range(gh):
        for c in range(gw):
            cell = depth[ys[r]:ys[r + 1], xs[c]:xs[c + 1]]
            valid = cell[cell > 0]
            if valid.size * 3 < cell.size:
                continue
            z = float(np.median(valid))
            u, v = (xs[c] + xs[c + 1] - 1) / 2, (ys[r] + ys[r + 1] - 1) / 2
            pts[r, c] = ((u - cx) / fx * z, (v - cy) / fy * z, z)
    return pts.reshape(-1, 3)


def mutual_matches(a: np.ndarray, b: np.ndarray, min_similarity: float) -> np.ndarray:
    """(m, 2) indices (i into a, j into b) of rows that are each other's nearest by cosine
    (rows of unit length), at least `min_similarity` alike."""
    if not len(a) or not len(b):
        return np.zeros((0, 2), dtype=int)
    s = a.astype(np.float32) @ b.astype(np.float32).T
    ab, ba = s.argmax(1), s.argmax(0)
    i = np.flatnonzero((ba[ab] == np.arange(len(a))) & (s[np.arange(len(a)), ab] >= min_similarity))
    return np.stack([i, ab[i]], 1)


def _rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    R, t, _ = umeyama(src, dst)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def ransac_rigid(src: np.ndarray, dst: np.ndarray, threshold: float, iterations: int = 200,
                 rng: Optional[np.random.Generator] = None) -> tuple[Optional[np.ndarray], np.ndarray]:
    """The rigid T (4x4) with dst ~ T src for (n, 3) point pairs with outliers: the 3-point fit
    with the most pairs within `threshold` (m), refitted on them. Returns (T, inlier mask), or
    (None, all False) with fewer than 3 pairs."""
    n = len(src)
    if n < 3:
        return None, np.zeros(n, dtype=bool)
    rng = rng or np.random.default_rng(0)
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        pick = rng.choice(n, 3, replace=False)
        # A degenerate sample (nearly collinear) fixes no rotation.
        a, b, c = src[pick]
        if np.linalg.norm(np.cross(b - a, c - a)) < 1e-3:
            continue
        T = _rigid(src[pick], dst[pick])
        inliers = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < threshold
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < 3:
        return None, best
    for _ in range(2):  # refit on the inliers, then take the inliers of the refit
        T = _rigid(src[best], dst[best])
        again = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < threshold
        if again.sum() < 3:
            break
        best = again
    return T, best


@dataclass
class Place:
    """What a keyframe keeps for recognition: its unit patch tokens (h*w, D, float16), one
    camera point per patch (NaN where none), its descriptor and its view (tracking size)."""

    keyframe: int
    tokens: np.ndarray
    points: np.ndarray
    descriptor: np.ndarray
    view: View

    @classmethod
    def of(cls, keyframe: int, tokens: np.ndarray, view: View, K_track: np.ndarray) -> "Place":
        grid = tokens.shape[:2]
        return cls(keyframe, tokens.reshape(-1, tokens.shape[-1]).astype(np.float16),
                   patch_points(view.depth, K_track, grid), global_descriptor(tokens), view)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.tokens, self.points, self.descriptor, self.view.rgb,
                                      self.view.depth))


@dataclass(frozen=True)
class Recognised:
    """A view placed in the map: its pose, the keyframe it was aligned to, the descriptor
    similarity, the patch matches RANSAC kept (of those tried) and the dense alignment's
    inlier ratio."""

    pose: np.ndarray
    keyframe: int
    similarity: float
    inliers: int
    matches: int
    inlier_ratio: float


class PlaceIndex:
    """The places of keyframes, and the recognition of a view among them. `config` is the
    SLAMConfig (its place_* options); `tracker` does the dense verification at the tracking
    size, intrinsics `K_track`."""

    def __init__(self, config, tracker: Tracker, K_track: np.ndarray):
        self.config, self.tracker, self.K = config, tracker, K_track
        self.places: dict[int, Place] = {}

    def add(self, place: Place) -> None:
        self.places[place.keyframe] = place

    def __len__(self) -> int:
        return len(self.places)

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self.places.values())

    def set_pose(self, keyframe: int, pose: np.ndarray) -> None:
        """A keyframe moved (a loop closure): its view keeps its images, with the new pose."""
        p = self.places[keyframe]
        p.view = View(pose, p.view.rgb, p.view.depth)

    def candidates(self, descriptor: np.ndarray, among: Optional[list[int]] = None) -> list[tuple[int, float]]:
        """(keyframe, cosine) of the `place_candidates` most similar places (of `among`, all by
        default) at least `place_min_similarity` alike, best first."""
        keys = [k for k in (self.places if among is None else among) if k in self.places]
        if not keys:
            return []
        sims = np.stack([self.places[k].descriptor for k in keys]) @ descriptor
        order = np.argsort(-sims)[:self.config.place_candidates]
        return [(keys[i], float(sims[i])) for i in order if sims[i] >= self.config.place_min_similarity]

    def recognise(self, query: Place, among: Optional[list[int]] = None) -> Optional[Recognised]:
        """The pose of the view `query` (its keyframe field unused) in the map, from the first
        candidate place that verifies; None when none does."""
        for kf, similarity in self.candidates(query.descriptor, among):
            found = self.verify(query, self.places[kf], similarity)
            if found is not None:
                return found
        return None

    def verify(self, query: Place, place: Place, similarity: float = 1.0) -> Optional[Recognised]:
        """Coarse alignment of `query` to `place` from patch matches, refined by the tracker
        against the place's view; None unless both agree (see the module's docstring)."""
        c = self.config
        pairs = mutual_matches(query.tokens, place.tokens, c.place_min_token_similarity)
        ok = ~np.isnan(query.points[pairs[:, 0]]).any(1) & ~np.isnan(place.points[pairs[:, 1]]).any(1)
        pairs = pairs[ok]
        T, inliers = ransac_rigid(query.points[pairs[:, 0]], place.points[pairs[:, 1]],
                                  c.place_ransac_threshold)
        if T is None or inliers.sum() < c.place_min_inliers:
            return None
        ref = self.tracker.prepare_reference(place.view.rgb, place.view.depth, self.K, place.view.pose)
        res = self.tracker.track(query.view.rgb, query.view.depth, self.K,
                                 init_pose=place.view.pose @ T, reference=ref)
        if res.lost or res.inlier_ratio < c.place_min_inlier_ratio:
            return None
        return Recognised(res.pose, place.keyframe, similarity, int(inliers.sum()), len(pairs),
                          float(res.inlier_ratio))
