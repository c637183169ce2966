"""The SLAM loop: per frame, track against the map rendered at the predicted pose, decide
keyframes, grow and train the map; language features of keyframes arrive asynchronously and
become feature targets of the map.

    slam = SLAM(SLAMConfig(), K, width, height)
    for frame in legslam.datasets.open(path):
        step = slam.step(frame.rgb, frame.depth)
    slam.finish()
    slam.gaussian_map().save("map.ply")

The Python side decides what to do; the engine (legslam._core) does the arithmetic.
"""

from __future__ import annotations

import json
import numbers
import os
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from . import _core
from .map import GaussianMap
from .mapping_thread import MappingThread
from .tracking import Tracker

__all__ = ["SLAMConfig", "SLAM", "StepResult"]


@dataclass
class SLAMConfig:
    """Every knob of a run, with defaults for a 2-core CPU. `mapper` and `tracker` override
    the engine's own options (`_core.mapper_default_config()`, `tracking.DEFAULT_CONFIG`)."""

    #: Tracking runs at about this width (frame and map render alike; full resolution for
    #: narrower input).
    track_width: int = 320
    #: New keyframe when the camera moved this far (m) or turned this much (degrees) since the
    #: last one, or the map covers less than `keyframe_overlap` of the pixels where the frame
    #: measured depth, or `keyframe_max_gap` frames passed.
    keyframe_translation: float = 0.1
    keyframe_rotation: float = 10.0
    keyframe_overlap: float = 0.9
    keyframe_max_gap: int = 15
    #: Mapping iterations after a new keyframe, and after every other tracked frame.
    map_iters_keyframe: int = 15
    map_iters_frame: int = 2
    #: The map trains at the coarsest pyramid level at least this wide (or full resolution).
    map_width: int = 320
    #: New Gaussians are seeded on a grid about this many columns wide (every pixel of a
    #: narrower training level). On 7-Scenes, 150 frames at 320x240, seeding every other pixel
    #: gave a better map (22.9 against 22.6 dB) from a quarter of the Gaussians, 2.3x faster.
    grow_width: int = 160
    #: Degree of the spherical harmonics of each Gaussian's colour (0: one colour seen alike
    #: from everywhere; 3, as LEG-SLAM and 3DGS, 16 coefficients a channel). On 7-Scenes, 200
    #: frames: 23.3 / 24.1 / 25.0 / 25.8 dB with degree 0 / 1 / 2 / 3, at the same speed
    #: (view-dependent colour can follow gloss, and an exposure that changes with the view).
    sh_degree: int = 3
    #: Mapping iterations once the sequence has ended, on keyframes drawn from all of them.
    final_iters: int = 100
    #: Map in a worker thread while this one tracks (real time: the frame rate is the
    #: tracker's, and the map gets the iterations the spare CPU allows, `mapping_batch` at a
    #: time, on a thread pool of its own). Low overlap then makes a keyframe only once the
    #: previous one has had `map_iters_keyframe` iterations; `map_iters_frame` is unused.
    #: The tracker's reference is the map rendered after each batch at the latest tracked
    #: pose.
    mapping_thread: bool = False
    mapping_batch: int = 2
    #: With a mapping thread: the mapper's threads (0: one per core); the tracker then runs
    #: on one thread of its own.
    mapping_threads: int = 0
    #: A rendered pixel is trusted as a tracking reference where its alpha exceeds this; below
    #: `min_reference_coverage` of trusted pixels, the last keyframe is the reference instead.
    reference_alpha: float = 0.8
    min_reference_coverage: float = 0.5
    #: Language features: encoder ("default", a model name or an ONNX path), its input size,
    #: the compressed dimension K, and how many keyframes' patches fit the PCA.
    features: bool = True
    encoder: str = "default"
    encoder_size: int = 224
    encoder_threads: int = 1
    feature_dim: int = 64
    pca_keyframes: int = 3
    #: A PCA fitted beforehand (.npz from legslam.features.PCA.save) instead of fitting one.
    pca_path: Optional[str] = None
    mapper: dict = field(default_factory=dict)
    tracker: dict = field(default_factory=dict)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Raises ValueError naming the first option of the wrong type or out of its range
        (`mapper` and `tracker` options are checked by the engine and the tracker)."""
        for f in fields(self):
            v = getattr(self, f.name)
            kind = dict if f.name in ("mapper", "tracker") else type(f.default)
            if f.name == "pca_path":
                ok = v is None or isinstance(v, (str, os.PathLike))
            elif kind in (int, float):  # numpy scalars too, but not True/False
                ok = isinstance(v, _NUMBER[kind]) and not isinstance(v, bool)
            else:
                ok = isinstance(v, kind)
            if not ok:
                raise ValueError(f"{f.name} must be {_KIND_NAMES.get(kind, 'a path')}, "
                                 f"got {v!r}")
            low, high = _RANGES.get(f.name, (None, None))
            if low is not None and not low <= v <= high:  # also false for NaN
                bound = f"at least {low}" if high == _INF else f"in [{low}, {high}]"
                raise ValueError(f"{f.name} must be {bound}, got {v}")

    @classmethod
    def from_file(cls, path, **overrides) -> "SLAMConfig":
        """Reads a .toml, .json or .yaml file (only the keys given change a default)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no config file at {path}")
        text = path.read_text()
        if path.suffix == ".toml":
            import tomllib
            data = tomllib.loads(text)
        elif path.suffix == ".json":
            data = json.loads(text)
        elif path.suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError:
                raise ValueError(f"{path}: reading YAML needs PyYAML (pip install pyyaml); "
                                 "TOML and JSON need nothing") from None
            data = yaml.safe_load(text) or {}
        else:
            raise ValueError(f"{path}: config files are .toml, .json or .yaml")
        return cls.from_dict({**data, **overrides}, source=str(path))

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> "SLAMConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{source}: unknown option(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(known))}")
        return cls(**data)

    def to_dict(self) -> dict:
        return asdict(self)


