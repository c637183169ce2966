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

from typing import Any, Optional

import numpy as np

from legslam import _core

__all__ = ["DEFAULT_CONFIG", "fitting_levels", "odometry_finest_level", "TrackResult", "Tracker", "Reference", "Odometry",
           "OdometryStep"]

#: The engine's default tracker options (`Tracker(**overrides)` changes any of them).
DEFAULT_CONFIG: dict[str, Any] = dict(_core.tracker_options())

#: Outcome of one alignment (the engine's):
#: pose: 4x4 camera-to-world estimate (when `lost`, the best estimate, not to be trusted);
#: residual_rms: RMS of the Huber-normalised joint residual (dimensionless);
#: geometric_rms: RMS point-to-plane distance of the inliers (m);
#: photometric_rms: RMS intensity residual (intensity in [0, 1]);
#: inlier_ratio: inlier correspondences / frame pixels with valid depth (finest level);
#: inliers: number of inlier correspondences (finest level);
#: condition: condition number of the normal equations (inf if singular);
#: iterations: Gauss-Newton iterations over all levels;
#: gain: estimated exposure gain applied to the frame intensity (1 if not estimated);
#: lost: the alignment cannot be trusted; `reason` says why.
TrackResult = _core.TrackResult

#: One frame of `Odometry`: `pose` (tracked, or the constant-velocity prediction when lost),
#: `predicted`, `result` (a TrackResult; None for the first frame) and `lost`.
OdometryStep = _core.OdometryStep


def fitting_levels(width: int, height: int, finest_level: int) -> int:
    """The default number of pyramid levels, fewer where the coarsest would be under 8 pixels
    (the engine refuses that) for a width x height image tracked from `finest_level`."""
    smallest = min(width, height) >> finest_level
    return min(DEFAULT_CONFIG["levels"], max(1, int(np.log2(max(smallest, 8) / 8)) + 1))


def odometry_finest_level(width: int) -> int:
    """The finest level `legslam odometry` tracks a `width`-pixel-wide frame at: the default's
    on 640x480 (160 pixels wide), no coarser than what leaves at least 160 pixels."""
    return min(DEFAULT_CONFIG["finest_level"], int(np.log2(max(width, 160) / 160)))


def _image(a) -> np.ndarray:
    """An image as the engine takes it: floats as float32, anything else as it is, for the
    bindings to check (integer depth is in sensor units: refused, never taken as metres)."""
    a = np.asarray(a)
    return np.ascontiguousarray(a, dtype=np.float32) if a.dtype.kind == "f" else np.ascontiguousarray(a)


def _mat(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


class Reference:
    """A reference view prepared once (pyramids, gradients, normals) for many `track` calls,
    e.g. colour + depth rendered from the map at the predicted pose."""

    def __init__(self, core: Any):
        self._core = core

    @property
    def pose(self) -> np.ndarray:
        return self._core.pose


class Tracker:
    """Dense RGB-D tracker. Keyword arguments override `DEFAULT_CONFIG` (the engine's
    `TrackerConfig` documents each); unknown or invalid options raise ValueError. `threads`:
    run on a thread pool of this many threads of its own (default: the engine's shared
    pool)."""

    def __init__(self, threads: int | None = None, **config: Any):
        self._core = _core.TrackerCore(config, threads=threads)

    @property
    def config(self) -> dict[str, Any]:
        return dict(self._core.config())

    def prepare_reference(self, rgb, depth, K, pose) -> Reference:
        """Prepares a reference view with camera-to-world `pose`."""
        return Reference(self._core.prepare_reference(_image(rgb), _image(depth), _mat(K), _mat(pose)))

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
        return self._core.track(reference._core, _image(rgb), _image(depth), _mat(K), _mat(init))


class Odometry:
    """Frame-to-frame RGB-D odometry: each frame is tracked against the previous one from a
    constant-velocity prediction (`motion_prior=False`: from the previous pose). A lost frame
    keeps the prediction and is counted in `lost_frames`. Keyword arguments are tracker
    options (see `Tracker`)."""

    def __init__(self, initial_pose=None, motion_prior: bool = True, **config: Any):
        init = np.eye(4) if initial_pose is None else initial_pose
        self._core = _core.OdometryCore(config, _mat(init), bool(motion_prior))

    def step(self, rgb, depth, K) -> OdometryStep:
        return self._core.step(_image(rgb), _image(depth), _mat(K))

    @property
    def frames(self) -> int:
        return self._core.frames

    @property
    def lost_frames(self) -> int:
        return self._core.lost_frames
