"""The built-in scene: a procedural living room, ray cast (analytically, with numpy) into an
RGB-D sequence with ground-truth poses and per-pixel class labels, so that legslam runs and is
tested with no download.

The room (walls, floor, ceiling, a rug) holds a table, two chairs, a sofa, a plant, a lamp, a
bookshelf and a picture. Surfaces carry solid (3D) procedural textures, band-limited so they do
not alias, and Lambertian shading under fixed lights: a point looks the same from every view,
as photometric tracking assumes. Depth is z-depth in metres. The camera moves like a hand-held
one around the table, ~2 cm and ~0.7 degrees per frame, looking at the furniture.

The sequence is written in the plain-folder format (see folder.py): color/, depth/ (16-bit PNG,
depth_scale 5000), labels/ (8-bit PNG class ids, names in classes.txt), camera.json and
groundtruth.txt (TUM, c2w), so `legslam.datasets.open(path)` reads it like any dataset. The
same seed gives the same bytes.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

VERSION = 1  # bump when the scene or its files change, so cached copies are regenerated
FPS = 30.0
DEPTH_SCALE = 5000.0
CLASS_NAMES = ["wall", "floor", "ceiling", "rug", "table", "chair", "sofa", "plant", "lamp",
               "bookshelf", "picture"]
ROOM_MIN, ROOM_MAX = np.array([-3.5, -3.0, 0.0]), np.array([3.5, 3.0, 2.7])  # world z is up
LIGHTS = [(np.array([0.35, -0.45, 0.82]), 0.55), (np.array([-0.6, 0.5, 0.62]), 0.25)]
AMBIENT = 0.3


@dataclass
class Part:
    """One primitive: kind "box" (centre, half sizes, yaw about z), "sphere" (centre, radius)
    or "cylinder" (vertical: centre of base, radius, height). Material: base colour (RGB in
    [0, 1]) and texture kind "noise", "tiles", "books" or "paint"."""

    kind: str
    centre: np.ndarray
    size: np.ndarray
    cls: int
    colour: np.ndarray
    texture: str = "noise"
    yaw: float = 0.0


def _box(c, half, cls, colour, texture="noise", yaw=0.0) -> Part:
    return Part("box", np.asarray(c, float), np.asarray(half, float), cls, np.asarray(colour, float), texture, yaw)


def build_scene(rng: np.random.Generator) -> list:
    """The furniture of the room (walls, floor and ceiling are the room box itself)."""
    C = {n: i for i, n in enumerate(CLASS_NAMES)}
    jit = lambda s=0.08: rng.uniform(-s, s)  # noqa: E731  small seeded placement changes
    tint = lambda c: np.clip(np.asarray(c) + rng.uniform(-0.06, 0.06, 3), 0, 1)  # noqa: E731
    parts = [_box((0, 0, 0.005), (1.6, 1.1, 0.005), C["rug"], tint((0.55, 0.2, 0.2)), "paint")]

    # Table: top and four legs, turned a little.
    tx, ty, yaw = jit(), jit(), rng.uniform(-0.15, 0.15)
    wood = tint((0.55, 0.36, 0.2))
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    parts.append(_box((tx, ty, 0.745), (0.7, 0.4, 0.025), C["table"], wood, yaw=yaw))
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        lx, ly = rot @ (sx * 0.62, sy * 0.32)
        parts.append(_box((tx + lx, ty + ly, 0.36), (0.03, 0.03, 0.36), C["table"], wood * 0.8, yaw=yaw))

    # Two chairs facing the table from its ends.
    for side in (1, -1):
        cx, cy = side * (1.05 + jit(0.05)), jit(0.1)
        col = tint((0.2, 0.35, 0.6))
        parts.append(_box((cx, cy, 0.46), (0.23, 0.23, 0.03), C["chair"], col))
        parts.append(_box((cx + side * 0.21, cy, 0.75), (0.025, 0.23, 0.27), C["chair"], col))
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            parts.append(_box((cx + sx * 0.19, cy + sy * 0.19, 0.215), (0.02, 0.02, 0.215), C["chair"], col * 0.7))

    # Sofa against the +y wall: seat, back, two arms.
    sx = jit(0.2)
    fabric = tint((0.3, 0.5, 0.3))
    parts += [_box((sx, 2.5, 0.22), (1.0, 0.45, 0.22), C["sofa"], fabric),
              _box((sx, 2.85, 0.55), (1.0, 0.12, 0.55), C["sofa"], fabric * 0.85),
              _box((sx - 1.05, 2.5, 0.35), (0.1, 0.45, 0.35), C["sofa"], fabric * 0.9),
              _box((sx + 1.05, 2.5, 0.35), (0.1, 0.45, 0.35), C["sofa"], fabric * 0.9)]

    # Plant in a corner: pot and foliage; lamp in another: base, pole, shade.
    px, py = 2.9 + jit(0.1), -2.4 + jit(0.1)
    parts += [Part("cylinder", np.array([px, py, 0.0]), np.array([0.2, 0.4]), C["plant"], tint((0.6, 0.3, 0.15))),
              Part("sphere", np.array([px, py, 0.8]), np.array([0.42]), C["plant"], tint((0.2, 0.55, 0.15)))]
    lx, ly = -2.9 + jit(0.1), 2.4 + jit(0.1)
    brass = tint((0.8, 0.7, 0.35))
    parts += [Part("cylinder", np.array([lx, ly, 0.0]), np.array([0.18, 0.04]), C["lamp"], brass),
              Part("cylinder", np.array([lx, ly, 0.04]), np.array([0.025, 1.4]), C["lamp"], brass),
              Part("cylinder", np.array([lx, ly, 1.35]), np.array([0.25, 0.3]), C["lamp"], tint((0.95, 0.9, 0.75)))]

    # Bookshelf against the -x wall; a picture on the -y wall.
    parts.append(_box((-3.3, -0.5 + jit(0.2), 0.95), (0.2, 0.6, 0.95), C["bookshelf"], tint((0.45, 0.3, 0.2)), "books"))
    parts.append(_box((jit(0.4), -2.985, 1.55), (0.6, 0.015, 0.4), C["picture"], tint((0.5, 0.5, 0.6)), "paint"))
    return parts


# --- camera path ------------------------------------------------------------------------

def camera_path(n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) c2w poses: a slow elliptic walk round the table with hand-held sway, looking
    at a target that drifts over the furniture. Speeds are per second, so longer sequences
    just continue the walk."""
    t = np.arange(n_frames) / FPS
    phase = rng.uniform(0, 2 * np.pi, 8)
    ang = phase[0] + 0.33 * t  # ~0.63 degrees of the ellipse per frame, ~2 cm at its radius
    pos = np.stack([2.1 * np.cos(ang), 1.55 * np.sin(ang), 1.4 + 0.06 * np.sin(0.9 * t + phase[1])], 1)
    pos += 0.012 * np.stack([np.sin(2.1 * t + phase[2]), np.sin(2.7 * t + phase[3]), np.sin(3.3 * t + phase[4])], 1)
    target = np.stack([0.6 * np.sin(0.25 * t + phase[5]), 0.5 * np.sin(0.35 * t + phase[6]),
                       0.7 + 0.2 * np.sin(0.5 * t + phase[7])], 1)
    roll = np.radians(2.0) * np.sin(1.1 * t + phase[1])
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        z = target[i] - pos[i]
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])  # OpenCV axes: x right, y down, z forward
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        c, s = np.cos(roll[i]), np.sin(roll[i])
        poses[i, :3, :3] = np.stack([c * x + s * y, -s * x + c * y, z], 1)
        poses[i, :3, 3] = pos[i]
    return poses


