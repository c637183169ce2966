"""The frame type shared by all loaders, and the sequence logic (frame range, stride, downscale,
depth scaling, camera normalisation, validation) that every format gets from one place.

A format only says where its files are: it implements `_count`, `_read` and, when it has
them, `_pose` and `_timestamp`. Everything it returns is at the dataset's native resolution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence as SequenceT

import numpy as np

log = logging.getLogger("legslam")

# Label value for pixels without a class (unlabelled, or a class outside the benchmark set).
IGNORE_LABEL = -1

# Frame time for formats whose files carry no timestamps: the 30 Hz of the sensors they come from.
NOMINAL_FPS = 30.0

# Unreadable frames in a row after which `each_readable` gives up (a second at 30 Hz): a
# corrupt file is skipped, a sequence whose files are broken is not tracked blind.
MAX_UNREADABLE_IN_A_ROW = 30


class DatasetError(ValueError):
    """Input that cannot be read as the dataset it claims to be; the message says what and where."""


class DatasetNotFoundError(DatasetError, FileNotFoundError):
    """A file or folder the format needs is missing."""


@dataclass
class Frame:
    """One RGB-D frame in legslam's conventions.

    rgb: HxWx3 uint8; depth: HxW float32 metres, 0 = invalid; K: 3x3 float64 intrinsics of
    this image; pose: 4x4 float64 camera-to-world (OpenCV axes) or None when the dataset has
    no pose for this frame; timestamp: seconds; index: the frame's position in the original,
    unstrided sequence; labels: HxW int32 class ids (IGNORE_LABEL = unlabelled) or None.
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose: Optional[np.ndarray]
    timestamp: float
    index: int
    labels: Optional[np.ndarray] = None


