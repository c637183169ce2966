"""Recognising a place the map has seen: retrieval from what the pipeline computes anyway (the
DINOv2 patch tokens of keyframes), geometry from ORB keypoints of the keyframe's view.

- Retrieval: a global descriptor per view (the mean of its unit patch tokens, normalised),
  nearest keyframes by cosine.
- Coarse alignment, wide basin: ORB keypoints of the two views (at the tracking size) matched
  by Lowe's ratio test, each lifted to 3D with the depth under it, then RANSAC over 3-point
  rigid fits (Umeyama) gives the pose of one view in the other's camera. Keypoints, not patch
  tokens: on a Replica render whose camera jumped 0.44 m and 35 degrees, mutual matches of
  16x16 patch tokens were 1-6 geometrically right of ~30, ORB's 120-160 of 140-190.
- Dense verification: the tracker refines that pose against the keyframe's own view; a place
  is recognised only when the tracker does not call it lost, the two views overlap enough,
  enough of the pixels both see are the tracker's inliers, and enough keypoints agreed. Its
  inliers are counted among the pixels both views see, not all the query's: after a jump the
  nearest keyframe often sees half of the view, and a right alignment then has half its pixels
  as inliers (Replica render, 0.44 m jump: 0.36-0.60 of all, 0.87-0.92 of those both see).

Per keyframe it keeps its descriptor, its keypoints (a camera point and a 32-byte ORB
descriptor each) and its view at the tracking size (colour and depth): see `Place.nbytes`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from ..eval.trajectory import umeyama
from ..tracking import Tracker
from .trajectory import View

__all__ = ["Place", "PlaceIndex", "Recognised", "global_descriptor", "keypoints", "overlap",
           "ratio_matches", "ransac_rigid", "rigid_fits", "shared_inliers"]


def global_descriptor(tokens: np.ndarray) -> np.ndarray:
    """The mean of the unit patch tokens (h, w, D) of a view, of unit length."""
    t = tokens.reshape(-1, tokens.shape[-1]).astype(np.float32)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    d = t.mean(0)
    return d / max(float(np.linalg.norm(d)), 1e-12)


#: ORB keypoints per view at most; ORB's border and patch (px): 15 rather than its 31 keeps
#: keypoints near the edges of small views (160x120 has 2.2x as many, each matching as well).
#: FAST threshold 10 rather than its 20: more corners on weakly textured walls (the built-in
#: scene: 2-3x as many matches agreeing across a 10-20 degree turn; as many on real frames).
ORB_FEATURES, ORB_PATCH, ORB_FAST = 1000, 15, 10


def keypoints(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB keypoints of a view (uint8 colour) with depth under them: (n, 3) float32 camera
    points and (n, 32) uint8 descriptors (none where the image is too small or has no corners)."""
    orb = cv2.ORB_create(nfeatures=ORB_FEATURES, edgeThreshold=ORB_PATCH, patchSize=ORB_PATCH,
                         fastThreshold=ORB_FAST)
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    found, desc = orb.detectAndCompute(grey, None)
    if desc is None:
        return np.zeros((0, 3), np.float32), np.zeros((0, 32), np.uint8)
    uv = np.array([k.pt for k in found])
    H, W = depth.shape
    x = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
    y = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
    z = depth[y, x]
    ok = np.isfinite(z) & (z > 0)
    return lift(uv[ok, 0], uv[ok, 1], z[ok], K).astype(np.float32), desc[ok]


def lift(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n, 3) camera points of pixels (u, v) at depths z."""
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)


def ratio_matches(a: np.ndarray, b: np.ndarray, ratio: float) -> np.ndarray:
    """(m, 2) indices (i into a, j into b) of binary descriptors whose nearest in b (Hamming) is
    clearly nearer than the second nearest: distance < `ratio` times it (Lowe's test)."""
    if len(a) < 1 or len(b) < 2:
        return np.zeros((0, 2), dtype=int)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, b, k=2)
    pairs = [(m.queryIdx, m.trainIdx) for m, n in (x for x in knn if len(x) == 2)
             if m.distance < ratio * n.distance]
    return np.array(pairs, dtype=int).reshape(-1, 2)


def overlap(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, other: View, stride: int = 1) -> float:
    """The share of the pixels with depth of a view at `pose` that land, lifted and moved into
    `other`'s camera (same intrinsics K), inside `other` where it has depth: what both views
    see (occlusion not checked, so an upper bound). `stride`: every this-many-th pixel of every
    this-many-th row counts (an estimate, `stride`^2 times cheaper)."""
    v, u = np.nonzero(depth[::stride, ::stride] > 0)
    v, u = v * stride, u * stride
    if not len(u):
        return 0.0
    p = lift(u, v, depth[v, u], K)
    T = np.linalg.inv(other.pose) @ pose
    q = p @ T[:3, :3].T + T[:3, 3]
    ahead = q[:, 2] > 1e-6
    q = q[ahead]
    x = np.rint(q[:, 0] / q[:, 2] * K[0, 0] + K[0, 2])
    y = np.rint(q[:, 1] / q[:, 2] * K[1, 1] + K[1, 2])
    H, W = other.depth.shape
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    seen = other.depth[y[inside].astype(int), x[inside].astype(int)] > 0
    return float(seen.sum()) / len(u)


