"""ROS bags: a ROS1 `.bag` file, or a ROS2 bag folder (metadata.yaml beside .db3 or .mcap
files; a lone .db3 or .mcap file, as the RealSense SDK records, too), read with the
pure-Python rosbags (no ROS install: `pip install 'legslam[bags]'`).

Topics. Colour is a sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) or a CompressedImage
(jpeg, png); depth an Image (16UC1 or mono16 in millimetres, 32FC1 in metres) or a
CompressedImage in compressedDepth (png). The two are picked by themselves when the bag holds
one colour and one depth topic (a compressed copy of a raw topic and, beside colour, mono
images do not count), or when one of several has a name a recorder gives (TUM RGB-D's
/camera/rgb/image_color and /camera/depth/image, realsense-ros' colour and aligned depth, the
RealSense SDK's recordings); otherwise `rgb_topic` and `depth_topic` choose, and the error
lists the image topics found.

Camera. An image topic's sensor_msgs/CameraInfo is the camera_info topic beside it
(`.../camera_info`, the RealSense SDK's `.../info/camera_info`): its K, and its distortion
(plumb_bob, rational_polynomial), removed on load as for TUM. Without one, `intrinsics` must
be given, and the images are taken as they are. Depth whose camera differs from the colour's
(its own K or size, or a transform between their frames) is registered to the colour camera
with the transform between the two frames in /tf_static (in the RealSense SDK's recordings,
the streams' extrinsics); depth with the colour's K and size and no transform is taken as
registered already. 16-bit depth of a RealSense recording is in its "Depth Units".

Time. Colour and depth pair by their header stamps as TUM's do (within 0.02 s), and a frame
keeps its colour image's stamp. Opening reads every colour and depth message once for its
stamp, chunk by chunk (a long bag is never held in memory); a frame's images are read when
it is asked for, through the bag's index.
"""

from __future__ import annotations

import logging
import weakref
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import Optional

import numpy as np

from ._io import decode_image, decode_rgb, quat_to_pose
from .base import DatasetError, DatasetNotFoundError, Sequence, as_K
from .registration import register_depth
from .tum import MAX_TIME_DIFF, associate
from .undistort import undistortion

log = logging.getLogger("legslam")

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
COLOUR_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
DEPTH_DTYPES = {"16uc1": "u2", "mono16": "u2", "32fc1": "f4"}
# Topics recorders name (matched at the end of the topic), preferred among several candidates.
KNOWN_TOPICS = {
    "colour": ("/camera/rgb/image_color", "/camera/color/image_raw", "/Color_0/image/data"),
    "depth": ("/camera/depth/image", "/camera/aligned_depth_to_color/image_raw",
              "/camera/depth_registered/image_raw", "/Depth_0/image/data"),
}
TRANSPORTS = ("/compressed", "/compressedDepth")
BAG_FILES = (".bag", ".db3", ".mcap")  # ROS1; a ROS2 storage file read without its metadata.yaml
MILLIMETRES = 1000.0  # raw units per metre of 16-bit depth
# compressed_depth_image_transport's header before the PNG: format (int32), two float32
# quantisation parameters (for 32FC1: depth = a / (value - b)).
COMPRESSED_DEPTH_HEADER = 12


def is_bag(path: Path) -> bool:
    return (path.is_file() and path.suffix in BAG_FILES) or (path.is_dir() and (path / "metadata.yaml").is_file())


def bag_root(path: Path) -> Path:
    """The bag at path: a .db3 or .mcap file stands for the ROS2 bag folder that holds it (all
    its files), or alone for itself (the RealSense SDK records single .db3 files)."""
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


@contextmanager
def _reading(where):
    """rosbags' errors (a truncated, unindexed or foreign file, a message that does not
    deserialise) as a DatasetError naming where."""
    try:
        yield
    except DatasetError:
        raise
    except Exception as e:  # noqa: BLE001 (rosbags, sqlite and lz4/bz2/zstd each have their own)
        raise DatasetError(f"cannot read {where}: {type(e).__name__}: {e}".rstrip(": ")) from None


