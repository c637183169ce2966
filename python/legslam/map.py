"""A Gaussian map as numpy arrays: saved and loaded as a PLY that standard 3DGS viewers open
(language features as extra `f_lang_*` properties), and rendered from any pose.

    m = GaussianMap.load("run/map.ply")
    out = m.render(pose, K, 640, 480, features=True)   # a legslam.Render
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .render import Render, render

__all__ = ["GaussianMap"]


@dataclass
class GaussianMap:
    means: np.ndarray           # N x 3
    log_scales: np.ndarray      # N x 3
    quats: np.ndarray           # N x 4 (w, x, y, z)
    opacity_logits: np.ndarray  # N
    sh: np.ndarray              # N x C x 3
    features: np.ndarray        # N x K (K may be 0)

    def __post_init__(self):
        for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "features"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))

    def __len__(self) -> int:
        return len(self.opacity_logits)

    @property
    def num_features(self) -> int:
        return self.features.shape[1]

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def render(self, pose, K, width: int, height: int, features: bool = True) -> Render:
        """Renders colour, depth, alpha (and features) from a camera-to-world pose."""
        return render(self.means, self.log_scales, self.quats, self.opacity_logits, self.sh, K,
                      pose, width, height, features=self.features if features else None)

    # --- PLY -------------------------------------------------------------------------------

    def _columns(self) -> list[tuple[str, np.ndarray]]:
        n, c = len(self), self.sh.shape[1]
        rest = self.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (c - 1))  # 3DGS: per channel
        cols = [("x", self.means[:, 0]), ("y", self.means[:, 1]), ("z", self.means[:, 2])]
        cols += [(a, np.zeros(n, np.float32)) for a in ("nx", "ny", "nz")]
        cols += [(f"f_dc_{i}", self.sh[:, 0, i]) for i in range(3)]
        cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
        cols += [("opacity", self.opacity_logits)]
        cols += [(f"scale_{i}", self.log_scales[:, i]) for i in range(3)]
        cols += [(f"rot_{i}", self.quats[:, i]) for i in range(4)]
        cols += [(f"f_lang_{i}", self.features[:, i]) for i in range(self.num_features)]
        return cols

    def save(self, path) -> Path:
        """Writes a binary little-endian PLY in the 3DGS layout (+ f_lang_* features)."""
        path = Path(path)
        cols = self._columns()
        data = np.empty(len(self), dtype=[(name, "<f4") for name, _ in cols])
        for name, col in cols:
            data[name] = col
        header = ["ply", "format binary_little_endian 1.0",
                  "comment legslam Gaussian map (3DGS layout; f_lang_* = language features)",
                  f"element vertex {len(self)}"]
        header += [f"property float {name}" for name, _ in cols] + ["end_header"]
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(data.tobytes())
        tmp.replace(path)  # never leave a half-written map under the real name
        return path

    @classmethod
    def load(cls, path) -> "GaussianMap":
        """Reads a PLY in the 3DGS layout (ours or another 3DGS tool's)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no map file at {path}")
        with open(path, "rb") as f:
            if f.readline().strip() != b"ply":
                raise ValueError(f"{path} is not a PLY file")
            names, n, fmt = [], None, None
            while True:
                line = f.readline()
                if not line:
                    raise ValueError(f"{path}: PLY header has no end_header")
                words = line.decode("ascii", "replace").split()
                if not words:
                    continue
                short = words[0] in ("format", "element", "property") and len(words) < 3
                if short or (words[0] == "element" and not words[2].isdigit()):
                    raise ValueError(f"{path}: bad PLY header line {' '.join(words)!r}")
                if words[0] == "format":
                    fmt = words[1]
                elif words[0] == "element":
                    if words[1] != "vertex":
                        raise ValueError(f"{path}: unexpected PLY element {words[1]!r}")
                    n = int(words[2])
                elif words[0] == "property":
                    if words[1] != "float":
                        raise ValueError(f"{path}: property {words[-1]} is {words[1]}, expected float")
                    names.append(words[2])
                elif words[0] == "end_header":
                    break
            if fmt != "binary_little_endian" or n is None:
                raise ValueError(f"{path}: expected a binary little-endian vertex PLY")
            body, need = f.read(), n * 4 * len(names)
            if len(body) < need:
                raise ValueError(f"{path} is cut short: its {n} Gaussians need {need} bytes after "
                                 f"the header, it has {len(body)}")
            data = np.frombuffer(body, dtype=[(name, "<f4") for name in names], count=n)
        missing = [k for k in ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0") if k not in names]
        if missing:
            raise ValueError(f"{path}: not a Gaussian-splat PLY (missing {', '.join(missing)})")
        for name in names:
            bad = ~np.isfinite(data[name])
            if bad.any():
                raise ValueError(f"{path}: property {name} of Gaussian {int(np.argmax(bad))} is "
                                 f"{data[name][bad][0]} ({int(bad.sum())} non-finite values in all)")

        def stack(prefix):
            cols = sorted((c for c in names if c.startswith(prefix)), key=lambda c: int(c[len(prefix):]))
            return np.stack([data[c] for c in cols], axis=1) if cols else np.zeros((n, 0), np.float32)

        rest = stack("f_rest_")
        c = 1 + rest.shape[1] // 3
        sh = np.concatenate([stack("f_dc_")[:, None, :], rest.reshape(n, 3, c - 1).transpose(0, 2, 1)], axis=1)
        # 3DGS tools store rotations unnormalised; the rotation is the normalised quaternion.
        # Unit ones (legslam's own) are kept to the bit, so that a map reads back as it was.
        quats = stack("rot_")
        norm = np.linalg.norm(quats, axis=1, keepdims=True)
        if quats.shape[1] != 4 or not np.all(norm > 0):
            raise ValueError(f"{path}: rot_0..rot_3 must be a quaternion of non-zero length per Gaussian")
        norm[np.abs(norm - 1) < 1e-5] = 1
        return cls(
            means=np.stack([data["x"], data["y"], data["z"]], axis=1),
            log_scales=stack("scale_"),
            quats=quats / norm,
            opacity_logits=np.array(data["opacity"]),
            sh=np.ascontiguousarray(sh),
            features=stack("f_lang_"),
        )
