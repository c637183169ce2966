"""Intel RealSense cameras through the SDK (pyrealsense2: `pip install 'legslam[realsense]'`):
live, or a recording (.bag; .db3 from SDK 2.5x on) played back by the SDK. (legslam's bag
reader reads those recordings too, without the SDK.) A camera is a stream, not a Sequence: its
frames come once, as they are taken.

    cam = RealSenseCamera()                  # the first camera found; file="rec.bag" plays one back
    cam.start(record_to="out/recording")     # K, width, height, depth_scale are known from here
    for k, frame in cam.frames(): ...        # until cam.stop() (Ctrl-C), max_frames or the file's end
    cam.dropped                              # frames the camera delivered that were not taken
    cam.recording()                          # the frames taken, as a Sequence (a plain folder)

Depth is registered to the colour camera (datasets.registration, from the two streams'
intrinsics and the device's extrinsics between them), so frames carry the colour stream's
intrinsics; depth is scaled by the device's depth units. Live, each frame taken is the newest
the camera has delivered, and the frames that came while SLAM worked on the one before are
dropped (counted from the camera's frame numbers). Played back, every frame of the recording is
taken: the playback is not real time, each sensor hands its frames to legslam and the playback
waits while they wait to be taken, and colour and depth are paired by nearest timestamp as
legslam's bag reader pairs them. (The sensors start while the playback is paused: started one
after the other while it played, the second lost its first frames, more of them on a busy
machine.) Each frame taken is written to `record_to` as a plain folder dataset (lossless PNGs,
camera.json, timestamps.txt), so that the run can be evaluated, and run again offline.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import deque
from pathlib import Path
from typing import Iterator, NamedTuple, Optional

import numpy as np

from .base import DatasetError, Frame, make_K
from .folder import FolderSequence, FolderWriter
from .registration import register_depth
from .tum import MAX_TIME_DIFF, associate

log = logging.getLogger("legslam")

# A live camera that delivers nothing for this long is gone; a recording played back is over.
TIMEOUT_MS = 5000
# How long a recording played to its end is waited on for the frames still on their way.
DRAIN_MS = 250
# Frames a played-back recording hands over before its playback waits for them to be taken.
PLAYBACK_QUEUE = 8
# A colour frame whose depth has not come by the time colour this much newer has is unpaired.
PAIR_WAIT_S = 1.0


def import_sdk():
    """pyrealsense2, or a DatasetError saying how to install it, or why it cannot load."""
    try:
        import pyrealsense2
    except ModuleNotFoundError:
        raise DatasetError("a RealSense camera needs Intel's SDK for Python: pip install 'legslam[realsense]' "
                           "(pyrealsense2)") from None
    except ImportError as e:
        # Installed, but a library it links is missing (a minimal system lacks libusb).
        hint = " (Debian/Ubuntu: apt-get install libusb-1.0-0)" if "libusb" in str(e) else ""
        raise DatasetError(f"Intel's SDK for Python (pyrealsense2) is installed but cannot load: {e}{hint}") from None
    return pyrealsense2


class Image(NamedTuple):
    """One stream's frame, copied out of the SDK (whose frames are recycled)."""
    number: int
    t: float  # seconds
    data: np.ndarray
    format: object


def copied(frame) -> Image:
    return Image(frame.get_frame_number(), frame.get_timestamp() / 1e3, np.array(frame.get_data()),
                 frame.get_profile().format())


def video(profile) -> tuple:
    """(K, (width, height), distortion coefficients) of a video stream profile."""
    intr = profile.as_video_stream_profile().get_intrinsics()
    return make_K(intr.fx, intr.fy, intr.ppx, intr.ppy), (int(intr.width), int(intr.height)), list(intr.coeffs)


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
        self.K, size, coeffs = video(source.colour)
        if any(coeffs):
            log.warning("%s: the colour camera's distortion (%s) is ignored: frames are taken as pinhole "
                        "images", where, ", ".join(f"{c:.4g}" for c in coeffs))
        self.width, self.height = size
        self.depth_scale = 1.0 / float(source.device.first_depth_sensor().get_depth_scale())
        try:
            self._register = self._registration(source)
        except RuntimeError as e:
            source.stop()
            raise DatasetError(f"{where}: depth cannot be registered to colour: no extrinsics between the two "
                               f"streams ({e})") from None
        self._rs, self._pipe = rs, source
        if record_to is not None:
            self._writer = FolderWriter(record_to, self.K, self.width, self.height, self.depth_scale)

    def _registration(self, source) -> Optional[tuple]:
        """(K_depth, colour_from_depth in depth units) when depth is on a camera of its own."""
        K_depth, size, _ = video(source.depth)
        ext = source.depth.get_extrinsics_to(source.colour)
        motion = np.eye(4)
        motion[:3, :3] = np.reshape(ext.rotation, (3, 3)).T  # the SDK's is column-major
        motion[:3, 3] = np.asarray(ext.translation) * self.depth_scale
        if np.allclose(K_depth, self.K) and size == (self.width, self.height) and np.allclose(motion, np.eye(4)):
            return None
        return K_depth, motion

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
                pair = self._pipe.next()
                if pair is None:
                    break
                colour, depth = pair
                if last is not None and colour.number > last + 1:
                    self.dropped += colour.number - last - 1
                last = colour.number
                frame = Frame(rgb=self._rgb(colour), depth=self._depth(depth), K=self.K.copy(), pose=None,
                              timestamp=colour.t, index=k)
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

    def _rgb(self, colour: Image) -> np.ndarray:
        rs = self._rs
        if colour.format in (rs.format.rgb8, rs.format.rgba8):
            return np.ascontiguousarray(colour.data[..., :3])
        if colour.format in (rs.format.bgr8, rs.format.bgra8):
            return np.ascontiguousarray(colour.data[..., 2::-1])
        raise DatasetError(f"{self.path}: colour frames in {colour.format} cannot be read (rgb8, bgr8, rgba8, bgra8 "
                           "can)")

    def _depth(self, depth: Image) -> np.ndarray:
        raw = depth.data
        if self._register is not None:
            K_depth, motion = self._register
            raw = register_depth(raw, K_depth, self.K, motion, (self.width, self.height))
        return raw.astype(np.float32) / np.float32(self.depth_scale)


