"""Recordings written the way their recorders write them, from frames whose values are known:
ROS1 and ROS2 bags (rosbags' writers, messages as ROS drivers fill them), Stray Scanner
exports and Record3D archives. Used by the tests and by benches/bench_sources.py; nothing
here calls the loaders under test.

A recording is made of Shots: colour (uint8 RGB), depth (float metres, 0 = none) and a
time in seconds, with the camera-to-world pose (OpenCV axes) where the recorder has one.
"""

from __future__ import annotations

import json
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

STAMP0 = 1_300_000_000.25  # a wall-clock time in the range of real recordings
DEPTH_DELAY = 0.004  # depth stamped 4 ms after colour, as two sensors are
LOG_DELAY = 0.010  # the recorder receives a message 10 ms after its stamp
TUM_TOPICS = ("/camera/rgb/image_color", "/camera/depth/image")
# ROS' compressed_depth_image_transport quantisation of 32FC1 depth (its defaults).
DEPTH_QUANTIZATION, DEPTH_MAX = 100.0, 10.0


@dataclass
class Shot:
    rgb: np.ndarray
    depth: np.ndarray
    t: float
    pose: Optional[np.ndarray] = None


def synthetic_shots(n: int, width: int, height: int, seed: int = 3, K=None, poses=None) -> tuple:
    """(shots, K): n frames of the built-in scene ray cast at width x height (with K, default
    the scene's camera; at `poses`, default its camera path), 30 Hz from STAMP0."""
    from legslam.datasets import synthetic as S

    rng = np.random.default_rng(seed)
    parts, textures, path = S.build_scene(rng), S.Textures(rng), S.camera_path(n, rng)
    K = S.intrinsics(width, height) if K is None else K
    poses = path if poses is None else poses
    shots = []
    for i, pose in enumerate(poses):
        rgb, depth, _ = S.render(parts, textures, K, pose, width, height)
        shots.append(Shot(rgb, depth.astype(np.float32), STAMP0 + i / 30.0, pose))
    return shots, K


def folder_shots(folder: Path, n: int) -> tuple:
    """(shots, K) of the first n frames of a 7-Scenes folder, as legslam reads them (depth
    registered to the colour camera)."""
    from legslam.datasets import open as open_dataset

    seq = open_dataset(folder, max_frames=n)
    return [Shot(f.rgb, f.depth, STAMP0 + f.timestamp, f.pose) for f in seq], seq.K


# --- ROS bags -----------------------------------------------------------------------------

