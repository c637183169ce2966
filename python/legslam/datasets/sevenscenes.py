"""Microsoft 7-Scenes and 3DMatch-style folders: frame-XXXXXX.color.{png,jpg},
frame-XXXXXX.depth.png (millimetres; 0 and 65535 invalid) and frame-XXXXXX.pose.txt (4x4
camera-to-world). camera-intrinsics.txt (3x3) is read from the folder or its parent (3DMatch
keeps one per scene); without one, 7-Scenes' nominal Kinect camera.
"""

from __future__ import annotations

from pathlib import Path

from ._io import first_existing, read_depth, read_intrinsics, read_pose_matrix, read_rgb
from .base import NOMINAL_FPS, DatasetNotFoundError, Sequence, make_K, paths_sorted

DEPTH_SCALE = 1000.0
DEFAULT_K = make_K(585.0, 585.0, 320.0, 240.0)


def is_sevenscenes(path: Path) -> bool:
    return any(path.glob("frame-*.depth.png"))


class SevenScenesSequence(Sequence):
    format = "7scenes"
    invalid_depth_values = (65535,)

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name if p.name not in ("data", "") else p.parent.name
        self._depth = paths_sorted(list(p.glob("frame-*.depth.png")))
        if not self._depth:
            raise DatasetNotFoundError(f"{p}: no frame-XXXXXX.depth.png files")
        self._stems = [f.name[: -len(".depth.png")] for f in self._depth]
        self._rgb = [first_existing([p / (s + e) for e in (".color.png", ".color.jpg")], f"colour for {s}.depth.png")
                     for s in self._stems]
        K = DEFAULT_K
        for cand in (p / "camera-intrinsics.txt", p.parent / "camera-intrinsics.txt"):
            if cand.is_file():
                K = read_intrinsics(cand)[0]
                break
        h, w = read_rgb(self._rgb[0]).shape[:2]
        self._setup(K, DEPTH_SCALE, (w, h))

    def _count(self):
        return len(self._depth)

    def _read(self, i):
        return read_rgb(self._rgb[i]), read_depth(self._depth[i]), None

    def _pose(self, i):
        return read_pose_matrix(self.path / (self._stems[i] + ".pose.txt"))

    def _timestamp(self, i):
        # The frame number, not the position, so a copied excerpt keeps the original times.
        number = self._stems[i][len("frame-"):]
        return (int(number) if number.isdigit() else i) / NOMINAL_FPS