class _Live:
    """A camera's colour and depth streams through the SDK's pipeline, which pairs them."""

    def __init__(self, rs, width: int, height: int, fps: int):
        cfg, self._pipe = rs.config(), rs.pipeline()
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        profile = self._pipe.start(cfg)
        self.device = profile.get_device()
        self.colour, self.depth = profile.get_stream(rs.stream.color), profile.get_stream(rs.stream.depth)

    def next(self) -> tuple:
        """The newest (colour, depth) the camera has delivered: the ones before it are dropped."""
        while True:
            ok, frames = self._pipe.try_wait_for_frames(TIMEOUT_MS)
            if not ok:
                raise DatasetError(f"no frames from the RealSense camera for {TIMEOUT_MS / 1e3:.0f} s "
                                   "(disconnected?)")
            while True:
                newer = self._pipe.poll_for_frames()
                if not newer:
                    break
                frames = newer
            colour, depth = frames.get_color_frame(), frames.get_depth_frame()
            if colour and depth:
                return copied(colour), copied(depth)

    def stop(self) -> None:
        self._pipe.stop()


class _Playback:
    """A recording's colour and depth sensors, each handing its frames to one queue, started
    while the playback is paused and not real time: then the playback waits while the queue is
    full, and every frame of both streams arrives. (A pipeline starts playing before it can be
    told so; a sensor started while another plays loses its first frames.)"""

    def __init__(self, rs, file: Path):
        self.device = rs.context().load_device(str(file))
        self._playback, self._stopped = self.device.as_playback(), rs.playback_status.stopped
        self._playback.set_real_time(False)
        self._queue, self._closing = queue.Queue(PLAYBACK_QUEUE), threading.Event()
        self._pairs = Pairing()
        self._sensors, kinds = [], {}
        for sensor in self.device.query_sensors():  # a D405 has both streams on one sensor
            profiles = [p for p in sensor.get_stream_profiles() if p.stream_type() in (rs.stream.color, rs.stream.depth)]
            kinds.update((p.stream_type(), p) for p in profiles)
            if profiles:
                sensor.open(profiles)
                self._sensors.append(sensor)
        if len(kinds) < 2:
            raise RuntimeError("the recording has no colour stream" if rs.stream.depth in kinds
                               else "the recording has no depth stream")
        self.colour, self.depth = kinds[rs.stream.color], kinds[rs.stream.depth]
        is_colour = rs.stream.color
        self._playback.pause()
        for sensor in self._sensors:
            sensor.start(lambda f: self._take(f.get_profile().stream_type() == is_colour, copied(f)))
        self._playback.resume()

    def _take(self, is_colour: bool, img: Image) -> None:
        """On the SDK's thread: waits while the queue is full, and so does the playback."""
        while not self._closing.is_set():
            try:
                return self._queue.put((is_colour, img), timeout=0.1)
            except queue.Full:
                pass

    def next(self) -> Optional[tuple]:
        """The next (colour, depth) pair of the recording, None at its end."""
        quiet = 0
        while (pair := self._pairs.pop()) is None:
            stopped = self._playback.current_status() == self._stopped
            try:
                self._pairs.add(*self._queue.get(timeout=DRAIN_MS / 1e3))
                quiet = 0
            except queue.Empty:
                quiet += DRAIN_MS
                if stopped or quiet >= TIMEOUT_MS:  # played to its end, and nothing came for DRAIN_MS
                    return self._pairs.pop(ended=True)
        return pair

    def stop(self) -> None:
        self._closing.set()  # a callback waiting on the queue returns, and the sensors can stop
        for sensor in self._sensors:
            sensor.stop()
            sensor.close()
        if self._pairs.unpaired:
            log.warning("%d colour frames of the recording had no depth frame within %.0f ms, and were skipped",
                        self._pairs.unpaired, MAX_TIME_DIFF * 1e3)


class Pairing:
    """Colour and depth frames as they arrive, in pairs of nearest timestamp (datasets.tum's
    associate, on the frames still waiting): the oldest colour frame is paired once no depth
    frame still to come could be nearer to it."""

    def __init__(self):
        self.colour, self.depth, self.unpaired = deque(), deque(), 0

    def add(self, is_colour: bool, img: Image) -> None:
        (self.colour if is_colour else self.depth).append(img)

    def pop(self, ended: bool = False) -> Optional[tuple]:
        """The oldest colour frame and its depth; None until it is known (at the end: none left)."""
        while self.colour:
            c = self.colour[0]
            settled = (ended or (self.depth and self.depth[-1].t > c.t + MAX_TIME_DIFF)
                       or self.colour[-1].t > c.t + PAIR_WAIT_S)
            if not settled:
                return None
            self.colour.popleft()
            pairs = associate(np.array([c.t] + [x.t for x in self.colour]), np.array([d.t for d in self.depth]),
                              MAX_TIME_DIFF)
            j = next((j for i, j in pairs if i == 0), None)
            if j is not None:
                for _ in range(j):  # older depth: nearer to no colour frame still to come
                    self.depth.popleft()
                return c, self.depth.popleft()
            self.unpaired += 1
            while self.depth and self.depth[0].t < c.t - MAX_TIME_DIFF:
                self.depth.popleft()
        return None
