"""A plain folder of colour and depth images: legslam's own format, and the way in for data
that comes in no published layout.

    color/ (or colour/, rgb/, image/, images/)   N.png / N.jpg
    depth/                                       N.png (16-bit, divided by the depth scale) or
                                                 N.tif / N.exr / N.npy (float metres)
    camera.json, cam_params.json, intrinsics.json, intrinsics.txt, camera-intrinsics.txt or K.txt
    poses.txt, pose.txt, groundtruth.txt or traj.txt    optional, line i = frame i: 7 numbers
                   (tx ty tz qx qy qz qw), 8 (TUM, with a timestamp) or 16 (row-major 4x4 c2w)
    timestamps.txt optional, line i = frame i's time in seconds (where no pose file has them)
    labels/ (or label/) N.png and classes.txt    optional: class ids, line k of classes.txt
                   names id k; 255 (8-bit) or 65535 (16-bit) marks unlabelled pixels

Colour and depth pair up by file name (without extension), in natural order. The JSON camera
may carry "depth_scale" (default 1000, millimetres); open(..., intrinsics=, depth_scale=)
supplies or overrides either. A negative focal length (ICL-NUIM's fy = -480) is handled by the
sequence: the image is flipped and the focal length negated, poses unchanged.
"""

from __future__ import annotations

import json
import queue
import threading
from pathlib import Path

import numpy as np

from ._io import (poses_from_rows, read_depth, read_intrinsics, read_labels, read_numbers, read_rgb,
                  read_text)
from .base import IGNORE_LABEL, NOMINAL_FPS, DatasetError, DatasetNotFoundError, Sequence, check_pose, paths_sorted

COLOUR_DIRS = ("color", "colour", "rgb", "image", "images")
DEPTH_DIRS = ("depth",)
LABEL_DIRS = ("labels", "label")
CAMERA_FILES = ("camera.json", "cam_params.json", "intrinsics.json", "intrinsics.txt",
                "camera-intrinsics.txt", "K.txt")
POSE_FILES = ("poses.txt", "pose.txt", "groundtruth.txt", "traj.txt")
COLOUR_EXTS = (".png", ".jpg", ".jpeg")
DEPTH_EXTS = (".png", ".tif", ".tiff", ".exr", ".npy")
DEFAULT_DEPTH_SCALE = 1000.0
TIMESTAMPS = "timestamps.txt"
# Frames a FolderWriter holds while its thread encodes the ones before.
WRITE_QUEUE = 32


def _first_dir(path: Path, names) -> Path | None:
    return next((path / n for n in names if (path / n).is_dir()), None)


def is_folder(path: Path) -> bool:
    return _first_dir(path, COLOUR_DIRS) is not None and _first_dir(path, DEPTH_DIRS) is not None


def _images(folder: Path, exts) -> dict:
    return {f.stem: f for f in paths_sorted([f for f in folder.iterdir() if f.suffix.lower() in exts])}