def _field(msg, name: str):
    """A field named as in ROS2 (k) or ROS1 (K)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def _stamp(msg) -> float:
    s = msg.header.stamp
    return s.sec + s.nanosec * 1e-9


@dataclass
class _Topic:
    name: str
    connections: list
    msgtype: str
    encoding: str  # an Image's encoding, a CompressedImage's format
    count: int

    @property
    def kind(self) -> str:
        e = self.encoding.lower()
        if self.msgtype == COMPRESSED:
            return "depth" if "compresseddepth" in e or e.split(";")[0].strip() in DEPTH_DTYPES else "colour"
        return "colour" if e in COLOUR_CHANNELS else "depth" if e in DEPTH_DTYPES else ""

    @property
    def grey(self) -> bool:
        return self.encoding.lower().startswith("mono8")  # "mono8; png compressed mono8" too

    @property
    def base(self) -> str:
        """The topic without its transport's suffix."""
        return next((self.name[: -len(s)] for s in TRANSPORTS if self.name.endswith(s)), self.name)

    def describe(self) -> str:
        return f"{self.name}  ({self.msgtype.replace('/msg/', '/')} {self.encoding or '?'}, {self.count} messages)"


@dataclass
class _Camera:
    K: np.ndarray
    dist: np.ndarray
    size: tuple
    frame: str
    topic: str


