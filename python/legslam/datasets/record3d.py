"""Record3D (iOS, LiDAR) `.r3d` exports: a zip archive of

    metadata            JSON: w, h (colour), dw, dh (depth), K (3x3 of the colour image,
                        column-major), poses ([qx, qy, qz, qw, px, py, pz] a frame: ARKit's
                        camera-to-world), frameTimestamps (seconds; else fps gives the times)
    rgbd/N.jpg          colour
    rgbd/N.depth        depth: LZFSE-compressed float32 metres, dh x dw (NaN where none)
    rgbd/N.conf         LZFSE-compressed uint8 confidence, 0 low, 1 medium, 2 high (optional)

read in place (members are read when their frame is). The poses are ARKit's, in its camera
axes (x right, y up, z backward), and are turned into ours; they are the ground truth of the
figures. Frames come at the depth's resolution (see _phone). LZFSE is decoded by the `lzfse`
package (`pip install 'legslam[phone]'`).
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import numpy as np

from ._io import decode_rgb, quat_to_pose
from ._phone import ARKIT_TO_OPENCV, PhoneSequence
from .base import NOMINAL_FPS, DatasetError, DatasetNotFoundError, check_pose, scale_K

FRAME_FILE = re.compile(r"rgbd/(\d+)\.jpg")


def is_record3d(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".r3d"


class Record3DSequence(PhoneSequence):
    format = "record3d"

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.stem
        try:
            import lzfse
        except ImportError:
            raise DatasetError(f"{p}: reading Record3D depth needs lzfse: pip install 'legslam[phone]'") from None
        self._lzfse = lzfse
        try:
            self._zip = zipfile.ZipFile(p)
            names = set(self._zip.namelist())
        except (zipfile.BadZipFile, OSError) as e:
            raise DatasetError(f"cannot read {p} as a Record3D export (a zip archive; cut short?): {e}") from None
        if "metadata" not in names:
            raise DatasetNotFoundError(f"{p}: no metadata in the archive (is it a Record3D .r3d export?)")
        try:
            meta = json.loads(self._member("metadata"))
            w, h, dw, dh = (int(meta[k]) for k in ("w", "h", "dw", "dh"))
            K = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T
            poses = meta.get("poses")
            stamps = meta.get("frameTimestamps")
            fps = float(meta.get("fps") or NOMINAL_FPS)
        except (ValueError, KeyError, TypeError) as e:
            raise DatasetError(f"{p}: metadata is not the JSON Record3D writes ({type(e).__name__}: {e})") from None
        self._numbers = sorted(int(m.group(1)) for n in names if (m := FRAME_FILE.fullmatch(n)))
        if not self._numbers:
            raise DatasetNotFoundError(f"{p}: no rgbd/N.jpg frames in the archive")
        missing = [n for n in self._numbers if f"rgbd/{n}.depth" not in names]
        if missing:
            raise DatasetNotFoundError(f"{p}: no rgbd/N.depth for frames {', '.join(map(str, missing[:5]))}")
        self._has_confidence = all(f"rgbd/{n}.conf" in names for n in self._numbers)
        last = self._numbers[-1]
        for what, values in (("poses", poses), ("frameTimestamps", stamps)):
            if values is not None and len(values) <= last:
                raise DatasetError(f"{p}: metadata has {len(values)} {what}, too few for frame {last}")
        self._poses = poses
        self._stamps = stamps
        self._fps = fps
        self._depth_size = (dw, dh)
        self._setup(scale_K(K, dw / w, dh / h), 1.0, (dw, dh))

    def _member(self, name: str) -> bytes:
        try:
            return self._zip.read(name)
        except (KeyError, zipfile.BadZipFile, OSError, EOFError) as e:
            raise DatasetError(f"{self.path}: cannot read {name} ({type(e).__name__}: {e})") from None

    def _unpack(self, name: str, dtype) -> np.ndarray:
        """An LZFSE-compressed dh x dw image."""
        w, h = self._depth_size
        try:
            raw = self._lzfse.decompress(self._member(name))
        except self._lzfse.error as e:
            raise DatasetError(f"{self.path}: {name} is not LZFSE data ({e})") from None
        a = np.frombuffer(raw, dtype=dtype)
        if a.size != w * h:
            raise DatasetError(f"{self.path}: {name} holds {a.size} values, not the {w}x{h} of the depth (dw, dh)")
        return a.reshape(h, w)

    def _count(self):
        return len(self._numbers)

    def _frame(self, i):
        n = self._numbers[i]
        rgb = decode_rgb(self._member(f"rgbd/{n}.jpg"), f"{self.path}: rgbd/{n}.jpg")
        confidence = self._unpack(f"rgbd/{n}.conf", np.uint8) if self._has_confidence else None
        return rgb, self._unpack(f"rgbd/{n}.depth", np.float32), confidence

    def _pose(self, i):
        if self._poses is None:
            return None
        where = f"{self.path} metadata poses[{self._numbers[i]}]"
        try:
            qx, qy, qz, qw, px, py, pz = (float(v) for v in self._poses[self._numbers[i]])
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: expected [qx, qy, qz, qw, px, py, pz]") from None
        try:
            T = quat_to_pose((px, py, pz), (qx, qy, qz, qw))
        except DatasetError as e:
            raise DatasetError(f"{where}: {e}") from None
        return check_pose(T @ ARKIT_TO_OPENCV, where)

    def _timestamp(self, i):
        n = self._numbers[i]
        return float(self._stamps[n]) if self._stamps is not None else n / self._fps
