"""Microsoft 7-Scenes and 3DMatch-style folders: frame-XXXXXX.color.{png,jpg},
frame-XXXXXX.depth.png (millimetres; 0 and 65535 invalid) and frame-XXXXXX.pose.txt (4x4
camera-to-world). camera-intrinsics.txt (3x3) is read from the folder or its parent (3DMatch
keeps one per scene); without one, 7-Scenes' nominal Kinect camera.

7-Scenes' depth images are not registered to its colour images: they come from the Kinect's
depth camera (the nominal f = 585 of the dataset's page and of its camera-intrinsics.txt), the
colour from a camera of f = 525 about 2.6 cm beside it, so a surface's colour and depth lie up
to ~30 pixels apart near the image border. When a sequence has exactly that nominal depth
camera at 640x480 and no intrinsics are given, its depth is registered to the colour camera
(the calibration DSAC* and its successors use, from LIRIS' Kinect calibration), frames carry
the colour camera's intrinsics, and poses are the colour camera's. Giving `intrinsics` takes
the folder as registered.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._io import first_existing, read_depth, read_intrinsics, read_pose_matrix, read_rgb
from .base import NOMINAL_FPS, DatasetNotFoundError, Sequence, make_K, paths_sorted
from .registration import register_depth

DEPTH_SCALE = 1000.0
DEFAULT_K = make_K(585.0, 585.0, 320.0, 240.0)
NATIVE_SIZE = (640, 480)
# The Kinect's colour camera, and the rigid motion from its depth camera to it (metres).
COLOR_K = make_K(525.0, 525.0, 320.0, 240.0)
COLOR_FROM_DEPTH = np.array([
    [9.9996518012567637e-01, 2.6765126468950343e-03, -7.9041012313000904e-03, -2.5558943178152542e-02],
    [-2.7409311281316700e-03, 9.9996302803027592e-01, -8.1504520778013286e-03, 1.0109636268061706e-04],
    [7.8819942130445332e-03, 8.1718328771890631e-03, 9.9993554558014031e-01, 2.0318321729487039e-03],
    [0.0, 0.0, 0.0, 1.0]])
DEPTH_FROM_COLOR = np.linalg.inv(COLOR_FROM_DEPTH)


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
        #: Whether depth is registered to the colour camera here (see the module's docstring).
        self.registers_depth = (self._K_override is None and (w, h) == NATIVE_SIZE
                                and np.allclose(K, DEFAULT_K))
        self._setup(COLOR_K if self.registers_depth else K, DEPTH_SCALE, (w, h))

    def _count(self):
        return len(self._depth)

    def _read(self, i):
        rgb, depth = read_rgb(self._rgb[i]), read_depth(self._depth[i])
        if self.registers_depth and depth.shape == NATIVE_SIZE[::-1]:  # other sizes: an error later
            depth = np.where(np.isin(depth, self.invalid_depth_values), 0, depth).astype(depth.dtype)
            motion = COLOR_FROM_DEPTH.copy()
            motion[:3, 3] *= self.depth_scale  # the depth's unit
            depth = register_depth(depth, DEFAULT_K, COLOR_K, motion, NATIVE_SIZE)
        return rgb, depth, None

    def _pose(self, i):
        pose = read_pose_matrix(self.path / (self._stems[i] + ".pose.txt"))
        if self.registers_depth and pose is not None:  # the depth camera's: the colour camera's
            pose = pose @ DEPTH_FROM_COLOR
        return pose

    def _timestamp(self, i):
        # The frame number, not the position, so a copied excerpt keeps the original times.
        number = self._stems[i][len("frame-"):]
        return (int(number) if number.isdigit() else i) / NOMINAL_FPS