class BagSequence(Sequence):
    format = "bag"
    options = ("rgb_topic", "depth_topic")

    def __init__(self, path, rgb_topic: Optional[str] = None, depth_topic: Optional[str] = None, **kw):
        super().__init__(bag_root(Path(path)), **kw)
        p = self.path
        self.name = p.stem if p.is_file() else p.name
        try:
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise DatasetError(f"{p}: reading ROS bags needs rosbags: pip install 'legslam[bags]'") from None
        if p.is_dir() and p.suffix == ".bag":  # rosbags takes any *.bag for a ROS1 file
            raise DatasetError(f"{p} is a ROS2 bag folder whose name ends in .bag, which the bag library "
                               f"reads as a ROS1 file: rename the folder (to {p.with_suffix('').name}, say)")
        with _reading(f"bag {p} (cut short, or not a bag?)"):
            # ROS2 bags of older recorders carry no message definitions: the standard ones.
            self._reader = AnyReader([p], default_typestore=get_typestore(Stores.LATEST))
            self._reader.open()
        weakref.finalize(self, self._reader.close)
        topics = self._image_topics()
        self._rgb = self._pick(topics, "colour", rgb_topic, "rgb_topic (--rgb-topic)")
        self._depth = self._pick(topics, "depth", depth_topic, "depth_topic (--depth-topic)")
        self.rgb_topic, self.depth_topic = self._rgb.name, self._depth.name

        rgb_t, self._rgb_at = self._stamps(self._rgb)
        dep_t, self._depth_at = self._stamps(self._depth)
        pairs = associate(rgb_t, dep_t, MAX_TIME_DIFF)
        if not pairs:
            raise DatasetError(f"{p}: no colour ({self.rgb_topic}) and depth ({self.depth_topic}) images are "
                               f"within {MAX_TIME_DIFF} s of each other")
        self._pairs = pairs
        self._times = rgb_t[[i for i, _ in pairs]]

        first_rgb, first_depth = self._message(self._rgb, pairs[0][0]), self._message(self._depth, pairs[0][1])
        size = (int(first_rgb.width), int(first_rgb.height)) if self._rgb.msgtype == IMAGE else \
            decode_rgb(first_rgb.data, f"{p} {self.rgb_topic}").shape[1::-1]
        depth_size = self._decode_depth(first_depth, f"{p} {self.depth_topic} message {pairs[0][1]}").shape[::-1]
        self._setup_cameras(size, depth_size)
        self._setup(self._colour_K, self._realsense_depth_scale() or MILLIMETRES, size)

    # --- topics and their cameras --------------------------------------------------------
    def _image_topics(self) -> dict:
        by_topic: dict = {}
        for c in self._reader.connections:
            if c.msgtype in (IMAGE, COMPRESSED):
                by_topic.setdefault((c.topic, c.msgtype), []).append(c)
        topics = {}
        for (name, msgtype), conns in sorted(by_topic.items()):
            count = sum(c.msgcount for c in conns)
            encoding = ""
            if count:
                with _reading(f"bag {self.path} topic {name}"):
                    _, _, raw = next(self._reader.messages(connections=conns))
                    msg = self._reader.deserialize(raw, msgtype)
                encoding = msg.encoding if msgtype == IMAGE else msg.format
            topics[name] = _Topic(name, conns, msgtype, encoding, count)
        return topics

    def _pick(self, topics: dict, kind: str, given: Optional[str], option: str) -> _Topic:
        listing = "\n".join("  " + t.describe() for t in topics.values()) or "  (none)"
        if given is not None:
            t = topics.get(given)
            if t is None or t.kind != kind:
                what = "no image topic" if t is None else f"{t.encoding} images, not {kind}, on"
                raise DatasetError(f"{self.path}: {what} {given} ({option}); the image topics are:\n{listing}")
            return t
        cands = [t for t in topics.values() if t.kind == kind and t.count]
        if kind == "colour" and any(not t.grey for t in cands):  # mono8 beside colour: infrared
            cands = [t for t in cands if not t.grey]
        names = {t.name for t in cands}
        cands = [t for t in cands if t.base == t.name or t.base not in names]  # a raw topic's compressed copy
        if len(cands) != 1:
            known = [t for t in cands if t.base.endswith(KNOWN_TOPICS[kind])]
            if len(known) == 1:
                return known[0]
            what = (f"no {kind} image topic" if not cands else
                    f"{len(cands)} {kind} image topics ({', '.join(t.name for t in cands)}); choose one with {option}")
            raise DatasetError(f"{self.path}: {what}. The image topics are:\n{listing}")
        return cands[0]

    def _camera(self, topic: _Topic) -> Optional[_Camera]:
        """The CameraInfo beside an image topic, None when the bag has none."""
        looked = _info_topics(topic.name)
        conns = [c for c in self._reader.connections if c.topic in looked and c.msgtype == CAMERA_INFO]
        if not conns:
            return None
        where = f"{self.path} {conns[0].topic}"
        with _reading(where):
            _, _, raw = next(self._reader.messages(connections=conns[:1]))
            info = self._reader.deserialize(raw, CAMERA_INFO)
        K = np.asarray(_field(info, "k"), dtype=np.float64).reshape(3, 3)
        if not K.any():
            raise DatasetError(f"{where}: the camera is not calibrated (K is all zeros); give intrinsics "
                               "(--intrinsics fx,fy,cx,cy)")
        dist = np.asarray(_field(info, "d"), dtype=np.float64)
        model = info.distortion_model
        if dist.any() and model not in ("plumb_bob", "rational_polynomial"):
            raise DatasetError(f"{where}: cannot undistort the {model!r} distortion model (plumb_bob and "
                               "rational_polynomial can be); give intrinsics (--intrinsics fx,fy,cx,cy) to "
                               "take the images as they are")
        try:
            K = as_K(K)
        except DatasetError as e:
            raise DatasetError(f"{where}: {e}") from None
        return _Camera(K, dist, (int(info.width), int(info.height)), info.header.frame_id.lstrip("/"), conns[0].topic)

    def _setup_cameras(self, size: tuple, depth_size: tuple) -> None:
        """The colour K, and how depth gets to the colour camera: undistorted, registered."""
        self._undistort_rgb = self._undistort_depth = None
        self._register = None  # (K_depth, colour_from_depth) when depth is on another camera
        colour = depth = None
        if self._K_override is not None:  # the images as they are
            colour_K = self._K_override
        elif (colour := self._camera(self._rgb)) is None:
            raise DatasetNotFoundError(f"{self.path}: no sensor_msgs/CameraInfo for {self._rgb.name} (looked for "
                                       f"{' and '.join(_info_topics(self._rgb.name))}); give the intrinsics: "
                                       "--intrinsics fx,fy,cx,cy on the command line, intrinsics=(fx, fy, cx, cy) "
                                       "in Python")
        else:
            colour_K, depth = colour.K, self._camera(self._depth)
            self._undistort_rgb = undistortion(colour.K, colour.dist, size)
        self._colour_K = colour_K
        if depth is not None:
            motion = self._colour_from_depth(colour, depth)
            same = (np.allclose(depth.K, colour.K) and depth.size == colour.size
                    and (motion is None or np.allclose(motion, np.eye(4), atol=1e-9)))
            if not same:
                if motion is None:
                    raise DatasetError(
                        f"{self.path}: depth ({self._depth.name}, frame {depth.frame!r}) is on another camera than "
                        f"colour ({self._rgb.name}, frame {colour.frame!r}) and /tf_static has no transform between "
                        "the two frames to register it; record /tf_static, or record depth aligned to colour")
                self._register = (depth.K, motion)
                self._undistort_depth = undistortion(depth.K, depth.dist, depth.size)
                return
        if tuple(depth_size) != tuple(size):
            raise DatasetError(f"{self.path}: depth images ({self._depth.name}) are {depth_size[0]}x{depth_size[1]} "
                               f"and colour images ({self._rgb.name}) {size[0]}x{size[1]}, and no CameraInfo of a "
                               "depth camera of that size says how to register one to the other")
        self._undistort_depth = self._undistort_rgb  # registered depth: the colour camera's lens

    def _colour_from_depth(self, colour: _Camera, depth: _Camera) -> Optional[np.ndarray]:
        """The 4x4 taking depth-camera points to colour-camera points (metres), None when the bag
        does not say."""
        rs = self._realsense_extrinsics(colour.topic), self._realsense_extrinsics(depth.topic)
        if rs[0] is not None and rs[1] is not None and rs[0][0] == rs[1][0]:
            # Each stream's extrinsics are from a common reference stream to it.
            return rs[0][1] @ np.linalg.inv(rs[1][1])
        if depth.frame == colour.frame and depth.frame:
            return np.eye(4)
        return _chain(self._static_transforms(), colour.frame, depth.frame)

    def _static_transforms(self) -> dict:
        """{(parent, child): 4x4 taking child-frame points to parent-frame points} of /tf_static."""
        edges = {}
        conns = [c for c in self._reader.connections if c.topic == "/tf_static"]
        if not conns:  # (no connections would mean all of them to rosbags)
            return edges
        with _reading(f"{self.path} /tf_static"):
            for c, _, raw in self._reader.messages(connections=conns):
                for ts in self._reader.deserialize(raw, c.msgtype).transforms:
                    edges[(ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/"))] = _transform(ts.transform)
        return edges

    def _realsense_extrinsics(self, info_topic: str):
        """(reference stream, 4x4 from it to this stream) of a RealSense SDK recording's stream
        whose CameraInfo is info_topic (`/device_0/sensor_1/Color_0/info/camera_info`), or None."""
        if not info_topic.endswith("/info/camera_info"):
            return None
        prefix = info_topic[: -len("info/camera_info")] + "tf/"
        conns = [c for c in self._reader.connections if c.topic.startswith(prefix)]
        if not conns:
            return None
        with _reading(f"{self.path} {conns[0].topic}"):
            _, _, raw = next(self._reader.messages(connections=conns[:1]))
            return conns[0].topic[len(prefix):], _transform(self._reader.deserialize(raw, conns[0].msgtype))

    def _realsense_depth_scale(self) -> Optional[float]:
        """Raw units per metre of a RealSense SDK recording (its "Depth Units" option, metres
        per unit: a Float32, a String since SDK 2.5x), None for other bags."""
        conns = [c for c in self._reader.connections
                 if c.topic.endswith(("/option/Depth Units/value", "/option/Depth_Units/value"))]
        if not conns:
            return None
        with _reading(f"{self.path} {conns[0].topic}"):
            _, _, raw = next(self._reader.messages(connections=conns[:1]))
            units = float(self._reader.deserialize(raw, conns[0].msgtype).data)
        if not units > 0:
            raise DatasetError(f"{self.path} {conns[0].topic}: depth units must be positive, got {units}")
        return 1.0 / units

    # --- messages ----------------------------------------------------------------------
    def _stamps(self, topic: _Topic) -> tuple:
        """(header stamps in seconds, where each message is: (log time ns, position among the
        topic's messages of that log time)), read in one streamed pass."""
        stamps, at = [], []
        last, same = None, 0
        with _reading(f"bag {self.path} topic {topic.name}"):
            for _, t, raw in self._reader.messages(connections=topic.connections):
                stamps.append(_stamp(self._reader.deserialize(raw, topic.msgtype)))
                same = same + 1 if t == last else 0
                at.append((t, same))
                last = t
        return np.array(stamps), at

    def _message(self, topic: _Topic, j: int):
        """The j-th message of topic, read through the bag's index."""
        t, same = (self._rgb_at if topic is self._rgb else self._depth_at)[j]
        where = f"{self.path} {topic.name} message {j}"
        with _reading(where):
            found = next(islice(self._reader.messages(connections=topic.connections, start=t, stop=t + 1), same, None),
                         None)
            if found is None:
                raise DatasetError(f"{where} is missing from the bag's index")
            return self._reader.deserialize(found[2], topic.msgtype)

    def _decode_colour(self, msg, where) -> np.ndarray:
        if self._rgb.msgtype == COMPRESSED:
            return decode_rgb(msg.data, where)
        ch = COLOUR_CHANNELS[msg.encoding.lower()]
        img = _pixels(msg, np.uint8, ch, where)
        if ch == 1:
            return np.repeat(img[..., None], 3, axis=2)
        return np.ascontiguousarray(img[..., 2::-1] if msg.encoding.lower().startswith("bgr") else img[..., :3])

    def _decode_depth(self, msg, where) -> np.ndarray:
        """Raw depth: uint16 (units of the depth scale) or float32 metres."""
        if self._depth.msgtype == IMAGE:
            dtype = np.dtype(DEPTH_DTYPES[msg.encoding.lower()]).newbyteorder(">" if msg.is_bigendian else "<")
            return _pixels(msg, dtype, 1, where).astype(dtype.newbyteorder("="))
        import cv2

        fmt = msg.format.lower()
        data = np.asarray(msg.data, dtype=np.uint8)
        if "compresseddepth" not in fmt:  # a 16-bit PNG through the plain compressed transport
            return decode_image(data, cv2.IMREAD_UNCHANGED, where)
        if "png" not in fmt or len(data) <= COMPRESSED_DEPTH_HEADER:
            raise DatasetError(f"{where}: compressedDepth {msg.format!r} cannot be read (png can)")
        img = decode_image(data[COMPRESSED_DEPTH_HEADER:], cv2.IMREAD_UNCHANGED, where)
        if not fmt.startswith("32fc1"):
            return img
        a, b = np.frombuffer(data[4:COMPRESSED_DEPTH_HEADER].tobytes(), dtype="<f4")
        with np.errstate(divide="ignore"):
            return np.where(img > 0, a / (img.astype(np.float32) - b), 0).astype(np.float32)

    # --- the sequence ----------------------------------------------------------------
    def _count(self):
        return len(self._pairs)

    def _read(self, i):
        ri, di = self._pairs[i]
        rgb = self._decode_colour(self._message(self._rgb, ri), f"{self.path} {self.rgb_topic} message {ri}")
        depth = self._decode_depth(self._message(self._depth, di), f"{self.path} {self.depth_topic} message {di}")
        if self._undistort_rgb is not None and self._undistort_rgb.fits(rgb):  # other sizes: an error later
            rgb = self._undistort_rgb.colour(rgb)
        if self._undistort_depth is not None and self._undistort_depth.fits(depth):
            depth = self._undistort_depth.depth(depth)
        if self._register is not None:
            K_depth, motion = self._register
            motion = motion.copy()
            if np.issubdtype(depth.dtype, np.integer):
                motion[:3, 3] *= self.depth_scale  # the depth's unit
            depth = register_depth(depth, K_depth, self._colour_K, motion, self.native_size)
        return rgb, depth, None

    def _timestamp(self, i):
        return self._times[i]


def _info_topics(image_topic: str) -> tuple:
    """Where an image topic's CameraInfo is: `camera_info` beside it (its transport suffix
    dropped), or older RealSense SDKs' `info/camera_info` beside its `image/`."""
    for suffix in TRANSPORTS:
        image_topic = image_topic[: -len(suffix)] if image_topic.endswith(suffix) else image_topic
    ns = image_topic.rsplit("/", 1)[0]
    return ns + "/camera_info", ns.rsplit("/", 1)[0] + "/info/camera_info"


def _pixels(msg, dtype, channels: int, where) -> np.ndarray:
    """An Image message's pixels as (h, w[, channels]), its row padding (step) dropped."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or len(data) < h * step:
        raise DatasetError(f"{where}: {len(data)} bytes of data for a {w}x{h} {msg.encoding} image with "
                           f"{step} bytes a row (truncated?)")
    img = data[: h * step].reshape(h, step)[:, :row].copy().view(dtype)
    return img.reshape(h, w, channels) if channels > 1 else img.reshape(h, w)


def _transform(tf) -> np.ndarray:
    """4x4 of a geometry_msgs/Transform."""
    t, q = tf.translation, tf.rotation
    return quat_to_pose((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


def _chain(edges: dict, target: str, source: str) -> Optional[np.ndarray]:
    """The 4x4 taking `source`-frame points to `target`-frame points through the transforms
    `edges` (either way round), None when they do not connect the two."""
    graph: dict = {}
    for (parent, child), T in edges.items():
        graph.setdefault(child, []).append((parent, T))
        graph.setdefault(parent, []).append((child, np.linalg.inv(T)))
    reached, todo = {source: np.eye(4)}, [source]
    while todo:
        frame = todo.pop()
        for other, T in graph.get(frame, ()):
            if other not in reached:
                reached[other] = T @ reached[frame]
                todo.append(other)
    return reached.get(target)
