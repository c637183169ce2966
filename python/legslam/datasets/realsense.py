"""Intel RealSense cameras through the SDK (pyrealsense2: `pip install 'legslam[realsense]'`):
live, or a recording (.bag; .db3 from SDK 2.5x on) played back by the SDK. (legslam's bag
reader reads those recordings too, without the SDK.) A camera is a stream, not a Sequence: its
frames come once, as they are taken.

    cam = RealSenseCamera()                  # the first camera found; file="rec.bag" plays one back
    cam.start(record_to="out/recording")     # K, width, height, depth_scale are known from here
    for k, frame in cam.frames(): ...        # until cam.stop() (Ctrl-C), max_frames or the file's end
    cam.dropped                              # frames the camera delivered that were not taken
    cam.recording()                          # the frames taken, as a Sequence (a plain folder)

Depth is aligned to the colour camera by the SDK (rs.align), so frames carry the colour
stream's intrinsics; depth is scaled by the device's depth units. Live, each frame taken is
the newest the camera has delivered, and the frames that came while SLAM worked on the one
before are dropped (counted from the camera's frame numbers); played back, every frame the
SDK delivers is taken (it does not play in real time; it delivers a recording's first frame's
colour and depth apart, and that frame is skipped: legslam's bag reader, without the SDK, reads
it). Each frame taken is written to `record_to` as a plain folder dataset (lossless PNGs,
camera.json, timestamps.txt), so that the run can be evaluated, and run again offline.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from .base import DatasetError, Frame, make_K
from .folder import FolderSequence, FolderWriter

log = logging.getLogger("legslam")

# A live camera that delivers nothing for this long is gone; a recording played back is over.
TIMEOUT_MS = 5000
# How long a recording read to its end is waited on for the framesets still on their way.
DRAIN_MS = 250
# Framesets a played-back recording's syncer holds (the playback waits while it is full).
SYNC_QUEUE = 4


def import_sdk():
    """pyrealsense2, or a DatasetError saying how to install it."""
    try:
        import pyrealsense2
    except ImportError:
        raise DatasetError("a RealSense camera needs Intel's SDK for Python: pip install 'legslam[realsense]' "
                           "(pyrealsense2)") from None
    return pyrealsense2


class RealSenseCamera:
    #: pipeline.run takes frames from `frames()` as they come, and evaluates on `recording()`.
    live = True
    format = "realsense"

    def __init__(self, file=None, *, width: int = 640, height: int = 480, fps: int = 30,
                 max_frames: Optional[int] = None, sdk=None):
        """file: a RealSense recording to play back (None: the first camera connected). width,
        height, fps: the colour and depth streams asked of a live camera. sdk: the
        pyrealsense2 module (by default imported at start)."""
        self.file = None if file is None else Path(file)
        self.path = self.file if self.file is not None else Path("realsense")
        self.name = self.path.stem
        self._request = (width, height, fps)
        self.max_frames = max_frames
        self._sdk = sdk
        self._stop = threading.Event()
        self._pipe = self._writer = None
        self.dropped = 0

    def start(self, record_to=None) -> None:
        """Starts the streams (a DatasetError saying why when they cannot) and reads the camera."""
        rs = self._sdk or import_sdk()
        where = f"the RealSense recording {self.file}" if self.file else "a RealSense camera"
        if self.file is not None and not self.file.is_file():
            raise DatasetError(f"{self.file} does not exist")
        try:
            source = _Playback(rs, self.file) if self.file is not None else _Live(rs, *self._request)
        except RuntimeError as e:
            hint = "" if self.file else " (is one connected, and not in use by another program?)"
            raise DatasetError(f"cannot start {where}: {e}{hint}") from None
        intr = source.colour.as_video_stream_profile().get_intrinsics()
        if any(intr.coeffs):
            log.warning("%s: the colour camera's distortion (%s) is ignored: frames are taken as pinhole "
                        "images", where, ", ".join(f"{c:.4g}" for c in intr.coeffs))
        self.K = make_K(intr.fx, intr.fy, intr.ppx, intr.ppy)
        self.width, self.height = int(intr.width), int(intr.height)
        self.depth_scale = 1.0 / float(source.device.first_depth_sensor().get_depth_scale())
        self._rs, self._pipe, self._align = rs, source, rs.align(rs.stream.color)
        if record_to is not None:
            self._writer = FolderWriter(record_to, self.K, self.width, self.height, self.depth_scale)

    def stop(self) -> None:
        """Ends `frames()` before its next frame (safe from a signal handler or another thread)."""
        self._stop.set()

    def frames(self) -> Iterator[tuple[int, Frame]]:
        """(k, frame) of each frame taken, k counting from 0; the streams stop at the end."""
        if self._pipe is None:
            raise RuntimeError("start() the camera first (frames come once)")
        last, k = None, 0
        try:
            while not self._stop.is_set() and (self.max_frames is None or k < self.max_frames):
                frames = self._next()
                if frames is None:
                    break
                frames = self._align.process(frames)
                colour, depth = frames.get_color_frame(), frames.get_depth_frame()
                if not colour or not depth:
                    continue
                n = colour.get_frame_number()
                if last is not None and n > last + 1:
                    self.dropped += n - last - 1
                last = n
                frame = Frame(rgb=self._rgb(colour),
                              depth=np.asanyarray(depth.get_data()).astype(np.float32) / np.float32(self.depth_scale),
                              K=self.K.copy(), pose=None, timestamp=colour.get_timestamp() / 1e3, index=k)
                if self._writer is not None:
                    self._writer.add(frame)
                yield k, frame
                k += 1
        finally:
            self.close()

    def close(self) -> None:
        """Stops the streams and completes the recording (again: nothing)."""
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            pipe.stop()
        if self._writer is not None:
            self._writer.close()

    def recording(self) -> FolderSequence:
        """The frames taken, read back from `record_to`."""
        if self._writer is None:
            raise RuntimeError("the camera was started without record_to")
        return FolderSequence(self._writer.path)

    def _next(self):
        """The next frameset: live, the newest delivered; None at a recording's end."""
        ok, frames = self._pipe.try_wait_for_frames(TIMEOUT_MS)
        if not ok:
            if self.file is not None:
                return None
            raise DatasetError(f"no frames from the RealSense camera for {TIMEOUT_MS / 1e3:.0f} s (disconnected?)")
        if self.file is None:
            while True:  # take the newest: the ones before it are dropped
                newer = self._pipe.poll_for_frames()
                if not newer:
                    break
                frames = newer
        return frames

    def _rgb(self, colour) -> np.ndarray:
        img = np.asanyarray(colour.get_data())
        fmt = colour.get_profile().format()
        rs = self._rs
        if fmt in (rs.format.rgb8, rs.format.rgba8):
            return np.array(img[..., :3])
        if fmt in (rs.format.bgr8, rs.format.bgra8):
            return np.ascontiguousarray(img[..., 2::-1])
        raise DatasetError(f"{self.path}: colour frames in {fmt} cannot be read (rgb8, bgr8, rgba8, bgra8 can)")


