"""File reading shared by the loaders. cv2 returns None instead of raising on a missing or
corrupt file; every reader here turns that into a DatasetError that names the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .base import DatasetError, DatasetNotFoundError, as_K, check_pose


def _imread(path: Path, flags: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise DatasetNotFoundError(f"missing image {path}")
    # imdecode (not imread) so that non-ASCII paths work on every platform.
    img = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8), flags)
    if img is None:
        raise DatasetError(f"cannot decode image {path} (corrupt or not an image)")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """HxWx3 uint8 RGB from any 8-bit colour (or grey) image."""
    import cv2

    img = _imread(Path(path), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path) -> np.ndarray:
    """Raw single-channel depth: uint16 from PNG, float from TIFF/EXR/.npy (metres)."""
    import cv2

    path = Path(path)
    if path.suffix == ".npy":
        if not path.is_file():
            raise DatasetNotFoundError(f"missing depth {path}")
        try:
            img = np.load(path, allow_pickle=False)
        except ValueError as e:
            raise DatasetError(f"cannot read depth {path}: {e}") from None
    else:
        img = _imread(path, cv2.IMREAD_ANYDEPTH)
    if img.ndim != 2:
        raise DatasetError(f"depth {path} must have one channel, it has shape {img.shape}")
    if img.dtype == np.uint8:
        raise DatasetError(f"depth {path} is 8-bit; expected 16-bit integer or float depth")
    return img


def read_labels(path: Path) -> np.ndarray:
    """Single-channel 8- or 16-bit label image as stored (class ids are mapped by the format)."""
    import cv2

    img = _imread(Path(path), cv2.IMREAD_UNCHANGED)
    if img.ndim != 2 or not np.issubdtype(img.dtype, np.integer):
        raise DatasetError(f"label image {path} must be one integer channel, got shape {img.shape} {img.dtype}")
    return img


def read_numbers(path: Path, columns=None) -> np.ndarray:
    """A text table of numbers (# comments and blank lines skipped, commas or spaces) as a 2D
    float64 array; columns, when given, is the set of accepted row lengths."""
    path = Path(path)
    if not path.is_file():
        raise DatasetNotFoundError(f"missing file {path}")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            row = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f"{path}:{n}: not a row of numbers: {line!r}") from None
        widths = (len(rows[0]),) if rows else columns  # all rows as long as the first
        if widths is not None and len(row) not in widths:
            raise DatasetError(f"{path}:{n}: expected {' or '.join(map(str, widths))} numbers, "
                               f"found {len(row)}: {line!r}")
        rows.append(row)
    if not rows:
        raise DatasetError(f"{path} holds no numbers")
    return np.array(rows)


def read_intrinsics(path: Path) -> tuple:
    """(K, depth_scale or None, (w, h) or None) from a camera file.

    Text: a 3x3 or 4x4 matrix (7-Scenes, ScanNet) or one line fx fy cx cy. JSON: keys
    fx fy cx cy, optionally w/h or width/height and scale/depth_scale, at the top level or under
    "camera" (NICE-SLAM's cam_params.json)."""
    path = Path(path)
    if path.suffix == ".json":
        try:
            d = json.loads(path.read_text())
            d = d.get("camera", d)
            K = as_K([d["fx"], d["fy"], d["cx"], d["cy"]])
        except (ValueError, KeyError, AttributeError, TypeError) as e:
            raise DatasetError(f"{path}: expected JSON with fx, fy, cx, cy ({type(e).__name__}: {e})") from None
        scale = d.get("depth_scale", d.get("scale"))
        w, h = d.get("width", d.get("w")), d.get("height", d.get("h"))
        return K, scale, (int(w), int(h)) if w and h else None
    a = read_numbers(path)
    if a.size not in (4, 9, 16):
        raise DatasetError(f"{path}: expected fx fy cx cy or a 3x3/4x4 matrix, found {a.size} numbers")
    return as_K(a.reshape(-1) if a.size == 4 else a.reshape(int(np.sqrt(a.size)), -1)), None, None


def quat_to_pose(t, q) -> np.ndarray:
    """4x4 from translation and a Hamilton quaternion (qx, qy, qz, qw), TUM's order."""
    x, y, z, w = np.asarray(q, dtype=np.float64)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not n > 1e-6:
        raise DatasetError(f"quaternion {list(q)} has zero length")
    x, y, z, w = x / n, y / n, z / n, w / n
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = t
    return T


def poses_from_rows(rows: np.ndarray, where) -> tuple:
    """(timestamps or None, list of 4x4) from pose rows of 7 (tx ty tz qx qy qz qw),
    8 (TUM: with a leading timestamp) or 16 (row-major 4x4) numbers."""
    if rows.shape[1] == 16:
        return None, [r.reshape(4, 4) for r in rows]
    stamps = rows[:, 0] if rows.shape[1] == 8 else None
    body = rows[:, 1:] if rows.shape[1] == 8 else rows
    if body.shape[1] != 7:
        raise DatasetError(f"{where}: pose rows must have 7, 8 or 16 numbers, not {rows.shape[1]}")
    return stamps, [quat_to_pose(r[:3], r[3:]) for r in body]


def read_pose_matrix(path: Path):
    """A 4x4 camera-to-world from a text file, None when the file is missing or the pose is
    marked invalid (non-finite)."""
    return check_pose(read_numbers(path, columns=(4,)), str(path)) if path.is_file() else None


def first_existing(candidates, what: str) -> Path:
    """The first existing file among candidates, else an error naming all of them."""
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetNotFoundError(f"no {what}: looked for " + ", ".join(str(c) for c in candidates))
