"""RGB-D datasets in the formats the field publishes, and the user's own recordings, all read
into one Frame type.

    seq = legslam.datasets.open("path/to/sequence")      # format detected from the layout
    for frame in seq: frame.rgb, frame.depth, frame.K, frame.pose, frame.timestamp, frame.index

Formats: tum, replica (NICE-SLAM/SplaTAM renders), scannet (exported frames), 7scenes
(also 3DMatch), folder (plain colour + depth folders; legslam's own format, which the built-in
synthetic scene is written in), bag (ROS1 .bag files and ROS2 bag folders, RealSense SDK
recordings among them), stray (Stray Scanner's export) and record3d (Record3D's .r3d). A live
RealSense is not a sequence but a stream: `realsense.RealSenseCamera`.
"""

from __future__ import annotations

from pathlib import Path

from .base import IGNORE_LABEL, DatasetError, DatasetNotFoundError, Frame, Sequence, each_readable
from .detect import FORMATS, detect

__all__ = ["open", "detect", "each_readable", "Frame", "Sequence", "DatasetError",
           "DatasetNotFoundError", "IGNORE_LABEL", "FORMATS"]


def open(path, format: str = "auto", *, stride: int = 1, frames=None, max_frames=None,
         downscale: int = 1, intrinsics=None, depth_scale=None, **options) -> Sequence:
    """Open the RGB-D sequence at path, reading frames only when indexed.

    format: "auto" or one of FORMATS. stride: take every stride-th frame. frames: (start, stop)
    range of original frame positions (stop exclusive or None). max_frames: at most this many
    frames after range and stride. downscale: integer factor, images shrink and intrinsics
    follow. intrinsics ((fx, fy, cx, cy) or 3x3) and depth_scale (raw units per metre)
    override what the dataset says, or supply it where the dataset has none. options: the
    format's own (bag: rgb_topic, depth_topic; stray, record3d: min_confidence); None values
    are left out.
    """
    path = Path(path).expanduser()
    if format == "auto":
        format = detect(path)
    elif format not in FORMATS:
        raise DatasetError(f"unknown dataset format {format!r}; known: auto, {', '.join(FORMATS)}")
    elif not path.exists():
        raise DatasetNotFoundError(f"{path} does not exist")
    cls = FORMATS[format][0]
    options = {k: v for k, v in options.items() if v is not None}
    unknown = sorted(set(options) - set(cls.options))
    if unknown:
        raise DatasetError(f"{path}: a {format} sequence takes no option {', '.join(unknown)} "
                           f"(its options: {', '.join(cls.options) or 'none'})")
    return cls(path, stride=stride, frames=frames, max_frames=max_frames, downscale=downscale,
               intrinsics=intrinsics, depth_scale=depth_scale, **options)