# --- ray casting ------------------------------------------------------------------------
# Rays are three HxW component arrays (dx, dy, dz): elementwise work on them is several times
# faster than on (..., 3) arrays. The casting loop finds only distances; normals are computed
# afterwards for the surface that won each pixel.

def _t_box(p: Part, o, dx, dy, dz):
    ox, oy, oz = (o - p.centre).tolist()  # Python floats keep the float32 rays float32
    if p.yaw:  # into the box's frame
        c, s = np.cos(p.yaw), np.sin(p.yaw)
        ox, oy, dx, dy = c * ox + s * oy, -s * ox + c * oy, c * dx + s * dy, -s * dx + c * dy
    tnear, tfar = -np.inf, np.inf
    with np.errstate(divide="ignore", invalid="ignore"):
        for oi, di, hi in zip((ox, oy, oz), (dx, dy, dz), p.size.tolist()):
            t1, t2 = (-hi - oi) / di, (hi - oi) / di
            tnear, tfar = np.maximum(tnear, np.minimum(t1, t2)), np.minimum(tfar, np.maximum(t1, t2))
    return np.where((tnear <= tfar) & (tnear > 0), tnear, np.inf)


def _t_sphere(p: Part, o, dx, dy, dz):
    ox, oy, oz = (o - p.centre).tolist()
    a, b = dx * dx + dy * dy + dz * dz, dx * ox + dy * oy + dz * oz
    disc = b * b - a * (ox * ox + oy * oy + oz * oz - float(p.size[0]) ** 2)
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _t_cylinder(p: Part, o, dx, dy, dz):
    r, h = p.size.tolist()
    ox, oy, oz = (o - p.centre).tolist()
    a, b = dx * dx + dy * dy, dx * ox + dy * oy
    disc = b * b - a * (ox * ox + oy * oy - r * r)
    with np.errstate(invalid="ignore", divide="ignore"):
        ts = (-b - np.sqrt(disc)) / a
        zs = oz + ts * dz
        ts = np.where((disc >= 0) & (ts > 0) & (zs >= 0) & (zs <= h), ts, np.inf)
        tc = np.where(dz < 0, (h - oz) / dz, -oz / dz)  # the top seen from above, the bottom from below
    cx, cy = ox + tc * dx, oy + tc * dy
    tc = np.where((tc > 0) & (cx * cx + cy * cy <= r * r), tc, np.inf)
    return np.minimum(ts, tc)