def shared_inliers(res, depth: np.ndarray, K: np.ndarray, other: View, stride: int = 1) -> tuple[float, float]:
    """For a view (its `depth`) tracked against `other` to `res` (a TrackResult): the share of
    its pixels `other` sees (`overlap`, at `res.pose`), and the tracker's inliers as a share of
    those. A right alignment of views that half overlap has only half its pixels as inliers,
    but most of those both see."""
    seen = overlap(depth, K, res.pose, other, stride)
    return seen, res.inlier_ratio / max(seen, 1e-9)


def _rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    R, t, _ = umeyama(src, dst)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def rigid_fits(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fits of many small point sets at once, dst ~ R src + t, for (h, m, 3)
    arrays (m >= 3): rotations (h, 3, 3) and translations (h, 3); `umeyama` of each set."""
    mu_s, mu_d = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    cov = np.einsum("hmi,hmj->hij", dst - mu_d, src - mu_s)
    U, _, Vt = np.linalg.svd(cov)
    S = np.ones((len(src), 3))
    S[:, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt))  # a rotation, never a reflection
    R = np.einsum("hij,hj,hjk->hik", U, S, Vt)
    return R, mu_d[:, 0] - np.einsum("hij,hj->hi", R, mu_s[:, 0])


def ransac_rigid(src: np.ndarray, dst: np.ndarray, threshold: float, iterations: int = 200,
                 rng: Optional[np.random.Generator] = None) -> tuple[Optional[np.ndarray], np.ndarray]:
    """The rigid T (4x4) with dst ~ T src for (n, 3) point pairs with outliers: the 3-point fit
    with the most pairs within `threshold` (m), refitted on them. Returns (T, inlier mask), or
    (None, all False) with fewer than 3 pairs."""
    n = len(src)
    if n < 3:
        return None, np.zeros(n, dtype=bool)
    rng = rng or np.random.default_rng(0)
    picks = rng.integers(0, n, size=(iterations, 3))
    # A degenerate sample (nearly collinear, or a pair drawn twice) fixes no rotation.
    a, b, c = (src[picks[:, k]] for k in range(3))
    picks = picks[np.linalg.norm(np.cross(b - a, c - a), axis=1) >= 1e-3]
    best = np.zeros(n, dtype=bool)
    if len(picks):
        R, t = rigid_fits(src[picks], dst[picks])
        # (hypotheses, pairs) inlier masks: every sample's fit scored at once.
        moved = np.einsum("hij,nj->hni", R, src) + t[:, None, :]
        inliers = np.linalg.norm(moved - dst, axis=2) < threshold
        best = inliers[int(np.argmax(inliers.sum(1)))]
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
    """What a keyframe keeps for recognition: its descriptor, its keypoints (camera points
    (n, 3) and ORB descriptors (n, 32)) and its view (tracking size)."""

    keyframe: int
    descriptor: np.ndarray
    points: np.ndarray
    features: np.ndarray
    view: View

    @classmethod
    def of(cls, keyframe: int, tokens: np.ndarray, view: View, K_track: np.ndarray) -> "Place":
        return cls(keyframe, global_descriptor(tokens), *keypoints(view.rgb, view.depth, K_track), view)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.descriptor, self.points, self.features, self.view.rgb,
                                      self.view.depth))


@dataclass(frozen=True)
class Recognised:
    """A view placed in the map: its pose, the keyframe it was aligned to, the descriptor
    similarity, the keypoint matches RANSAC kept (of those tried), the dense alignment's
    inliers among the pixels both views see, and the share of the view's pixels they see."""

    pose: np.ndarray
    keyframe: int
    similarity: float
    inliers: int
    matches: int
    inlier_ratio: float
    overlap: float


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
        """Coarse alignment of `query` to `place` from keypoint matches, refined by the tracker
        against the place's view; None unless both agree (see the module's docstring)."""
        c = self.config
        pairs = ratio_matches(query.features, place.features, c.place_match_ratio)
        T, inliers = ransac_rigid(query.points[pairs[:, 0]].astype(np.float64),
                                  place.points[pairs[:, 1]].astype(np.float64), c.place_ransac_threshold)
        if T is None or inliers.sum() < c.place_min_inliers:
            return None
        ref = self.tracker.prepare_reference(place.view.rgb, place.view.depth, self.K, place.view.pose)
        res = self.tracker.track(query.view.rgb, query.view.depth, self.K,
                                 init_pose=place.view.pose @ T, reference=ref)
        if res.lost:
            return None
        seen, agree = shared_inliers(res, query.view.depth, self.K, place.view)
        if seen < c.place_min_overlap or agree < c.place_min_inlier_ratio:
            return None
        return Recognised(res.pose, place.keyframe, similarity, int(inliers.sum()), len(pairs),
                          float(agree), seen)
