"""Which format a path holds. Formats are tried from the most to the least specific layout:
a ScanNet scene also matches the plain-folder rules, so the folder format comes last."""

from __future__ import annotations

from pathlib import Path

from .bag import BagSequence, is_bag
from .base import DatasetNotFoundError
from .folder import FolderSequence, is_folder
from .record3d import Record3DSequence, is_record3d
from .replica import ReplicaSequence, is_replica
from .scannet import ScanNetSequence, is_scannet
from .sevenscenes import SevenScenesSequence, is_sevenscenes
from .stray import StraySequence, is_stray
from .tum import TUMSequence, is_tum

# name -> (sequence class, detector, what the detector looks for)
FORMATS = {
    "bag": (BagSequence, is_bag, "a ROS1 .bag file, a ROS2 bag folder with metadata.yaml, a .db3 or .mcap file"),
    "record3d": (Record3DSequence, is_record3d, "a Record3D .r3d export"),
    "stray": (StraySequence, is_stray, "Stray Scanner's rgb.mp4 and depth/"),
    "tum": (TUMSequence, is_tum, "rgb.txt and depth.txt"),
    "replica": (ReplicaSequence, is_replica, "traj.txt and results/frame*.jpg"),
    "scannet": (ScanNetSequence, is_scannet, "color/, depth/, pose/ and intrinsic/"),
    "7scenes": (SevenScenesSequence, is_sevenscenes, "frame-XXXXXX.depth.png files"),
    "folder": (FolderSequence, is_folder, "color/ (or rgb/, image/, images/) and depth/"),
}


def detect(path: Path) -> str:
    """The name of the format at path (a sequence's folder, or a recording's file), or
    DatasetNotFoundError listing what was looked for."""
    path = Path(path)
    if not path.exists():
        raise DatasetNotFoundError(f"{path} does not exist")
    for name, (_, matches, _) in FORMATS.items():
        if matches(path):
            return name
    looked = "\n".join(f"  {name}: {what}" for name, (_, _, what) in FORMATS.items())
    hint = ""
    subdirs = sorted(d for d in path.iterdir() if d.is_dir())[:100] if path.is_dir() else []  # a hint, not a search
    found = [(d.name, n) for d in subdirs for n, (_, m, _) in FORMATS.items() if m(d)]
    if found:
        hint = "\nbut these sub-folders match: " + ", ".join(f"{d} ({n})" for d, n in found[:5])
    raise DatasetNotFoundError(f"{path}: no dataset format recognised; looked for\n{looked}{hint}")