def _normals(kind: str, q, centre, size, yaw):
    """Outward unit normals at surface points q (N, 3) of parts of one kind, each point with
    its part's centre (N, 3), size (N, 3) and yaw (N,): all parts of a kind in one pass."""
    q = q - centre
    if kind == "sphere":
        return q / size[:, :1]
    if kind == "cylinder":
        r, h = size[:, 0], size[:, 1]
        rho = np.hypot(q[:, 0], q[:, 1])
        side = np.abs(rho - r) < np.minimum(np.abs(q[:, 2]), np.abs(q[:, 2] - h))
        zero = np.zeros_like(r)
        return np.where(side[:, None], np.stack([q[:, 0] / r, q[:, 1] / r, zero], 1),
                        np.stack([zero, zero, np.sign(q[:, 2] - h / 2)], 1))
    c, s = np.cos(yaw), np.sin(yaw)
    lx, ly, lz = c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]  # the box's frame
    rx, ry, rz = np.abs(lx) / size[:, 0], np.abs(ly) / size[:, 1], np.abs(lz) / size[:, 2]
    # The face is where |q| / half size is largest.
    fx, fy = (rx >= ry) & (rx >= rz), (ry > rx) & (ry >= rz)
    nx, ny = np.where(fx, np.sign(lx), 0.0), np.where(fy, np.sign(ly), 0.0)
    return np.stack([c * nx - s * ny, s * nx + c * ny, np.where(fx | fy, 0.0, np.sign(lz))], 1)


HIT = {"box": _t_box, "sphere": _t_sphere, "cylinder": _t_cylinder}


