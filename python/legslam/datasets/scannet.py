"""ScanNet frames as exported by its SensReader: color/N.jpg, depth/N.png (millimetres),
pose/N.txt (4x4 camera-to-world; -inf rows where tracking was lost, read as no pose) and
intrinsic/intrinsic_depth.txt. Colour is resized to the depth image's size, whose intrinsics
it then shares.

label-filt/N.png, when present, becomes per-pixel ScanNet-20 class ids (the benchmark's 20
classes; everything else IGNORE_LABEL). Label images hold either NYU40 ids (scannet_frames_25k
and most exports) or raw ScanNet ids (the 2d-label-filt zips); the latter need
scannetv2-labels.combined.tsv beside the scene, or one or two folders up, to map them to NYU40.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ._io import first_existing, read_depth, read_intrinsics, read_labels, read_pose_matrix, read_rgb
from .base import IGNORE_LABEL, DatasetError, DatasetNotFoundError, Sequence, paths_sorted

DEPTH_SCALE = 1000.0
# The ScanNet-20 benchmark classes and the NYU40 id of each, in benchmark order.
SCANNET20_NAMES = ["wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window",
                   "bookshelf", "picture", "counter", "desk", "curtain", "refrigerator",
                   "shower curtain", "toilet", "sink", "bathtub", "otherfurniture"]
SCANNET20_NYU40_IDS = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39]
LABELS_TSV = "scannetv2-labels.combined.tsv"


def is_scannet(path: Path) -> bool:
    return all((path / d).is_dir() for d in ("color", "depth", "pose", "intrinsic"))


def nyu40_to_scannet20() -> np.ndarray:
    lut = np.full(41, IGNORE_LABEL, dtype=np.int32)
    lut[SCANNET20_NYU40_IDS] = np.arange(len(SCANNET20_NYU40_IDS))
    return lut


def raw_to_nyu40(tsv: Path) -> np.ndarray:
    """Lookup table raw ScanNet id -> NYU40 id (0 = unknown) from the dataset's label tsv."""
    with open(tsv, newline="") as f:
        try:
            pairs = [(int(r["id"]), int(r["nyu40id"] or 0)) for r in csv.DictReader(f, delimiter="\t")]
        except (KeyError, ValueError) as e:
            raise DatasetError(f"{tsv}: expected the columns 'id' and 'nyu40id' ({e})") from None
    lut = np.zeros(max(i for i, _ in pairs) + 1, dtype=np.int32)
    for i, n in pairs:
        lut[i] = n
    return lut


class ScanNetSequence(Sequence):
    format = "scannet"

    def __init__(self, path, **kw):
        super().__init__(path, **kw)
        p = self.path
        self.name = p.name
        self._depth = paths_sorted(list((p / "depth").glob("*.png")))
        if not self._depth:
            raise DatasetNotFoundError(f"{p / 'depth'}: no .png depth images")
        self._stems = [f.stem for f in self._depth]
        self._rgb = [first_existing([p / "color" / (s + e) for e in (".jpg", ".png")], f"colour for depth/{s}.png") for s in self._stems]
        self._labels = None
        if (p / "label-filt").is_dir():
            self._labels = [first_existing([p / "label-filt" / (s + ".png")], "label image") for s in self._stems]
            self.class_names = list(SCANNET20_NAMES)
            self._raw_lut = None
            for d in (p, p.parent, p.parent.parent):
                if (d / LABELS_TSV).is_file():
                    self._raw_lut = raw_to_nyu40(d / LABELS_TSV)
                    break
        intr = p / "intrinsic"
        if (intr / "intrinsic_depth.txt").is_file():
            K = read_intrinsics(intr / "intrinsic_depth.txt")[0]
        else:
            raise DatasetNotFoundError(f"{intr}: missing intrinsic_depth.txt (the camera of the depth images)")
        h, w = read_depth(self._depth[0]).shape
        self._setup(K, DEPTH_SCALE, (w, h))

    def _count(self):
        return len(self._depth)

    def _read(self, i):
        import cv2

        depth = read_depth(self._depth[i])
        rgb = read_rgb(self._rgb[i])
        if rgb.shape[:2] != depth.shape:
            rgb = cv2.resize(rgb, depth.shape[::-1], interpolation=cv2.INTER_AREA)
        labels = None
        if self._labels is not None:
            raw = read_labels(self._labels[i])
            if raw.shape != depth.shape:
                raw = cv2.resize(raw, depth.shape[::-1], interpolation=cv2.INTER_NEAREST)
            labels = self._to_scannet20(raw.astype(np.int64), self._labels[i])
        return rgb, depth, labels

    def _to_scannet20(self, raw: np.ndarray, where: Path) -> np.ndarray:
        if self._raw_lut is not None:
            if raw.max() >= len(self._raw_lut):
                raise DatasetError(f"{where}: label {raw.max()} is not in {LABELS_TSV}")
            raw = self._raw_lut[raw]
        elif raw.max() > 40:
            raise DatasetError(f"{where}: label {raw.max()} is not an NYU40 id; these look like raw ScanNet "
                               f"ids, which need {LABELS_TSV} beside the scene or one or two folders up")
        return nyu40_to_scannet20()[raw]

    def _pose(self, i):
        return read_pose_matrix(self.path / "pose" / (self._stems[i] + ".txt"))