class FolderSequence(Sequence):
    format = "folder"

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name
        cdir, ddir = _first_dir(p, COLOUR_DIRS), _first_dir(p, DEPTH_DIRS)
        if cdir is None or ddir is None:
            raise DatasetNotFoundError(f"{p}: a folder dataset needs a colour folder ({', '.join(COLOUR_DIRS)}) "
                                       f"and a depth folder ({', '.join(DEPTH_DIRS)})")
        colour, depth = _images(cdir, COLOUR_EXTS), _images(ddir, DEPTH_EXTS)
        if not colour:
            raise DatasetNotFoundError(f"{cdir}: no {'/'.join(COLOUR_EXTS)} images")
        unpaired = sorted(set(colour) ^ set(depth))
        if unpaired:
            raise DatasetError(f"{p}: colour and depth images do not pair up by name; unpaired: "
                               f"{', '.join(unpaired[:5])}{' ...' if len(unpaired) > 5 else ''}")
        self._stems = list(colour)
        self._rgb, self._depth = list(colour.values()), [depth[s] for s in self._stems]
        n = len(self._stems)

        self._labels = None
        ldir = _first_dir(p, LABEL_DIRS)
        if ldir is not None:
            labels = _images(ldir, (".png",))
            missing = [s for s in self._stems if s not in labels]
            if missing:
                raise DatasetNotFoundError(f"{ldir}: no label image for {', '.join(missing[:5])}")
            self._labels = [labels[s] for s in self._stems]
            if (p / "classes.txt").is_file():
                self.class_names = [ln.strip() for ln in read_text(p / "classes.txt").splitlines() if ln.strip()]

        self._poses, self._stamps = [None] * n, None
        pose_file = next((p / f for f in POSE_FILES if (p / f).is_file()), None)
        if pose_file is not None:
            rows, lines = read_numbers(pose_file, columns=(7, 8, 16), line_numbers=True)
            stamps, poses = poses_from_rows(rows, pose_file, lines)
            if len(poses) != n:
                raise DatasetError(f"{pose_file} has {len(poses)} poses for {n} frames (line i must be frame i)")
            self._poses = [check_pose(T, f"{pose_file}:{line}") for line, T in zip(lines, poses)]
            self._stamps = stamps
        if self._stamps is None and (p / TIMESTAMPS).is_file():
            self._stamps = read_numbers(p / TIMESTAMPS, columns=(1,))[:, 0]
            if len(self._stamps) != n:
                raise DatasetError(f"{p / TIMESTAMPS} has {len(self._stamps)} times for {n} frames (line i is frame i)")

        cam = next((p / f for f in CAMERA_FILES if (p / f).is_file()), None)
        K, scale = None, None
        if cam is not None:
            K, scale, _ = read_intrinsics(cam)
        elif self._K_override is None:
            raise DatasetNotFoundError(f"{p}: no camera file (looked for {', '.join(CAMERA_FILES)}); "
                                       "add one or pass intrinsics=(fx, fy, cx, cy)")
        h, w = read_rgb(self._rgb[0]).shape[:2]
        self._setup(K if K is not None else self._K_override,
                    DEFAULT_DEPTH_SCALE if scale is None else scale, (w, h))

    def _count(self):
        return len(self._stems)

    def _read(self, i):
        labels = None
        if self._labels is not None:
            raw = read_labels(self._labels[i])
            labels = raw.astype(np.int32)
            labels[raw == np.iinfo(raw.dtype).max] = IGNORE_LABEL
            if self.class_names is not None and labels.max() >= len(self.class_names):
                raise DatasetError(f"{self._labels[i]}: label {labels.max()} but classes.txt names "
                                   f"only {len(self.class_names)} classes")
        return read_rgb(self._rgb[i]), read_depth(self._depth[i]), labels

    def _pose(self, i):
        return self._poses[i]

    def _timestamp(self, i):
        return self._stamps[i] if self._stamps is not None else i / NOMINAL_FPS


class FolderWriter:
    """Frames written as a folder dataset as they come (a live camera's), by a thread of its
    own so that encoding does not hold up the caller: color/N.png, depth/N.png (16-bit, raw
    units of depth_scale per metre), camera.json and, at close, timestamps.txt."""

    def __init__(self, path, K, width: int, height: int, depth_scale: float):
        self.path = Path(path)
        for sub in ("color", "depth"):
            (self.path / sub).mkdir(parents=True, exist_ok=True)
        camera = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": width, "height": height,
                  "depth_scale": depth_scale}
        (self.path / "camera.json").write_text(json.dumps(camera, indent=1) + "\n")
        self.depth_scale = depth_scale
        self._stamps: list = []
        self._error: Exception | None = None
        self._queue: queue.Queue = queue.Queue(WRITE_QUEUE)
        self._thread = threading.Thread(target=self._work, name="legslam-record", daemon=True)
        self._thread.start()

    def add(self, frame) -> None:
        if self._error is not None:
            raise self._error
        self._stamps.append(frame.timestamp)
        self._queue.put(frame)

    def close(self) -> None:
        """Waits for the frames added, then writes timestamps.txt."""
        self._queue.put(None)
        self._thread.join()
        (self.path / TIMESTAMPS).write_text("".join(f"{t:.6f}\n" for t in self._stamps))
        if self._error is not None:
            raise self._error

    def _work(self) -> None:
        import cv2

        while (frame := self._queue.get()) is not None:
            if self._error is not None:
                continue
            name = f"{frame.index:06d}.png"
            raw = np.clip(np.rint(frame.depth * self.depth_scale), 0, 65535).astype(np.uint16)
            for sub, img in (("color", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)), ("depth", raw)):
                ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
                try:
                    if not ok:
                        raise OSError(f"cannot encode {name}")
                    (self.path / sub / name).write_bytes(buf.tobytes())
                except OSError as e:
                    self._error = DatasetError(f"cannot record frame {frame.index} into {self.path / sub}: {e}")