def _bounds(p: Part) -> np.ndarray:
    """(8, 3) corners of a world box that contains the part."""
    if p.kind == "box":
        r = np.hypot(p.size[0], p.size[1]) if p.yaw else None
        half = np.array([r, r, p.size[2]]) if r else p.size
        lo, hi = p.centre - half, p.centre + half
    elif p.kind == "sphere":
        lo, hi = p.centre - p.size[0], p.centre + p.size[0]
    else:
        r, h = p.size
        lo, hi = p.centre - [r, r, 0], p.centre + [r, r, h]
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _pixel_rect(p: Part, K, T, w, h):
    """Slices of the image rows and columns the part can cover (None when it is off screen)."""
    pc = (T[:3, :3].T @ (_bounds(p) - T[:3, 3]).T).T
    if (pc[:, 2] < 0.05).all():
        return None
    if (pc[:, 2] < 0.05).any():  # straddles the camera plane: the whole image, to be safe
        return slice(0, h), slice(0, w)
    u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
    v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    u0, u1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, w)
    v0, v1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, h)
    return (slice(v0, v1), slice(u0, u1)) if u0 < u1 and v0 < v1 else None


def _room(o, dx, dy, dz):
    """Exit distance from inside the room box, the surface hit (0 wall, 1 floor, 2 ceiling:
    the class ids of CLASS_NAMES) and its inward normal."""
    with np.errstate(divide="ignore"):
        # A ray parallel to a pair of walls (d = 0) never reaches them: inf, not -inf.
        tx, ty, tz = [np.where(d > 0, float(ROOM_MAX[i] - o[i]) / d,
                               np.where(d < 0, float(ROOM_MIN[i] - o[i]) / d, np.inf))
                      for i, d in enumerate((dx, dy, dz))]
    t = np.minimum(np.minimum(tx, ty), tz)
    on_z, on_y = tz <= t, (ty <= t) & (tz > t)
    surface = np.where(on_z, np.where(dz < 0, 1, 2), 0)
    n = np.stack([np.where(on_z | on_y, 0.0, -np.sign(dx)), np.where(on_y, -np.sign(dy), 0.0),
                  np.where(on_z, -np.sign(dz), 0.0)], -1)
    return t, surface, n


# --- materials --------------------------------------------------------------------------

KINDS = ("noise", "tiles", "books", "paint")