class _Live:
    """A camera's colour and depth streams through the SDK's pipeline."""

    def __init__(self, rs, width: int, height: int, fps: int):
        cfg, self._pipe = rs.config(), rs.pipeline()
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        profile = self._pipe.start(cfg)
        self.device, self.colour = profile.get_device(), profile.get_stream(rs.stream.color)
        self.try_wait_for_frames, self.poll_for_frames = self._pipe.try_wait_for_frames, self._pipe.poll_for_frames

    def stop(self) -> None:
        self._pipe.stop()


class _Playback:
    """A recording's colour and depth sensors into one syncer, started only once the playback
    is made not real-time: then it waits for each frame to be taken, and reads every one. (A
    pipeline starts playing before it can be told so, and loses the first frames a few runs in
    ten; the syncer still delivers the very first frame's two streams apart, and that frame is
    skipped.)"""

    def __init__(self, rs, file: Path):
        self.device = rs.context().load_device(str(file))
        self._playback, self._stopped = self.device.as_playback(), rs.playback_status.stopped
        self._playback.set_real_time(False)
        self._sync, self._sensors, kinds = rs.syncer(SYNC_QUEUE), [], {}
        for sensor in self.device.query_sensors():  # a D405 has both streams on one sensor
            profiles = [p for p in sensor.get_stream_profiles() if p.stream_type() in (rs.stream.color, rs.stream.depth)]
            kinds.update((p.stream_type(), p) for p in profiles)
            if profiles:
                sensor.open(profiles)
                self._sensors.append(sensor)
        if len(kinds) < 2:
            raise RuntimeError("the recording has no colour stream" if rs.stream.depth in kinds
                               else "the recording has no depth stream")
        self.colour = kinds[rs.stream.color]
        for sensor in self._sensors:
            sensor.start(self._sync)

    def try_wait_for_frames(self, timeout_ms: int):
        """The next frameset, waited for in slices: the playback may stop while it is waited for."""
        for _ in range(max(1, timeout_ms // DRAIN_MS)):
            stopped = self._playback.current_status() == self._stopped
            ok, frames = self._sync.try_wait_for_frames(DRAIN_MS)
            if ok or stopped:  # read to its end, and nothing more came for DRAIN_MS
                return ok, frames
        return False, None

    def stop(self) -> None:
        for sensor in self._sensors:
            sensor.stop()
            sensor.close()