_KIND_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
               dict: "a table of options"}
_NUMBER = {int: numbers.Integral, float: numbers.Real}
_INF = float("inf")
# The final mapping iterations run in batches of this many: progress, and Ctrl-C, in between.
FINAL_BATCH = 25
#: Each numeric option's range (inclusive).
_RANGES = {
    "track_width": (16, _INF), "map_width": (16, _INF), "grow_width": (16, _INF),
    "sh_degree": (0, 3),
    "keyframe_translation": (0.0, _INF), "keyframe_rotation": (0.0, _INF),
    "keyframe_overlap": (0.0, 1.0), "keyframe_max_gap": (1, _INF),
    "map_iters_keyframe": (0, _INF), "map_iters_frame": (0, _INF), "final_iters": (0, _INF),
    "mapping_batch": (1, _INF), "mapping_threads": (0, _INF),
    "reference_alpha": (0.0, 1.0), "min_reference_coverage": (0.0, 1.0),
    "encoder_size": (28, _INF), "encoder_threads": (0, _INF), "feature_dim": (1, _INF),
    "pca_keyframes": (1, _INF),
}


@dataclass
class StepResult:
    index: int
    pose: np.ndarray
    #: "init" (first frame), "ok", or "lost" (pose is the motion-model prediction).
    state: str
    keyframe: bool
    reason: Optional[str] = None