class Textures:
    """Seeded solid textures. Each is a sum of a few sinusoids with random directions and
    frequencies (1.5-7 cycles per metre, far below the pixel rate at these distances), which
    looks like smooth coloured noise and gives photometric tracking gradients everywhere."""

    def __init__(self, rng: np.random.Generator, n_waves: int = 6):
        dirs = rng.normal(size=(n_waves, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        self.k = (dirs * rng.uniform(1.5, 7.0, (n_waves, 1)) * 2 * np.pi).astype(np.float32)
        self.phase = rng.uniform(0, 2 * np.pi, n_waves).astype(np.float32)
        self.tint = (0.12 / np.sqrt(n_waves) * rng.uniform(-1, 1, (n_waves, 3))).astype(np.float32)
        self.books = rng.uniform(0.15, 0.9, (16, 3)).astype(np.float32)

    def albedo(self, kinds: np.ndarray, base: np.ndarray, p: np.ndarray) -> np.ndarray:
        """RGB albedo in [0, 1] at points p (N, 3) of surfaces with base colours (N, 3) and
        texture kinds (N,), indices into KINDS."""
        # einsum, not BLAS, whose threads only contend on such thin products.
        w = np.sin(np.einsum("nj,kj->nk", p, self.k) + self.phase)  # (N, n_waves) in [-1, 1]
        noise = np.einsum("nk,kc->nc", w, self.tint)
        shade = 1.0 + (0.25 / 3) * (w[:, 0:1] + w[:, 1:2] + w[:, 2:3])
        m = kinds == KINDS.index("tiles")  # 0.5 m floor tiles with soft grout lines
        tile = np.tanh(12 * np.sin(np.pi * p[m, 0] / 0.5) * np.sin(np.pi * p[m, 1] / 0.5))
        shade[m] *= 1.0 + 0.15 * tile[:, None]
        m = kinds == KINDS.index("books")  # shelves of coloured book spines along the wall
        idx = (np.floor(p[m, 1] / 0.06) + 7 * np.floor(p[m, 2] / 0.38)).astype(np.int64) % len(self.books)
        board = np.abs(np.sin(np.pi * p[m, 2] / 0.38)) < 0.15
        base[m] = np.where(board[:, None], base[m] * 0.5, self.books[idx])
        m = kinds == KINDS.index("paint")  # bold colour fields
        base[m] += 0.3 * np.sin(3.0 * (w[m, :3] + w[m, 3:6]))
        return np.clip(base * shade + noise, 0.0, 1.0)


ROOM_MATERIALS = [((0.78, 0.74, 0.66), "noise"), ((0.6, 0.45, 0.3), "tiles"), ((0.9, 0.9, 0.88), "noise")]


def render(parts: list, textures: Textures, K: np.ndarray, pose: np.ndarray, width: int, height: int):
    """(rgb uint8 HxWx3, z-depth float64 HxW metres, labels uint8 HxW) seen from pose (c2w)."""
    # float32 rays: half the memory traffic of float64, and errors far below the 0.2 mm step
    # of the 16-bit depth files.
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    # Rays with unit z in the camera: the hit distance t along them is the z-depth.
    xc, yc = (u - float(K[0, 2])) / float(K[0, 0]), (v - float(K[1, 2])) / float(K[1, 1])
    R, o = pose[:3, :3].tolist(), pose[:3, 3]
    dx, dy, dz = (R[i][0] * xc + R[i][1] * yc + R[i][2] for i in range(3))
    t, surface, normals = _room(o, dx, dy, dz)
    for k, p in enumerate(parts):
        rect = _pixel_rect(p, K, pose, width, height)
        if rect is None:
            continue
        tp = HIT[p.kind](p, o, dx[rect], dy[rect], dz[rect])
        closer = tp < t[rect]
        t[rect][closer] = tp[closer]
        surface[rect][closer] = 3 + k  # materials: the room's three, then the parts
    q = o.astype(np.float32) + t.reshape(-1, 1) * np.stack([dx.ravel(), dy.ravel(), dz.ravel()], 1)
    surface = surface.ravel()
    materials = ROOM_MATERIALS + [(p.colour, p.texture) for p in parts]
    base = np.array([m[0] for m in materials], dtype=np.float32)[surface]
    normals = normals.reshape(-1, 3)
    centre = np.array([np.zeros(3)] * 3 + [p.centre for p in parts], dtype=np.float32)
    size = np.array([np.ones(3)] * 3 + [np.resize(p.size, 3) for p in parts], dtype=np.float32)
    yaw = np.array([0.0] * 3 + [p.yaw for p in parts], dtype=np.float32)
    shapes = list(HIT)
    shape_of = np.array([-1] * 3 + [shapes.index(p.kind) for p in parts])[surface]
    for code, kind in enumerate(shapes):
        m = shape_of == code
        if m.any():
            s = surface[m]
            normals[m] = _normals(kind, q[m], centre[s], size[s], yaw[s])
    kinds = np.array([KINDS.index(m[1]) for m in materials])[surface]
    albedo = textures.albedo(kinds, base, q)
    light = np.full(len(q), AMBIENT, dtype=np.float32)
    for direction, strength in LIGHTS:
        lx, ly, lz = (direction / np.linalg.norm(direction)).tolist()
        light += strength * np.clip(normals[:, 0] * lx + normals[:, 1] * ly + normals[:, 2] * lz, 0, None)
    rgb = np.clip(albedo * light[:, None], 0, 1).reshape(height, width, 3)
    labels = np.array([0, 1, 2] + [p.cls for p in parts], dtype=np.uint8)[surface].reshape(height, width)
    return (rgb * 255 + 0.5).astype(np.uint8), t, labels


# --- writing ----------------------------------------------------------------------------

def intrinsics(width: int, height: int) -> np.ndarray:
    """A 64-degree horizontal field of view with the principal point at the image centre."""
    f = 0.8 * width
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"cannot encode {path}")
    path.write_bytes(buf.tobytes())


def generate(out_dir, n_frames: int = 100, width: int = 320, height: int = 240, seed: int = 0) -> Path:
    """Render the scene into out_dir and return its path, ready for legslam.datasets.open.
    out_dir must be empty, new, or an earlier generated scene (which is replaced)."""
    from ..eval.trajectory import write_tum

    if n_frames < 1 or width < 16 or height < 16:
        raise ValueError(f"need n_frames >= 1 and images of at least 16x16, got {n_frames}, {width}x{height}")
    out = Path(out_dir)
    if out.is_dir() and any(out.iterdir()):
        if not (out / "scene.json").is_file():
            raise FileExistsError(f"{out} is not empty and holds no generated scene; not writing into it")
        (out / "scene.json").unlink()  # first, so an interrupted rewrite is not taken as complete
        for sub in ("color", "depth", "labels"):
            shutil.rmtree(out / sub, ignore_errors=True)
    for sub in ("color", "depth", "labels"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    parts, textures, poses = build_scene(rng), Textures(rng), camera_path(n_frames, rng)
    K = intrinsics(width, height)
    for i, pose in enumerate(poses):
        rgb, depth, labels = render(parts, textures, K, pose, width, height)
        raw = np.round(depth * DEPTH_SCALE)
        if not (np.isfinite(raw).all() and 0 < raw.min() and raw.max() <= 65535):
            raise RuntimeError(f"frame {i}: depth outside (0, {65535 / DEPTH_SCALE}] m; a bug in the ray caster")
        name = f"{i:06d}.png"
        _write_png(out / "color" / name, rgb[..., ::-1])  # cv2 writes BGR
        _write_png(out / "depth" / name, raw.astype(np.uint16))
        _write_png(out / "labels" / name, labels)
    camera = {"width": width, "height": height, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
              "depth_scale": DEPTH_SCALE}
    (out / "camera.json").write_text(json.dumps(camera, indent=1) + "\n")
    (out / "classes.txt").write_text("\n".join(CLASS_NAMES) + "\n")
    write_tum(out / "groundtruth.txt", np.arange(n_frames) / FPS, poses)
    params = {"version": VERSION, "n_frames": n_frames, "width": width, "height": height, "seed": seed}
    (out / "scene.json").write_text(json.dumps(params, indent=1) + "\n")
    return out


def cache_dir() -> Path:
    """Where default_scene keeps its copies: $LEGSLAM_CACHE, else $XDG_CACHE_HOME/legslam,
    else ~/.cache/legslam."""
    if os.environ.get("LEGSLAM_CACHE"):
        return Path(os.environ["LEGSLAM_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "legslam"


def default_scene(n_frames: int = 100, width: int = 320, height: int = 240, seed: int = 0) -> Path:
    """The scene with these parameters, generated into the cache on first use and reused after."""
    out = cache_dir() / f"synthetic-v{VERSION}" / f"{width}x{height}-{n_frames}f-seed{seed}"
    if (out / "scene.json").is_file():  # written last, so its presence means complete
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    # Render beside the target and rename: an interrupted run never leaves a partial scene.
    tmp = Path(tempfile.mkdtemp(prefix=out.name + ".", dir=out.parent))
    try:
        generate(tmp, n_frames, width, height, seed)
        try:
            tmp.rename(out)
        except OSError:  # another process finished first
            if not (out / "scene.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