def make_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K of the image resized by sx, sy, about pixel centres as cv2.resize samples:
    u' = (u + 0.5) * sx - 0.5."""
    return make_K(K[0, 0] * sx, K[1, 1] * sy, (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5)


def as_K(intrinsics) -> np.ndarray:
    """A 3x3 K from (fx, fy, cx, cy) or a 3x3 / 4x4 matrix."""
    a = np.asarray(intrinsics, dtype=np.float64)
    if a.shape == (4,):
        a = make_K(*a)
    elif a.shape == (4, 4):
        a = a[:3, :3]
    if a.shape != (3, 3):
        raise DatasetError(f"intrinsics must be (fx, fy, cx, cy) or a 3x3 matrix, got shape {a.shape}")
    fx, fy, cx, cy = a[0, 0], a[1, 1], a[0, 2], a[1, 2]
    if not np.all(np.isfinite(a)) or fx == 0 or fy == 0 or a[0, 1] != 0:
        raise DatasetError(f"intrinsics are not a pinhole camera without skew: {a.tolist()}")
    return make_K(fx, fy, cx, cy)


def warn_unusual_camera(K: np.ndarray, width: int, height: int, where: str) -> None:
    """Warns (the "legslam" logger) about intrinsics that are legal but unlikely to be meant: a
    principal point outside the image, or a field of view narrower than 2 or wider than 160
    degrees (focal lengths in another image's pixels, or in millimetres)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        log.warning("%s: the principal point (%.1f, %.1f) lies outside the %dx%d image: are the "
                    "intrinsics for another image size?", where, cx, cy, width, height)
    fov = np.degrees(2 * np.arctan2([width / 2, height / 2], [abs(fx), abs(fy)]))
    if fov.min() < 2 or fov.max() > 160:
        log.warning("%s: focal lengths fx %.4g, fy %.4g give a %.1f x %.1f degree field of view for "
                    "%dx%d images: are they in pixels of these images?", where, fx, fy, *fov, width, height)


def check_pose(pose: np.ndarray, where: str) -> Optional[np.ndarray]:
    """A validated 4x4 c2w pose. Non-finite entries mean "no pose" (ScanNet writes -inf when
    its tracking was lost), so they give None; a matrix that is not a rigid motion is an error."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise DatasetError(f"{where}: pose must be 4x4, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        return None
    R = pose[:3, :3]
    # 1e-2 admits rotations printed with few digits (7-Scenes has errors up to 4e-4).
    if (np.abs(R.T @ R - np.eye(3)).max() > 1e-2 or np.linalg.det(R) < 0
            or np.abs(pose[3] - [0, 0, 0, 1]).max() > 1e-6):
        raise DatasetError(f"{where}: pose is not a rigid transform (rotation not orthonormal "
                           f"or last row not 0 0 0 1):\n{pose}")
    return pose


class Sequence:
    """A lazily read RGB-D sequence: `len(seq)`, `seq[i]`, iteration. Only the frame asked for
    is read from disk.

    Subclasses set `name`, `format`, `class_names` (or None), and call `_setup()` at the end of
    their __init__ with the native intrinsics, depth scale and image size.
    """

    name: str = ""
    format: str = ""
    class_names: Optional[list] = None
    # Raw depth values that mean "no measurement" besides 0 (7-Scenes marks some with 65535).
    invalid_depth_values: tuple = ()
    # The keyword options of the format's own (a bag's topics, a phone's confidence), which
    # `open` passes on.
    options: tuple = ()

    def __init__(self, path, *, stride: int = 1, frames=None, max_frames: Optional[int] = None,
                 downscale: int = 1, intrinsics=None, depth_scale: Optional[float] = None):
        self.path = Path(path)
        self._stride, self._frames, self._max_frames = stride, frames, max_frames
        self._downscale = downscale
        self._K_override = None if intrinsics is None else as_K(intrinsics)
        self._depth_scale_override = depth_scale

    # --- to implement per format -------------------------------------------------------
    def _count(self) -> int:
        """Number of frames in the full, unstrided sequence."""
        raise NotImplementedError

    def _read(self, i: int):
        """(rgb HxWx3 uint8, raw depth HxW integer or float metres, labels or None) of frame i."""
        raise NotImplementedError

    def _pose(self, i: int) -> Optional[np.ndarray]:
        return None

    def _timestamp(self, i: int) -> float:
        return i / NOMINAL_FPS

    # --- shared logic ------------------------------------------------------------------
    def _setup(self, K, depth_scale: float, size: tuple):
        """Fix the camera after the format found its files. size is the native (width, height)."""
        K = self._K_override if self._K_override is not None else as_K(K)
        if self._depth_scale_override is not None:
            depth_scale = self._depth_scale_override
        depth_scale = float(depth_scale)
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise DatasetError(f"{self.path}: depth scale must be a positive number, got {depth_scale}")
        self.depth_scale = depth_scale
        self.native_size = (int(size[0]), int(size[1]))
        f = self._downscale
        if not (isinstance(f, (int, np.integer)) and f >= 1):
            raise DatasetError(f"downscale must be an integer >= 1, got {f!r}")
        w, h = self.native_size
        if w < f or h < f:
            raise DatasetError(f"{self.path}: images of {w}x{h} cannot be downscaled by {f}")
        # Negative focal lengths (ICL-NUIM's fy = -480) describe a mirrored image. Flipping the
        # image along that axis and negating the focal length gives the same rays with a normal
        # camera, so the poses stay exactly as the dataset wrote them.
        self._flip_rows, self._flip_cols = K[1, 1] < 0, K[0, 0] < 0
        K = K.copy()
        if self._flip_cols:
            K[0, 0], K[0, 2] = -K[0, 0], (w - 1) - K[0, 2]
        if self._flip_rows:
            K[1, 1], K[1, 2] = -K[1, 1], (h - 1) - K[1, 2]
        self.native_K = K
        warn_unusual_camera(K, w, h, str(self.path))
        self.K = scale_K(K, 1 / f, 1 / f)
        self.width, self.height = w // f, h // f

        n = self._count()
        start, stop = (0, n) if self._frames is None else tuple(self._frames)
        stop = n if stop is None else min(stop, n)
        for name, v in (("stride", self._stride), ("max_frames", self._max_frames)):
            if not (isinstance(v, (int, np.integer)) and v >= 1) and not (name == "max_frames" and v is None):
                raise DatasetError(f"{name} must be an integer >= 1, got {v!r}")
        if not 0 <= start < stop:
            raise DatasetError(f"frames=({start}, {stop}) is not a range inside the {n} frames of {self.path}")
        self._indices = range(start, stop, self._stride)[: self._max_frames]
        if len(self._indices) == 0:
            raise DatasetError(f"{self.path}: no frames selected (the sequence has {n})")

    @property
    def selection(self) -> dict:
        """The options that select these frames from the folder, as `open` takes them: the
        range, stride and downscale, the format's own options and given intrinsics."""
        r = self._indices
        out = {"frames": [r.start, r.stop], "stride": r.step, "downscale": self._downscale}
        out.update({name: getattr(self, name) for name in self.options})
        if self._K_override is not None:
            K = self._K_override
            out["intrinsics"] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        return out

    @property
    def intrinsics(self) -> tuple:
        """(fx, fy, cx, cy) of the frames this sequence returns."""
        return (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2])

    @property
    def indices(self) -> range:
        """The original frame indices this sequence returns, in order."""
        return self._indices

    def __len__(self) -> int:
        return len(self._indices)

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self)):
            yield self[k]

    def timestamp(self, k: int) -> float:
        """The k-th frame's timestamp (seconds), read without its images."""
        return float(self._timestamp(self._indices[k]))

    def pose(self, k: int) -> Optional[np.ndarray]:
        """The k-th frame's ground-truth pose (None when it has none), read without its images."""
        return self._pose(self._indices[k])

    def __getitem__(self, k: int) -> Frame:
        if not isinstance(k, (int, np.integer)):
            raise TypeError(f"sequence indices must be integers, not {type(k).__name__}")
        i = self._indices[k]  # raises IndexError past the end, handles negative k
        where = f"{self.path} frame {i}"
        try:
            rgb, depth, labels = self._read(i)
        except OSError as e:  # the loaders name their files; this is the net under them
            raise DatasetError(f"{where}: {e}") from None
        depth = self._to_metres(depth, where)
        w, h = self.native_size
        if rgb.shape != (h, w, 3) or depth.shape != (h, w):
            raise DatasetError(f"{where}: colour is {rgb.shape[1::-1]} and depth {depth.shape[::-1]}, "
                               f"expected both {w}x{h} (the sequence's image size)")
        if labels is not None and labels.shape != (h, w):
            raise DatasetError(f"{where}: labels are {labels.shape[1]}x{labels.shape[0]}, expected {w}x{h}")
        rgb, depth, labels = self._transform(rgb, depth, labels)
        return Frame(rgb=rgb, depth=depth, K=self.K.copy(), pose=self.pose(k),
                     timestamp=self.timestamp(k), index=int(i), labels=labels)

    def gt_trajectory(self) -> tuple:
        """(timestamps (M,), c2w poses (M,4,4)) of the selected frames that have a ground-truth
        pose, read without touching any image."""
        stamps, poses = [], []
        for k in range(len(self)):
            p = self.pose(k)
            if p is not None:
                stamps.append(self.timestamp(k))
                poses.append(p)
        return np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)

    def _to_metres(self, raw: np.ndarray, where: str) -> np.ndarray:
        if np.issubdtype(raw.dtype, np.integer):
            depth = raw.astype(np.float32) / np.float32(self.depth_scale)
            for v in self.invalid_depth_values:
                depth[raw == v] = 0.0
            return depth
        depth = raw.astype(np.float32)  # float depth images are in metres already
        if np.isnan(depth).all():
            raise DatasetError(f"{where}: depth is all NaN")
        depth[~np.isfinite(depth)] = 0.0  # NaN/inf is the float-image way of saying "invalid"
        if (depth < 0).any():
            raise DatasetError(f"{where}: depth has negative values (min {depth.min()} m)")
        return depth

    def _transform(self, rgb, depth, labels):
        if self._flip_rows:
            rgb, depth = rgb[::-1], depth[::-1]
            labels = None if labels is None else labels[::-1]
        if self._flip_cols:
            rgb, depth = rgb[:, ::-1], depth[:, ::-1]
            labels = None if labels is None else labels[:, ::-1]
        f = self._downscale
        if f > 1:
            import cv2

            h, w = self.height, self.width
            rgb = cv2.resize(np.ascontiguousarray(rgb[: h * f, : w * f]), (w, h), interpolation=cv2.INTER_AREA)
            # Depth and labels take the block-centre sample: averaging would blend foreground
            # and background depths (and invalid zeros) into values that exist nowhere.
            o = f // 2
            depth = depth[o::f, o::f][:h, :w]
            labels = None if labels is None else labels[o::f, o::f][:h, :w]
        return (np.ascontiguousarray(rgb), np.ascontiguousarray(depth, dtype=np.float32),
                None if labels is None else np.ascontiguousarray(labels, dtype=np.int32))

    def __repr__(self) -> str:
        return (f"<{type(self).__name__} {self.name!r} format={self.format} frames={len(self)} "
                f"{self.width}x{self.height} fx={self.K[0, 0]:.2f}>")


def natural_key(path: Path):
    """Sort key that puts frame2 before frame10."""
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def paths_sorted(paths: SequenceT[Path]) -> list:
    return sorted(paths, key=natural_key)


def each_readable(seq) -> Iterator[tuple[int, Optional[Frame]]]:
    """(k, frame) for every frame of `seq` in order; frame is None where it cannot be read,
    with a warning (the "legslam" logger) that says why. Raises DatasetError once MAX_UNREADABLE_IN_A_ROW
    frames in a row could not be read."""
    in_a_row = 0
    for k in range(len(seq)):
        try:
            frame = seq[k]
        except DatasetError as e:
            in_a_row += 1
            if in_a_row >= MAX_UNREADABLE_IN_A_ROW:
                raise DatasetError(f"{in_a_row} frames in a row cannot be read (frames "
                                   f"{k - in_a_row + 1}-{k}), the last: {e}") from e
            log.warning("frame %d skipped: %s", k, e)
            yield k, None
            continue
        in_a_row = 0
        yield k, frame