def _scaled_K(K: np.ndarray, s: float) -> np.ndarray:
    """Intrinsics of the image resized by `s`, pixel centres aligned."""
    out = K.astype(np.float64).copy()
    out[0, 0] *= s
    out[1, 1] *= s
    out[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return out


def _k4(K: np.ndarray) -> list:
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


class SLAM:
    """Online SLAM over frames of one camera (K for a width x height image)."""

    def __init__(self, config: SLAMConfig, K, width: int, height: int, encoder=None):
        self.config = config
        self.K = np.asarray(K, dtype=np.float64)
        if self.K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {self.K.shape}")
        self.width, self.height = int(width), int(height)
        config.check()  # again: a config's fields may have been set after it was made
        s = min(1.0, config.track_width / self.width)
        self.track_size = (max(1, round(self.width * s)), max(1, round(self.height * s)))
        self.K_track = _scaled_K(self.K, self.track_size[0] / self.width)
        mapper_opts = dict(config.mapper)
        mapper_opts.setdefault("num_features", config.feature_dim if config.features else 0)
        mapper_opts.setdefault("sh_degree", config.sh_degree)
        # Train and grow at about 320 pixels wide (full resolution for smaller inputs): what
        # two cores afford per iteration.
        level = 0
        while self.width >> (level + 1) >= config.map_width:
            level += 1
        mapper_opts.setdefault("finest_level", level)
        mapper_opts.setdefault("grow_level", level)
        mapper_opts.setdefault("levels", level + 3)
        mapper_opts.setdefault("grow_stride", max(1, round((self.width >> level) / config.grow_width)))
        threads = (config.mapping_threads or os.cpu_count() or 2) if config.mapping_thread else None
        self.mapper = _core.MapperCore(mapper_opts, threads=threads)
        self.tracker = Tracker(threads=1 if config.mapping_thread else None, **self._tracker_options())
        self.poses: list[np.ndarray] = []
        self.states: list[str] = []
        self.keyframe_frames: list[int] = []
        #: Per frame: the keyframe it was placed after (its id) and its pose relative to that
        #: keyframe's, so that refined keyframe poses carry their frames along (`finish`).
        self._anchors: list[tuple[int, np.ndarray]] = []
        self._last_kf: Optional[tuple] = None  # (pose, rgb_t, depth_t, frame index)
        self._last_tracked: Optional[tuple] = None  # (pose, rgb_t, depth_t)
        self._prepared: Optional[tuple] = None  # (render, trusted pixels, prepared reference or None)
        self.timings: dict[str, list[float]] = {
            "preprocessing": [], "tracking": [], "mapping": [], "frame": []}
        self.feature_timings: dict[str, list[float]] = {"extraction": [], "compression": []}
        self.mapping_stats: list[dict] = []
        #: With a mapping thread: seconds it spent rendering tracking references.
        self.reference_render_s = 0.0
        self._features = _FeatureFeed(self, encoder) if config.features else None
        self._thread: Optional[MappingThread] = None
        if config.mapping_thread:
            self._thread = MappingThread(self.mapper, _k4(self.K_track), self.track_size,
                                         config.mapping_batch)

    def _tracker_options(self) -> dict:
        """The tracker sees images already at `track_width`: its finest level is theirs, and
        it uses only as many pyramid levels as keep the coarsest at least 8 pixels."""
        from .tracking import fitting_levels

        opts = {"finest_level": 0, **self.config.tracker}
        if "levels" not in self.config.tracker:
            opts["levels"] = fitting_levels(*self.track_size, opts["finest_level"])
        return opts

    # --- per frame ---------------------------------------------------------------------------

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> StepResult:
        t_frame = time.perf_counter()
        t0 = time.perf_counter()
        rgb = np.asarray(rgb)
        depth = np.asarray(depth, dtype=np.float32)
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"frame {len(self.poses)}: rgb must be {self.height}x{self.width}x3 "
                             f"uint8, got {rgb.dtype} {rgb.shape}")
        if depth.shape != (self.height, self.width):
            raise ValueError(f"frame {len(self.poses)}: depth must be {self.height}x{self.width}, "
                             f"got {depth.shape}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        rgb_t = cv2.resize(rgb, self.track_size, interpolation=cv2.INTER_AREA)
        depth_t = cv2.resize(depth, self.track_size, interpolation=cv2.INTER_NEAREST)
        self.timings["preprocessing"].append(1e3 * (time.perf_counter() - t0))

        i = len(self.poses)
        t0 = time.perf_counter()
        reason = None
        if self._map_empty():
            # Nothing to track against yet (first frame, or no valid depth so far): this frame
            # starts the map where the camera last was.
            pose, state, coverage = (self.poses[-1] if self.poses else np.eye(4)), "init", 0.0
        else:
            pose, state, coverage, reason = self._track(rgb_t, depth_t)
        self.timings["tracking"].append(1e3 * (time.perf_counter() - t0))

        t0 = time.perf_counter()
        keyframe = state != "lost" and self._is_keyframe(i, pose, coverage)
        if keyframe:
            rgb_f = rgb.astype(np.float32) / 255.0
            kf_id, _ = self._mapping.add_keyframe(rgb_f, depth, _k4(self.K), pose)
            self._last_kf = (pose, rgb_t, depth_t, i)
            self.keyframe_frames.append(i)
            if self._features is not None:
                self._features.submit(kf_id, rgb)
        if self._features is not None:
            self._features.collect()
        if state != "lost" and self._thread is None:
            iters = self.config.map_iters_keyframe if keyframe else self.config.map_iters_frame
            self.mapping_stats.append(self.mapper.train(iters))
        elif state != "lost":
            self._thread.track_at(pose)
        self.timings["mapping"].append(1e3 * (time.perf_counter() - t0))

        if state != "lost":
            self._last_tracked = (pose, rgb_t, depth_t)
        self._record(pose, state)
        self.timings["frame"].append(1e3 * (time.perf_counter() - t_frame))
        return StepResult(i, pose, state, keyframe, reason)

    def skip(self) -> StepResult:
        """Records a frame that could not be read as lost: the motion model's pose, no mapping."""
        if not self.poses:
            raise ValueError("the first frame cannot be skipped: it places the map")
        pose = self._predict()
        self._record(pose, "lost")
        return StepResult(len(self.poses) - 1, pose, "lost", False, "unreadable")

    def _record(self, pose: np.ndarray, state: str) -> None:
        """A frame's pose and state, anchored to the last keyframe (see `_follow_keyframes`)."""
        self._anchors.append((len(self.keyframe_frames) - 1, np.linalg.inv(self._last_kf[0]) @ pose))
        self.poses.append(pose)
        self.states.append(state)

    @property
    def _mapping(self):
        """Where keyframes and features go: the mapping thread while it runs, else the mapper."""
        return self._thread or self.mapper

    @property
    def mapping_in_thread(self) -> bool:
        """Whether a mapping thread owns the map now (until `finish`)."""
        return self._thread is not None

    @property
    def num_gaussians(self) -> int:
        return self._mapping.num_gaussians

    def _map_empty(self) -> bool:
        if self._thread is not None:
            return not self._thread.pending and self._thread.num_gaussians == 0
        return self.mapper.num_gaussians == 0

    def _reference_render(self, predicted: np.ndarray):
        """(pose, render at the tracking size) to track against: the map at the predicted pose,
        or with a mapping thread its latest render (None before the first)."""
        if self._thread is not None:
            return self._thread.reference() or (None, None)
        w, h = self.track_size
        return predicted, self.mapper.render(predicted, _k4(self.K_track), w, h)

    def _predict(self) -> np.ndarray:
        """Constant velocity from the last two tracked frames; after a lost frame, the last
        tracked pose (an extrapolated velocity would carry the camera away for good)."""
        if len(self.poses) < 2 or self.states[-1] == "lost" or self.states[-2] == "lost":
            return self._last_tracked[0]
        a, b = self.poses[-2], self.poses[-1]
        return b @ np.linalg.inv(a) @ b

    def _track(self, rgb_t, depth_t):
        """Tracks against the map rendered at the predicted pose; where the map covers too
        little of the view or the alignment fails, against the last tracked frame, then the
        last keyframe. Lost only when all of them fail."""
        predicted = self._predict()
        trusted, map_reference = self._map_reference(*self._reference_render(predicted))
        # What the map covers of what this frame measured: where it has no depth, a keyframe
        # could not add anything (7-Scenes' registered depth leaves the image border empty).
        measured = depth_t > 0
        coverage = 1.0 if trusted is None else float(trusted[measured].mean() if measured.any()
                                                     else trusted.mean())

        def references():  # prepared only when the one before fails
            if map_reference is not None:
                yield map_reference
            for pose, rgb, depth in (self._last_tracked, self._last_kf[:3]):
                yield self.tracker.prepare_reference(rgb, depth, self.K_track, pose)

        reason = None
        for ref in references():
            res = self.tracker.track(rgb_t, depth_t, self.K_track, init_pose=predicted,
                                     reference=ref)
            if not res.lost:
                return res.pose, "ok", coverage, None
            reason = reason or res.reason
        return predicted, "lost", coverage, reason

    def _map_reference(self, pose, r) -> tuple:
        """(the pixels where the render is trusted, the render prepared as a tracking reference
        or None when it covers too little). A mapping thread's render serves many frames: it is
        prepared once."""
        if r is None:
            return None, None  # unknown until the mapping thread's first render: no keyframe for it
        if self._prepared is not None and self._prepared[0] is r:
            return self._prepared[1:]
        alpha = r["alpha"]
        trusted = alpha > self.config.reference_alpha
        reference = None
        if trusted.mean() >= self.config.min_reference_coverage:
            depth = np.where(trusted, r["depth"] / np.maximum(alpha, 1e-6), 0).astype(np.float32)
            rgb = np.clip(r["color"] / np.maximum(alpha, 1e-6)[..., None], 0, 1)
            reference = self.tracker.prepare_reference(rgb, depth, self.K_track, pose)
        self._prepared = (r, trusted, reference)
        return trusted, reference

    def _is_keyframe(self, i: int, pose: np.ndarray, coverage: float) -> bool:
        c = self.config
        if self._last_kf is None or self._map_empty():
            return True
        kf_pose, _, _, kf_index = self._last_kf
        # Fresh Gaussians are faint until trained: with a mapping thread behind, low coverage
        # says little, and counting it would flood the mapper with keyframes.
        coverage_counts = self._thread is None or self._thread.trained(c.map_iters_keyframe)
        moved = np.linalg.norm(pose[:3, 3] - kf_pose[:3, 3])
        return (moved > c.keyframe_translation
                or _rotation_deg(kf_pose, pose) > c.keyframe_rotation
                or (coverage_counts and coverage < c.keyframe_overlap)
                or i - kf_index >= c.keyframe_max_gap)

    # --- end of sequence ---------------------------------------------------------------------

    def finish(self, train: bool = True, progress=None) -> None:
        """Stops the mapping thread, waits for outstanding keyframe features and runs the final
        mapping iterations (unless `train` is false: a run cut short keeps the map it has), in
        batches, calling `progress(done, total)` after each; Ctrl-C stops between batches."""
        if self._thread is not None:
            self._thread.stop()
            self.mapping_stats.extend(self._thread.stats)
            self.reference_render_s = self._thread.reference_s
            self._thread = None
        if self._features is not None:
            self._features.drain()
        total = self.config.final_iters if train else 0
        for done in range(0, total, FINAL_BATCH):
            # Over every keyframe: the map is used (and evaluated) over the whole sequence.
            n = min(FINAL_BATCH, total - done)
            self.mapping_stats.append(self.mapper.train(n, window=self.mapper.num_keyframes))
            if progress is not None:
                progress(done + n, total)
        self._follow_keyframes()

    def _follow_keyframes(self) -> None:
        """Moves every frame with its keyframe, whose pose mapping may have refined."""
        refined = self.mapper.keyframe_poses()
        self.poses = [refined[k] @ rel if 0 <= k < len(refined) else p
                      for (k, rel), p in zip(self._anchors, self.poses)]

    def frame_exposures(self) -> Optional[np.ndarray]:
        """Per frame, the exposure (n x 2 x 3: per channel gain and bias, from the map's
        colour to the camera's) of the keyframe it was tracked after; None when exposures are
        not trained (mapper option `exposure_lr`)."""
        self._check_idle()
        if not self.mapper.config()["exposure_lr"]:
            return None
        kf = self.mapper.keyframe_exposures()
        return np.stack([kf[k] for k, _ in self._anchors]) if self._anchors else None

    def _check_idle(self) -> None:
        if self.mapping_in_thread:
            raise RuntimeError("the mapping thread owns the map while SLAM runs: call finish() first")

    def gaussian_map(self) -> GaussianMap:
        self._check_idle()
        return GaussianMap.from_arrays(self.mapper.export())

    @property
    def pca(self):
        return None if self._features is None else self._features.pca

    def render(self, pose, K=None, width=None, height=None, features=False) -> dict:
        """Renders the live map (colour, depth, alpha, and features if asked)."""
        self._check_idle()
        K = self.K if K is None else np.asarray(K)
        return self.mapper.render(np.asarray(pose, dtype=np.float64), _k4(K),
                                  width or self.width, height or self.height, features)


class _FeatureFeed:
    """Keyframe features, off the tracking path: an encoder in a worker thread, a PCA fitted on
    the first keyframes' patches (or loaded), and the compressed grids handed to the mapper."""

    def __init__(self, slam: SLAM, encoder=None):
        from .features import PCA, AsyncExtractor, Encoder

        c = slam.config
        self.slam = slam
        if encoder is None:
            encoder = Encoder(c.encoder, input_size=c.encoder_size, threads=c.encoder_threads)
        self.extractor = AsyncExtractor(encoder)
        self.pca = PCA.load(c.pca_path) if c.pca_path else None
        if self.pca is not None and self.pca.n_components != c.feature_dim:
            raise ValueError(f"{c.pca_path} compresses to {self.pca.n_components} dimensions, "
                             f"feature_dim is {c.feature_dim}")
        self._waiting: list = []  # (keyframe id, raw features) until the PCA is fitted

    def submit(self, kf_id: int, rgb: np.ndarray) -> None:
        self.extractor.submit(kf_id, rgb)

    def collect(self) -> None:
        for r in self.extractor.poll():
            self._take(r)

    def drain(self) -> None:
        self.extractor.close()
        self.collect()
        if self._waiting and self.pca is None:
            self._fit()
        self._flush()

    def _take(self, r) -> None:
        self.slam.feature_timings["extraction"].append(r.extract_ms)
        self._waiting.append((r.key, r.features))
        if self.pca is None and len(self._waiting) >= self.slam.config.pca_keyframes:
            self._fit()
        self._flush()

    def _fit(self) -> None:
        from .features import PCA

        pca = PCA(self.slam.config.feature_dim)
        for _, raw in self._waiting:
            pca.partial_fit(raw.reshape(-1, raw.shape[-1]))
        self.pca = pca

    def _flush(self) -> None:
        """Compresses the waiting grids and hands them to the mapper, once there is a PCA."""
        if self.pca is None:
            return
        for key, raw in self._waiting:
            t0 = time.perf_counter()
            grid = np.ascontiguousarray(self.pca.transform(raw), dtype=np.float32)
            self.slam.feature_timings["compression"].append(1e3 * (time.perf_counter() - t0))
            self.slam._mapping.set_features(int(key), grid)
        self._waiting.clear()
