"""File reading shared by the loaders. cv2 returns None instead of raising on a missing or
corrupt file; every reader here turns that into a DatasetError that names the file."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from .base import DatasetError, DatasetNotFoundError, as_K, check_pose


def read_bytes(path: Path, what: str = "file") -> bytes:
    """A file's bytes; missing, unreadable (permissions, a folder) or empty is a DatasetError
    naming it."""
    path = Path(path)
    if not path.exists():
        raise DatasetNotFoundError(f"missing {what} {path}")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DatasetError(f"cannot read {what} {path}: {e.strerror or e}") from None
    if not data:
        raise DatasetError(f"{what} {path} is empty (0 bytes)")
    return data


def read_text(path: Path, what: str = "file") -> str:
    """A text file's contents, with read_bytes' errors, and one that is not text named."""
    try:
        return read_bytes(path, what).decode("utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{what} {path} is not a text file") from None


def decode_image(data, flags: int, where) -> np.ndarray:
    """An encoded image (PNG, JPEG, ...: bytes or a uint8 array) decoded by cv2 with `flags`;
    what cannot be decoded is a DatasetError naming `where` (a file, a bag message)."""
    import cv2

    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error:
        img = None
    if img is None:
        raise DatasetError(f"cannot decode image {where} (corrupt or not an image)")
    return img


def _imread(path: Path, flags: int) -> np.ndarray:
    # imdecode (not imread) so that non-ASCII paths work on every platform.
    return decode_image(read_bytes(path, "image"), flags, path)


def decode_rgb(data, where) -> np.ndarray:
    """HxWx3 uint8 RGB from any encoded 8-bit colour (or grey) image."""
    import cv2

    return cv2.cvtColor(decode_image(data, cv2.IMREAD_COLOR, where), cv2.COLOR_BGR2RGB)


def read_rgb(path: Path) -> np.ndarray:
    """HxWx3 uint8 RGB from any 8-bit colour (or grey) image."""
    return decode_rgb(read_bytes(path, "image"), path)


def read_depth(path: Path) -> np.ndarray:
    """Raw single-channel depth: uint16 from PNG, float from TIFF/EXR/.npy (metres)."""
    import cv2

    path = Path(path)
    if path.suffix == ".npy":
        try:
            img = np.load(io.BytesIO(read_bytes(path, "depth")), allow_pickle=False)
        except (ValueError, EOFError) as e:
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


def read_numbers(path: Path, columns=None, line_numbers: bool = False, header: bool = False):
    """A text table of numbers (# comments and blank lines skipped, commas or spaces) as a 2D
    float64 array; columns, when given, is the set of accepted row lengths. With
    `line_numbers`, also each row's line number in the file; with `header`, a first line of
    column names is skipped."""
    path = Path(path)
    rows, lines = [], []
    for n, line in enumerate(read_text(path).splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            row = [float(v) for v in line.split()]
        except ValueError:
            if header and not rows:  # the column names
                header = False
                continue
            raise DatasetError(f"{path}:{n}: not a row of numbers: {line!r}") from None
        widths = (len(rows[0]),) if rows else columns  # all rows as long as the first
        if widths is not None and len(row) not in widths:
            raise DatasetError(f"{path}:{n}: expected {' or '.join(map(str, widths))} numbers, "
                               f"found {len(row)}: {line!r}")
        rows.append(row)
        lines.append(n)
    if not rows:
        raise DatasetError(f"{path} holds no numbers")
    return (np.array(rows), lines) if line_numbers else np.array(rows)


def read_intrinsics(path: Path) -> tuple:
    """(K, depth_scale or None, (w, h) or None) from a camera file.

    Text: a 3x3 or 4x4 matrix (7-Scenes, ScanNet) or one line fx fy cx cy. JSON: keys
    fx fy cx cy, optionally w/h or width/height and scale/depth_scale, at the top level or under
    "camera" (NICE-SLAM's cam_params.json)."""
    path = Path(path)
    if path.suffix == ".json":
        try:
            d = json.loads(read_text(path, "camera file"))
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
    if not np.all(np.isfinite([*t, x, y, z, w])):
        raise DatasetError(f"pose {[*t, *q]} has a non-finite value (NaN or inf)")
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


def poses_from_rows(rows: np.ndarray, where, lines=None) -> tuple:
    """(timestamps or None, list of 4x4) from pose rows of 7 (tx ty tz qx qy qz qw),
    8 (TUM: with a leading timestamp) or 16 (row-major 4x4) numbers; `lines`: each row's line
    in the file `where`, for errors."""
    if rows.shape[1] == 16:
        return None, [r.reshape(4, 4) for r in rows]
    stamps = rows[:, 0] if rows.shape[1] == 8 else None
    body = rows[:, 1:] if rows.shape[1] == 8 else rows
    if body.shape[1] != 7:
        raise DatasetError(f"{where}: pose rows must have 7, 8 or 16 numbers, not {rows.shape[1]}")
    poses = []
    for k, r in enumerate(body):
        try:
            poses.append(quat_to_pose(r[:3], r[3:]))
        except DatasetError as e:
            raise DatasetError(f"{where}:{lines[k] if lines else k + 1}: {e}") from None
    return stamps, poses


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
