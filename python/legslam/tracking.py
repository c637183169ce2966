"""Dense RGB-D camera tracking (the engine's `track` module).

Aligns an RGB-D frame to a reference RGB-D view with a known pose (a previous keyframe, or
colour + depth rendered from the map) by Gauss-Newton over SE(3) on point-to-plane +
photometric residuals, coarse to fine. Every result carries quality signals and a `lost`
verdict.

Conventions: images are HxWx3 uint8 RGB (float32 in [0, 1] is accepted too, e.g. renders),
depth is HxW float32 metres with 0 = invalid, K is the 3x3 pinhole matrix of that image, and
poses are 4x4 camera-to-world matrices with OpenCV axes (x right, y down, z forward).

    >>> tracker = Tracker(finest_level=1)
    >>> res = tracker.track(rgb, depth, K, ref_rgb, ref_depth, ref_pose)
    >>> if not res.lost: pose = res.pose

    >>> odo = Odometry()                      # frame-to-frame, constant-velocity prior
    >>> for f in frames: step = odo.step(f.rgb, f.depth, f.K); traj.append(step.pose)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from legslam import _core

__all__ = ["DEFAULT_CONFIG", "fitting_levels", "TrackResult", "Tracker", "Reference", "Odometry",
           "OdometryStep"]

#: The engine's default tracker options (`Tracker(**overrides)` changes any of them).
DEFAULT_CONFIG: dict[str, Any] = dict(_core.tracker_default_config())


def fitting_levels(width: int, height: int, finest_level: int) -> int:
    """The default number of pyramid levels, fewer where the coarsest would be under 8 pixels
    (the engine refuses that) for a width x height image tracked from `finest_level`."""
    smallest = min(width, height) >> finest_level
    return min(DEFAULT_CONFIG["levels"], max(1, int(np.log2(max(smallest, 8) / 8)) + 1))


@dataclass(frozen=True)
class TrackResult:
    """Outcome of one alignment.

    pose: 4x4 camera-to-world estimate (when `lost`, the best estimate, not to be trusted).
    residual_rms: RMS of the Huber-normalised joint residual (dimensionless).
    geometric_rms: RMS point-to-plane distance of the inliers (m).
    photometric_rms: RMS intensity residual (intensity in [0, 1]).
    inlier_ratio: inlier correspondences / frame pixels with valid depth (finest level).
    inliers: number of inlier correspondences (finest level).
    condition: condition number of the normal equations (inf if singular).
    iterations: Gauss-Newton iterations over all levels.
    gain: estimated exposure gain applied to the frame intensity (1 if not estimated).
    lost: the alignment cannot be trusted; `reason` says why.
    """

    pose: np.ndarray
    residual_rms: float
    geometric_rms: float
    photometric_rms: float
    inlier_ratio: float
    inliers: int
    condition: float
    iterations: int
    gain: float
    lost: bool
    reason: Optional[str]

    @classmethod
    def _from_dict(cls, d: dict) -> "TrackResult":
        return cls(**d)


@dataclass(frozen=True)
class OdometryStep:
    """One frame of `Odometry`: the pose assigned to it (tracked, or the constant-velocity
    prediction when lost), the prediction, and the alignment (None for the first frame)."""

    pose: np.ndarray
    predicted: np.ndarray
    result: Optional[TrackResult]

    @property
    def lost(self) -> bool:
        return self.result is not None and self.result.lost


def _rgb(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{name} must be an HxWx3 RGB image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if np.issubdtype(a.dtype, np.floating):
        return np.ascontiguousarray(a, dtype=np.float32)
    raise ValueError(f"{name} must be uint8 (or float in [0, 1]), got dtype {a.dtype}")


def _depth(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be an HxW depth map in metres, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be float32 metres, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _mat(a, n: int, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n, n):
        raise ValueError(f"{name} must be {n}x{n}, got shape {a.shape}")
    return np.ascontiguousarray(a)


class Reference:
    """A reference view prepared once (pyramids, gradients, normals) for many `track` calls,
    e.g. colour + depth rendered from the map at the predicted pose."""

    def __init__(self, core: Any):
        self._core = core

    @property
    def pose(self) -> np.ndarray:
        return self._core.pose


class Tracker:
    """Dense RGB-D tracker. Keyword arguments override `DEFAULT_CONFIG`: `levels`,
    `finest_level`, `iterations` (per level, finest first), `min_depth`, `max_depth`,
    `max_depth_diff`, `geometric_huber`, `photometric_huber`, `photometric_weight`,
    `estimate_gain`, `min_gradient`, `convergence_eps`, `inlier_threshold`, `min_inlier_ratio`, `min_inliers`,
    `max_condition`, `max_translation`, `max_rotation_deg`. Unknown or invalid options raise
    ValueError. `threads`: run on a thread pool of this many threads of its own (default: the
    engine's shared pool)."""

    def __init__(self, threads: int | None = None, **config: Any):
        self._core = _core.TrackerCore(config, threads=threads)

    @property
    def config(self) -> dict[str, Any]:
        return dict(self._core.config())

    def prepare_reference(self, rgb, depth, K, pose) -> Reference:
        """Prepares a reference view with camera-to-world `pose`."""
        return Reference(
            self._core.prepare_reference(
                _rgb(rgb, "ref_rgb"), _depth(depth, "ref_depth"), _mat(K, 3, "K"),
                _mat(pose, 4, "ref_pose"),
            )
        )

    def track(self, rgb, depth, K, ref_rgb=None, ref_depth=None, ref_pose=None,
              init_pose=None, *, reference: Optional[Reference] = None) -> TrackResult:
        """Aligns the frame (`rgb`, `depth`, `K`) to the reference view — given either as
        `ref_rgb`, `ref_depth`, `ref_pose` (same K and size) or prepared as `reference` —
        starting from `init_pose` (default: the reference pose)."""
        if reference is None:
            if ref_rgb is None or ref_depth is None or ref_pose is None:
                raise ValueError("give ref_rgb, ref_depth and ref_pose, or reference=")
            reference = self.prepare_reference(ref_rgb, ref_depth, K, ref_pose)
        elif ref_rgb is not None or ref_depth is not None or ref_pose is not None:
            raise ValueError("give either reference= or ref_rgb/ref_depth/ref_pose, not both")
        init = reference.pose if init_pose is None else init_pose
        d = self._core.track(
            reference._core, _rgb(rgb, "rgb"), _depth(depth, "depth"), _mat(K, 3, "K"),
            _mat(init, 4, "init_pose"),
        )
        return TrackResult._from_dict(d)


class Odometry:
    """Frame-to-frame RGB-D odometry: each frame is tracked against the previous one from a
    constant-velocity prediction (`motion_prior=False`: from the previous pose). A lost frame
    keeps the prediction and is counted in `lost_frames`. Keyword arguments are tracker
    options (see `Tracker`)."""

    def __init__(self, initial_pose=None, motion_prior: bool = True, **config: Any):
        init = np.eye(4) if initial_pose is None else initial_pose
        self._core = _core.OdometryCore(config, _mat(init, 4, "initial_pose"), bool(motion_prior))

    def step(self, rgb, depth, K) -> OdometryStep:
        d = self._core.step(_rgb(rgb, "rgb"), _depth(depth, "depth"), _mat(K, 3, "K"))
        res = d["result"]
        return OdometryStep(
            pose=d["pose"], predicted=d["predicted"],
            result=None if res is None else TrackResult._from_dict(res),
        )

    @property
    def frames(self) -> int:
        return self._core.frames

    @property
    def lost_frames(self) -> int:
        return self._core.lost_frames