class BagWriter:
    """Messages into a ROS1 .bag (storage "ros1") or a ROS2 bag folder ("sqlite3", "mcap")."""

    def __init__(self, path: Path, storage: str):
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg

        self.ros1 = storage == "ros1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # Noetic's store lacks tf2_msgs
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self.writer = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.connections: dict = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def T(self, name: str):
        return self.ts.types[name]

    def header(self, t: float, frame: str):
        sec = int(t)
        stamp = self.T("builtin_interfaces/msg/Time")(sec=sec, nanosec=int(round((t - sec) * 1e9)))
        kw = {"seq": 0} if self.ros1 else {}
        return self.T("std_msgs/msg/Header")(stamp=stamp, frame_id=frame, **kw)

    def write(self, topic: str, msg, t_log: float) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        data = self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)
        self.writer.write(self.connections[topic], int(round(t_log * 1e9)), data)

    def image(self, t: float, frame: str, img: np.ndarray, encoding: str):
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).view(np.uint8).reshape(-1)
        return self.T("sensor_msgs/msg/Image")(header=self.header(t, frame), height=h, width=w, encoding=encoding,
                                               is_bigendian=0, step=len(data) // h, data=data)

    def compressed(self, t: float, frame: str, data: bytes, fmt: str):
        return self.T("sensor_msgs/msg/CompressedImage")(header=self.header(t, frame), format=fmt,
                                                         data=np.frombuffer(data, dtype=np.uint8))

    def camera_info(self, t: float, frame: str, K: np.ndarray, size: tuple, dist=(0.0,) * 5, model="plumb_bob"):
        f = (lambda n: n.upper()) if self.ros1 else (lambda n: n)
        P = np.zeros((3, 4))
        P[:3, :3] = K
        roi = self.T("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        fields = {f("d"): np.asarray(dist, dtype=np.float64), f("k"): K.reshape(-1).astype(np.float64),
                  f("r"): np.eye(3).reshape(-1), f("p"): P.reshape(-1)}
        return self.T("sensor_msgs/msg/CameraInfo")(
            header=self.header(t, frame), height=size[1], width=size[0], distortion_model=model,
            binning_x=0, binning_y=0, roi=roi, **fields)

    def transform(self, T: np.ndarray):
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        return self.T("geometry_msgs/msg/Transform")(
            translation=self.T("geometry_msgs/msg/Vector3")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=self.T("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))

    def tf_static(self, t: float, edges) -> object:
        """A TFMessage of (parent, child, 4x4 taking child points to parent points)."""
        stamped = [self.T("geometry_msgs/msg/TransformStamped")(header=self.header(t, parent), child_frame_id=child,
                                                                transform=self.transform(T))
                   for parent, child, T in edges]
        return self.T("tf2_msgs/msg/TFMessage")(transforms=stamped)


def encode(img: np.ndarray, ext: str) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok, ext
    return buf.tobytes()


def colour_message(w: BagWriter, t: float, frame: str, rgb: np.ndarray, colour: str):
    if colour in ("jpeg", "png"):
        return w.compressed(t, frame, encode(rgb[..., ::-1], "." + colour.replace("jpeg", "jpg")), colour)
    img = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)}[colour]
    return w.image(t, frame, img, colour)


def depth_message(w: BagWriter, t: float, frame: str, depth: np.ndarray, kind: str):
    """16UC1 (mm), 32FC1 (m), or compressedDepth of either ("16UC1 compressedDepth")."""
    mm = np.round(depth * 1000.0).astype(np.uint16)
    if kind == "16UC1":
        return w.image(t, frame, mm, "16UC1")
    if kind == "32FC1":
        return w.image(t, frame, depth.astype(np.float32), "32FC1")
    if kind == "16UC1 compressedDepth":
        return w.compressed(t, frame, struct.pack("<iff", 0, 0, 0) + encode(mm, ".png"), "16UC1; compressedDepth png")
    a = DEPTH_QUANTIZATION * (DEPTH_QUANTIZATION + 1.0)
    b = 1.0 - a / DEPTH_MAX
    inv = np.where(depth > 0, np.round(a / np.maximum(depth, 1e-6) + b), 0).astype(np.uint16)
    return w.compressed(t, frame, struct.pack("<iff", 0, a, b) + encode(inv, ".png"), "32FC1; compressedDepth png")


def write_bag(path: Path, shots, K, *, storage: str = "ros1", colour: str = "rgb8", depth: Optional[str] = "16UC1",
              topics=TUM_TOPICS, info: bool = True, dist=(0.0,) * 5, model="plumb_bob", depth_camera=None, extra=(),
              skip_depth=()) -> Path:
    """A bag of the shots on `topics` (colour, depth), with CameraInfo beside each (unless
    not `info`) and a compressed topic name for compressed images. depth=None: no depth topic.
    depth_camera (K_depth, [depth images], link_from_colour, link_from_depth): depth seen by
    another camera, its frames tied to the colour's through a "camera_link" in /tf_static.
    extra: (topic, colour kind) of more colour topics, for choosing among. skip_depth: shots
    whose depth message is missing."""
    path = Path(path)
    rgb_topic, depth_topic = topics
    if colour in ("jpeg", "png"):
        rgb_topic += "/compressed"
    if depth is not None and "compressedDepth" in depth:
        depth_topic += "/compressedDepth"
    ns = lambda topic: topic.split("/image")[0] if "/image" in topic else topic.rsplit("/", 1)[0]  # noqa: E731
    with BagWriter(path, storage) as w:
        t0 = shots[0].t
        if depth_camera is not None:
            K_d, depth_images, link_from_colour, link_from_depth = depth_camera
            if link_from_colour is not None:  # else a bag that does not say where depth's camera is
                w.write("/tf_static", w.tf_static(t0, [("camera_link", "color_optical", link_from_colour),
                                                       ("camera_link", "depth_optical", link_from_depth)]), t0)
        for k, s in enumerate(shots):
            h, wd = s.rgb.shape[:2]
            w.write(rgb_topic, colour_message(w, s.t, "color_optical", s.rgb, colour), s.t + LOG_DELAY)
            if info:
                w.write(ns(rgb_topic) + "/camera_info", w.camera_info(s.t, "color_optical", K, (wd, h), dist, model),
                        s.t + LOG_DELAY)
            for topic, kind in extra:
                w.write(topic, colour_message(w, s.t, "other", s.rgb, kind), s.t + LOG_DELAY)
            if depth is None or k in skip_depth:
                continue
            td = s.t + DEPTH_DELAY
            if depth_camera is not None:
                img = depth_images[k]
                w.write(depth_topic, depth_message(w, td, "depth_optical", img, depth), td + LOG_DELAY)
                w.write(ns(depth_topic) + "/camera_info",
                        w.camera_info(td, "depth_optical", K_d, img.shape[::-1]), td + LOG_DELAY)
            else:
                w.write(depth_topic, depth_message(w, td, "color_optical", s.depth, depth), td + LOG_DELAY)
                if info:
                    w.write(ns(depth_topic) + "/camera_info", w.camera_info(td, "color_optical", K, (wd, h), dist),
                            td + LOG_DELAY)
    return path


def write_realsense_bag(path: Path, shots, K, K_depth, depth_images, colour_from_depth, depth_units: float) -> Path:
    """A ROS1 bag in older RealSense SDKs' layout (their ros_writer): /device_0/sensor_N/<Stream>_0/
    image/data and info/camera_info, 16-bit depth (mono16) in the "Depth Units" option's metres,
    and each stream's extrinsics from the reference stream (here depth) in tf/0; an infrared
    stream beside them."""
    s0 = "/device_0/sensor_0"
    colour, depth, infrared = "/device_0/sensor_1/Color_0", f"{s0}/Depth_0", f"{s0}/Infrared_1"
    with BagWriter(Path(path), "ros1") as w:
        t0 = shots[0].t
        w.write(f"{s0}/option/Depth Units/value", w.T("std_msgs/msg/Float32")(data=depth_units), t0)
        w.write(f"{depth}/tf/0", w.transform(np.eye(4)), t0)
        w.write(f"{colour}/tf/0", w.transform(colour_from_depth), t0)
        for s, d in zip(shots, depth_images):
            h, wd = s.rgb.shape[:2]
            w.write(f"{colour}/image/data", colour_message(w, s.t, "0", s.rgb, "rgb8"), s.t)
            w.write(f"{colour}/info/camera_info", w.camera_info(s.t, "0", K, (wd, h)), s.t)
            w.write(f"{infrared}/image/data", colour_message(w, s.t, "0", s.rgb, "mono8"), s.t)
            units = np.round(d / depth_units).astype(np.uint16)
            w.write(f"{depth}/image/data", w.image(s.t + DEPTH_DELAY, "0", units, "mono16"), s.t + DEPTH_DELAY)
            w.write(f"{depth}/info/camera_info", w.camera_info(s.t, "0", K_depth, d.shape[::-1]), s.t + DEPTH_DELAY)
    return Path(path)


def record_realsense(path: Path, shots, K, K_depth, depth_images, colour_from_depth, depth_units: float) -> Path:
    """A recording made by the RealSense SDK itself (pyrealsense2's recorder on a software
    device with a depth and a colour sensor): colour rgb8, depth z16 in depth_units, the
    depth-to-colour extrinsics registered as a device does. SDK 2.5x writes a .db3. The
    recorder now and then loses a frame on a loaded machine: recorded again until the file
    holds every frame (counted in the file's messages, not by the reader under test)."""
    import sqlite3

    for _ in range(5):
        Path(path).unlink(missing_ok=True)
        _record_realsense_once(path, shots, K, K_depth, depth_images, colour_from_depth, depth_units)
        with sqlite3.connect(path) as db:
            counts = [n for n, in db.execute(
                "SELECT COUNT(*) FROM messages JOIN topics ON topics.id = messages.topic_id "
                "WHERE topics.name LIKE '%/image/camera_info' GROUP BY topics.id")]
        if counts == [len(shots)] * 2:
            return Path(path)
    raise RuntimeError(f"the RealSense SDK's recorder lost frames of {path} five times")


def _record_realsense_once(path: Path, shots, K, K_depth, depth_images, colour_from_depth, depth_units):
    import time

    import pyrealsense2 as rs

    device = rs.software_device()

    def stream(sensor, kind, fmt, bpp, uid, K, size):
        intr = rs.intrinsics()
        intr.width, intr.height = size
        intr.fx, intr.fy, intr.ppx, intr.ppy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
        v = rs.video_stream()
        v.type, v.index, v.uid, v.width, v.height = kind, 0, uid, size[0], size[1]
        v.fps, v.bpp, v.fmt, v.intrinsics = 30, bpp, fmt, intr
        return sensor.add_video_stream(v)

    depth_sensor, colour_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth = stream(depth_sensor, rs.stream.depth, rs.format.z16, 2, 0, K_depth, depth_images[0].shape[::-1])
    colour = stream(colour_sensor, rs.stream.color, rs.format.rgb8, 3, 1, K, shots[0].rgb.shape[1::-1])
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
    extrinsics = rs.extrinsics()
    extrinsics.rotation = colour_from_depth[:3, :3].T.reshape(-1).tolist()  # column-major
    extrinsics.translation = colour_from_depth[:3, 3].tolist()
    depth.register_extrinsics_to(colour, extrinsics)
    recorder = rs.recorder(str(path), device)
    depth_sensor.open(depth)
    colour_sensor.open(colour)
    queue = rs.frame_queue(100)
    depth_sensor.start(queue)
    colour_sensor.start(queue)
    kept = []  # the SDK reads the pixels after on_video_frame returns
    for k, (s, d) in enumerate(zip(shots, depth_images)):
        units = np.round(d / depth_units).astype(np.uint16)
        for sensor, profile, bpp, img in ((depth_sensor, depth, 2, units), (colour_sensor, colour, 3, s.rgb)):
            f = rs.software_video_frame()
            kept.append(np.ascontiguousarray(img))
            f.pixels, f.stride, f.bpp = kept[-1], img.shape[1] * bpp, bpp
            f.timestamp, f.domain, f.frame_number = 1e3 * s.t, rs.timestamp_domain.hardware_clock, k
            f.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(f)
        time.sleep(0.02)
    for sensor in (depth_sensor, colour_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # writes the file
    return Path(path)


# --- phones -------------------------------------------------------------------------------

ARKIT_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y up and z backward in ARKit


def arkit_pose(pose: np.ndarray) -> np.ndarray:
    """ARKit's camera.transform of a camera at c2w `pose` (OpenCV axes): its columns are the
    camera's axes in the world, ARKit's y (up) and z (backward) OpenCV's -y and -z."""
    return pose @ ARKIT_FROM_OPENCV


def write_stray(path: Path, shots, K_video, depth_shots, confidence=None, fps: float = 30.0) -> Path:
    """A Stray Scanner export: the shots' colour as rgb.mp4 (mp4v), `depth_shots`' depth (any
    size) as millimetre PNGs, confidence maps (or none), camera_matrix.csv (K of the video)
    and odometry.csv as the app writes it (quaternion = ARKit's camera rotation times a half
    turn about x)."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    (path / "depth").mkdir(parents=True)
    h, w = shots[0].rgb.shape[:2]
    video = cv2.VideoWriter(str(path / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert video.isOpened()
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    q_AC = Rotation.from_quat([1.0, 0.0, 0.0, 0.0])  # (x, y, z, w): the app's half turn about x
    for k, (s, d) in enumerate(zip(shots, depth_shots)):
        video.write(np.ascontiguousarray(s.rgb[..., ::-1]))
        (path / "depth" / f"{k:06d}.png").write_bytes(encode(np.round(d.depth * 1000).astype(np.uint16), ".png"))
        if confidence is not None:
            (path / "confidence").mkdir(exist_ok=True)
            (path / "confidence" / f"{k:06d}.png").write_bytes(encode(confidence[k].astype(np.uint8), ".png"))
        T_WA = arkit_pose(s.pose)
        q = (Rotation.from_matrix(T_WA[:3, :3]) * q_AC).as_quat()
        x, y, z = T_WA[:3, 3]
        rows.append(f"{s.t:.6f}, {k:06d}, {x:.9f}, {y:.9f}, {z:.9f}, " + ", ".join(f"{v:.9f}" for v in q))
    video.release()
    (path / "odometry.csv").write_text("\n".join(rows) + "\n")
    (path / "camera_matrix.csv").write_text("\n".join(", ".join(f"{v:.6f}" for v in r) for r in K_video) + "\n")
    return path


def write_r3d(path: Path, shots, K, depth_shots, confidence=None) -> Path:
    """A Record3D .r3d archive: metadata (K column-major, poses as ARKit's camera.transform in
    [qx, qy, qz, qw, px, py, pz]), rgbd/N.jpg, LZFSE float32 rgbd/N.depth and rgbd/N.conf."""
    import lzfse
    from scipy.spatial.transform import Rotation

    h, w = shots[0].rgb.shape[:2]
    dh, dw = depth_shots[0].depth.shape
    poses = []
    for s in shots:
        T = arkit_pose(s.pose)
        poses.append([*Rotation.from_matrix(T[:3, :3]).as_quat().tolist(), *T[:3, 3].tolist()])
    meta = {"w": w, "h": h, "dw": dw, "dh": dh, "fps": 30, "K": K.T.reshape(-1).tolist(), "poses": poses,
            "frameTimestamps": [s.t for s in shots], "initPose": poses[0], "cameraType": 1}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("metadata", json.dumps(meta))
        for k, (s, d) in enumerate(zip(shots, depth_shots)):
            z.writestr(f"rgbd/{k}.jpg", encode(s.rgb[..., ::-1], ".jpg"))
            z.writestr(f"rgbd/{k}.depth", lzfse.compress(d.depth.astype("<f4").tobytes()))
            if confidence is not None:
                z.writestr(f"rgbd/{k}.conf", lzfse.compress(confidence[k].astype(np.uint8).tobytes()))
    return Path(path)
