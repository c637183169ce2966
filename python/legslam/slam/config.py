"""Every knob of a SLAM run: `SLAMConfig`, with typed sections for the engine's mapper and
tracker (`MapperOptions`, `TrackerOptions`) generated from the engine's own option tables, so
that names, kinds and defaults have one source. `DERIVED` is the one place that says which
option wins where SLAMConfig sets engine options itself.

    cfg = SLAMConfig(final_iters=500, mapper={"exposure_lr": 0.01})
    cfg = SLAMConfig.from_file("run.toml")      # [mapper] and [tracker] tables are the sections
"""

from __future__ import annotations

import json
import logging
import numbers
import os
from dataclasses import asdict, dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Optional

from .. import _core
from ..models import INT8_NAME
from ..tracking import fitting_levels

__all__ = ["SLAMConfig", "MapperOptions", "TrackerOptions", "DERIVED"]

log = logging.getLogger("legslam")

#: Engine options that SLAMConfig sets from options of its own: giving one in a section is an
#: error naming the option to set instead, so neither silently overrides the other.
DERIVED = {
    "mapper": {"num_features": "feature_dim (or features = false)", "sh_degree": "sh_degree",
               "levels": "map_width", "finest_level": "map_width", "grow_level": "map_width",
               "grow_stride": "grow_width", "feature_level_offset": "feature_width"},
    "tracker": {},
}

#: Section options that became derived, with the default they had: config files written before
#: (every run's config.json) still read. The old default is dropped quietly; another value with
#: a warning naming the option to set instead.
RETIRED = {"mapper": {"feature_level_offset": 1}, "tracker": {}}

#: Where a SLAM run's defaults differ from the engine's: it tracks images already shrunk to
#: `track_width`, from their own resolution, through as many levels as they have room for
#: (None: as many as keep the coarsest at least 8 pixels), with 2 Gauss-Newton iterations at
#: the finest level instead of 4. Frame to frame at 320 wide, the finest level's iterations
#: were most of the tracker's time, and two placed frames as well as four (median error
#: against the ground truth 0.256 / 0.257 cm on 7-Scenes, 0.022 / 0.022 cm on a Replica
#: render, 0.052 / 0.052 cm with Kinect-like noise) in 12-17 instead of 20-24 ms; one was as
#: good frame to frame, but placed a real frame seen from 2 cm away 1.3-2.9 mm off (two and
#: four: 0.15-0.87 mm; tests/test_tracking.py). Real time on 7-Scenes: 11.4-11.8 instead of
#: 9.1-10.2 fps, its map 0.2 dB behind (a shorter run maps less); synchronous: ATE 4.17 / 4.06
#: cm and 24.85 / 24.81 dB, Replica 0.46 / 0.45 cm and 33.75 / 34.12 dB, Kinect-like noise
#: 0.53 / 0.53 cm and 34.07 / 33.27 dB.
SLAM_DEFAULTS = {"mapper": {}, "tracker": {"finest_level": 0, "levels": None,
                                           "iterations": [2, 8, 10]}}

_INF = float("inf")
_NUMBER = {int: numbers.Integral, float: numbers.Real}
_KIND_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
               list: "a list of integers", dict: "a table of options"}


def _is(kind, v) -> bool:
    """Whether `v` is a value of `kind` (numpy scalars too, but never True/False for numbers)."""
    if kind in _NUMBER:
        return isinstance(v, _NUMBER[kind]) and not isinstance(v, bool)
    if kind is list:
        return isinstance(v, (list, tuple)) and all(_is(int, x) for x in v)
    return isinstance(v, kind)


def _section_class(section: str, engine_defaults: dict, doc: str) -> type:
    """A dataclass of the engine's options of `section`, less the derived ones, with the SLAM's
    defaults where they differ."""
    own = SLAM_DEFAULTS[section]
    specs = []
    for name, default in engine_defaults.items():
        if name in DERIVED[section]:
            continue
        default = own.get(name, default)
        kind = type(engine_defaults[name])
        annotation = Optional[kind] if default is None else kind
        value = field(default_factory=lambda d=default: list(d)) if kind is list else field(default=default)
        specs.append((name, annotation, value))

    def from_dict(cls, data: dict, source: str = "config"):
        """The section from a dict (a config file's table): unknown and derived names are
        errors that say what to do instead."""
        if not isinstance(data, dict):
            raise ValueError(f"{section} must be a table of options, got {data!r}")
        data = dict(data)
        for name, default in RETIRED[section].items():
            if name in data and data.pop(name) != default:
                log.warning("%s: %s.%s is no longer read; it is set from %s, set that instead",
                            source, section, name, DERIVED[section][name])
        for name in data:
            if name in DERIVED[section]:
                raise ValueError(f"{source}: {section}.{name} is set from {DERIVED[section][name]}; "
                                 f"set that instead")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{source}: unknown {section} option(s) {', '.join(map(str, unknown))}; "
                             f"known: {', '.join(sorted(known))}")
        return cls(**data)

    def check(self) -> None:
        """Raises ValueError naming the first option of the wrong kind or value (values are
        checked by the engine)."""
        for f in fields(self):
            v, kind = getattr(self, f.name), type(engine_defaults[f.name])
            if not ((v is None and f.default is None) or _is(kind, v)):
                raise ValueError(f"{section}.{f.name} must be {_KIND_NAMES[kind]}, got {v!r}")
        checker = {"mapper": _core.mapper_options, "tracker": _core.tracker_options}[section]
        try:
            checker(self.engine())
        except ValueError as e:
            raise ValueError(f"{section}: {e}") from None

    def engine(self) -> dict:
        """The options given to the engine (those left to the image size omitted)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)
                if getattr(self, f.name) is not None}

    cls = make_dataclass(
        f"{section.capitalize()}Options", specs,
        namespace={"from_dict": classmethod(from_dict), "check": check, "engine": engine,
                   "__doc__": doc, "__module__": __name__})
    return cls


def _plain(v):
    """Numpy scalars as Python numbers, which the engine's option tables take."""
    if isinstance(v, (list, tuple)):
        return [int(x) for x in v]
    if isinstance(v, bool) or not isinstance(v, numbers.Number):
        return v
    return int(v) if isinstance(v, numbers.Integral) else float(v)


MapperOptions = _section_class("mapper", dict(_core.mapper_options()), """The mapper's options
(the engine's `MapperConfig`, crates/legslam-core/src/map/train.rs, documents each): learning
rates, loss weights, growth, pruning, densification, keyframe window, pose and exposure
refinement. Those in `DERIVED["mapper"]` are set from SLAMConfig's own options.""")

TrackerOptions = _section_class("tracker", dict(_core.tracker_options()), """The tracker's
options (the engine's `TrackerConfig`, crates/legslam-core/src/track/mod.rs, documents each):
pyramid, iterations, robust thresholds, loss verdicts. `finest_level` defaults to 0 and
`levels` to None (as many as the tracking size has room for): the SLAM tracks images already
shrunk to `track_width`; `iterations` to 2 at the finest level (SLAM_DEFAULTS says why).""")


@dataclass
class SLAMConfig:
    """Every knob of a run, with defaults for a 2-core CPU. `mapper` and `tracker` are the
    engine's options (a dict is taken too); `DERIVED` lists those set from the fields here."""

    #: Tracking runs at about this width (frame and map render alike; full resolution for
    #: narrower input).
    track_width: int = 320
    #: New keyframe when the camera moved this far (m) or turned this much (degrees) since the
    #: last one, or the map covers less than `keyframe_overlap` of the pixels where the frame
    #: measured depth, or `keyframe_max_gap` frames passed. With a mapping thread the coverage
    #: counts only while the map keeps up: paced 7-Scenes made none of its 76 keyframes for it
    #: (two runs; `keyframe_reasons` in metrics.json), the synchronous run 32 of its 90, and
    #: without them 76 and 3.29 against 2.94 cm ATE; but the synchronous run alone moves
    #: that much with the surface's truncation 1 mm longer (README, *What the rest of real
    #: time's gap is*).
    keyframe_translation: float = 0.1
    keyframe_rotation: float = 10.0
    keyframe_overlap: float = 0.9
    keyframe_max_gap: int = 15
    #: Mapping iterations after a new keyframe, and after every other tracked frame (none:
    #: synchronous runs spend them at the end instead, `final_iters_per_frame`).
    map_iters_keyframe: int = 15
    map_iters_frame: int = 0
    #: The map trains at the coarsest pyramid level at least this wide (or full resolution).
    map_width: int = 320
    #: New Gaussians are seeded on a grid about this many columns wide (every pixel of a
    #: narrower training level). On 7-Scenes, 150 frames at 320x240, seeding every other pixel
    #: gave a better map (22.9 against 22.6 dB) from a quarter of the Gaussians, 2.3x faster.
    grow_width: int = 160
    #: Language features train at the coarsest pyramid level at least this wide, and at least
    #: one level below the colour (at most two): their target is the encoder's patch grid
    #: (16x16) upsampled, so finer pixels add cost, not information. Each of their pixels is
    #: the colour level's image at a point of its block drawn afresh every iteration (mapper
    #: option `feature_jitter`). A 640-wide input trains them at 80 (colour at 320), a 600-wide
    #: one at 150 (colour at 600). On 7-Scenes, 80 instead of 160 gave held-out feature
    #: agreement 0.759 against 0.730 and a cheaper mapping iteration (README, *The engine's
    #: speed*).
    feature_width: int = 80
    #: Degree of the spherical harmonics of each Gaussian's colour (0: one colour seen alike
    #: from everywhere; 3, as LEG-SLAM and 3DGS, 16 coefficients a channel). On 7-Scenes, 200
    #: frames: 23.3 / 24.1 / 25.0 / 25.8 dB with degree 0 / 1 / 2 / 3, at the same speed
    #: (view-dependent colour can follow gloss, and an exposure that changes with the view).
    sh_degree: int = 3
    #: Mapping iterations once the sequence has ended, on keyframes drawn from all of them.
    final_iters: int = 100
    #: Synchronous runs: this many final iterations more per frame of the run (a run cut short
    #: trains none of them: its map keeps what the keyframes gave it). An iteration
    #: after the sequence is worth more than one after a frame: it draws from every keyframe
    #: and its learning rate anneals (`final_lr_factor`). 0.4 a frame at the end instead of
    #: one after each (`map_iters_frame` 1): 7-Scenes 3.49 against 2.80 fps, 25.14 against
    #: 25.23 dB every 5th frame (ATE 3.95 / 3.97 cm); 400-frame Replica render 35.91 against
    #: 35.48 dB, with Kinect-like noise 35.22 against 34.82 dB; the built-in scene 2.3-2.4
    #: against 1.9 fps, 31.87 against 32.06 dB. 0.6 since the engine got faster (2026-12-03):
    #: 7-Scenes 24.99 against 24.81 dB, the 400-frame Replica render 35.48 against 35.41 dB,
    #: the built-in scene 31.95 against 31.73 dB, for 7-16% of the frame rate (7-Scenes 5.28
    #: against 5.66 and 6.29 fps, the Replica render 5.00 against 5.47); 0.8 gave 25.11, 35.76
    #: and 32.07 dB at 4.84 and 4.66 fps, too near 4 fps for a slow hour.
    final_iters_per_frame: float = 0.6
    #: With `mapping_thread`: the final iterations go on past `final_iters` while they have
    #: taken less than this share of the time the frames took (0: `final_iters` only). The
    #: map of a real-time run is short of iterations, and this spends on it a set share of
    #: the run, whatever its length: on 7-Scenes 300 final iterations instead of 100 gave
    #: +0.8 dB at 15.9 instead of 19.8 fps, but a fixed 300 halved a 400-frame run's rate.
    #: 0.75 since frames are read ahead (2026-11-26, alternating): 7-Scenes 23.66 dB every 5th
    #: frame at 12.2 fps, against 0.5's 23.33 / 23.35 dB at 13.9 / 14.3 fps and 1.0's 23.83 /
    #: 23.87 dB at 10.5 / 10.7; the 400-frame Replica render 33.01 dB at 12.9 fps, against
    #: 32.13 dB at 13.1 and 33.23 dB at 9.9. 1.25 since frames are tracked eight pixels at a
    #: time (2026-11-26): 7-Scenes 23.61 dB at 14.2 fps, against 0.75's 23.26 dB at 16.2 and,
    #: with the old tracker in the same hour, 23.54 dB at 13.2; the Replica render 33.12 dB
    #: at 13.3 fps, against 0.75's 31.65 dB at 17.2. 0.95 since features train at 80x60,
    #: point-sampled (2026-12-07, at the camera's pace, alternating where repeated): the
    #: Kinect-noise Replica render 35.19 and 35.51 dB at 14.9 and 14.8 fps, against 1.25's
    #: 35.32-35.81 dB at 13.0 and the synchronous 35.30; 7-Scenes 25.61 dB at 15.3 fps
    #: (synchronous 24.92); the exact Replica render 36.24 dB at 15.3 fps (synchronous 35.58).
    final_time: float = 0.95
    #: With `mapping_thread`: the final iterations also go on until the map has had, in all,
    #: at least this share of the iterations a synchronous run over the same frames would give
    #: it (`map_iters_keyframe` a keyframe, `map_iters_frame` a frame, then `final_iters` and
    #: `final_iters_per_frame` a frame; 0: no floor). A short recording leaves the mapping
    #: thread little time, and `final_time` a share of little: the built-in scene (60 frames,
    #: at the camera's pace) trained 2 iterations while its frames came and 100 after, its map
    #: 28.94 against the synchronous 31.92 dB every 5th frame. Not paced, 0.7 against 1.0
    #: (README: *A floor under real time's iterations*): the built-in scene 31.64 and 31.67
    #: against 32.65 and 32.68 dB at 10-11 against 7.7-8.5 fps, the Kinect-noise Replica render
    #: 35.64 against 36.36 dB at 14.5 against 11.7 fps, 7-Scenes 25.04 against 25.40 dB at 17.2
    #: against 13.8 fps; synchronous 31.92, 35.30 and 24.92-25.14 dB at 6.1, ~5 and 4.7-5.3.
    #: So 0.7: the synchronous map's level at the most frames a second.
    realtime_iters_floor: float = 0.7
    #: The final iterations' learning rates fall log-linearly from where the frames left them
    #: (the mapper's; with `mapping_thread`, the real-time scales of them) to this many times
    #: that (1: constant), as the iterations (or, in real time, the time) run out. At a
    #: constant rate Adam keeps moving every Gaussian by about the rate each step; annealed,
    #: the map settles. Synchronous, 0.1 against 1: 7-Scenes 25.61 against 24.85 dB every
    #: 5th frame, a 400-frame Replica render 35.63 against 33.75 dB, with Kinect-like depth
    #: noise 35.09 against 34.07 dB (ATE unchanged in all). Real time, to 0.1 of its own
    #: scales (geometry 0.3, the rest 0.2) instead of 0.1 of the mapper's (2026-11-27,
    #: alternating, means): 7-Scenes flat out 24.27 against 24.08 dB (3 runs each); at the
    #: camera's pace with `final_time` 0.95, 24.70 against 24.61 (5 each); a 400-frame Replica
    #: render paced 34.21 against 33.84 (3 each), flat out 33.08 against 32.98 (2 each), with
    #: Kinect-like depth noise flat out 32.67 against 32.26 and paced 34.20 against 34.02 (2
    #: each); the built-in scene 29.09 against 28.67 (3 each).
    final_lr_factor: float = 0.1
    #: With `mapping_thread`: the learning rates of the Gaussians' opacity, colour and features are
    #: this many times the mapper's (`lr_*`) while frames come in (their positions', scales' and
    #: rotations' `realtime_geometry_lr_scale` times), and the final iterations anneal them from
    #: there to `final_lr_factor` times that. A real-time map gets a third of a synchronous one's
    #: iterations, and larger steps make up part of it (measured with every group at this scale and
    #: the final rates annealed to 0.1 of the mapper's, as they were then; 2026-11-27, runs
    #: alternating, PSNR every 5th frame, means of 1-4 runs): 7-Scenes flat out 23.93 against 23.39
    #: dB, at the camera's pace 24.52 against 24.26 dB; the 400-frame Replica render flat out 32.46
    #: against 32.45 dB, paced 34.12 against 34.21, with Kinect-like noise paced 33.58 against
    #: 33.53; depth L1 lower (7-Scenes flat out 2.67-2.71 against 2.78-2.86 cm, Replica 1.25-1.38
    #: against 1.65-1.89) or the same (7-Scenes paced), the features closer to the encoder's. 3
    #: gained more on 7-Scenes (24.13 flat out, 24.80 paced) and on the Replica render flat out
    #: (32.85), but lost 0.5 dB on it paced (33.74), where the map gets more iterations a keyframe;
    #: 6 fell back (7-Scenes 23.69 dB, SSIM 0.785 against ~0.82; Replica 32.17 dB). The built-in
    #: scene in real time (a run of seconds) with 2: 28.6-28.7 against 28.9 dB, depth L1 3.0 against
    #: 4.0 cm. Synchronous runs lost with 2 (7-Scenes 25.25 against 25.21 dB but SSIM 0.835 against
    #: 0.847 and ATE 4.02 against 3.81 cm; Replica 35.50 against 35.90).
    realtime_lr_scale: float = 2.0
    #: With `mapping_thread`: the scale of the positions', scales' and rotations' learning rates, as
    #: `realtime_lr_scale` is the others'. New Gaussians are grown round, one pixel wide, and a
    #: real-time map has few iterations to shape them. 3 against 2 (2026-11-27, alternating, the
    #: final rates annealed to 0.1 of the mapper's as then): 7-Scenes flat out 24.34 / 24.18 against
    #: 24.17 / 24.06 dB every 5th frame, paced 24.81 / 24.85 against 24.76 / 24.78; a 400-frame
    #: Replica render with Kinect-like noise flat out 32.53 / 32.44 against 32.33 / 32.43 (depth L1
    #: 1.21 / 1.25 against 1.53 / 1.34 cm), paced 33.77 / 33.72 against 33.50 / 33.34. Colour at 3
    #: too lost on the exact render paced (33.92 against 34.20 dB, means of three), geometry alone
    #: not (34.26). The built-in scene in real time (4 iterations while frames come in, then 100)
    #: lost 0.1-0.25 dB (28.38-28.50 against 28.63) with depth L1 2.5 against 3.0 cm.
    realtime_geometry_lr_scale: float = 3.0
    #: With `mapping_thread`: no keyframe sooner than this many frames after the last. A camera
    #: moving about 1 m/s passes `keyframe_translation` every 3 frames, and a keyframe's work
    #: (encoding, covisibility alignments, its place) ten times a second put a real-time run up
    #: to a second behind a 30 Hz camera (a Replica render at 4 times its speed: 280-342 of 500
    #: frames late; with 5, 6 late, as good a map and trajectory). 7-Scenes never made two
    #: keyframes less than 8 frames apart, the built-in scene none less than 5.
    realtime_keyframe_min_gap: int = 5
    #: With `mapping_thread`: only the first keyframe and every this many-th after it are
    #: encoded (language features, places; a keyframe overlaps its neighbours' views). While
    #: frames came in, the encoder took 0.4 of the two cores and the map 0.7. Paced, 2 against
    #: 1 (runs alternating; README, "At the camera's pace"): 400-frame Replica renders 34.98,
    #: 34.83 against 34.23, 34.41 dB (Kinect-like noise; synchronous 35.17) and 35.36, 35.47
    #: against 34.64, 34.74 (exact; 35.61), 7-Scenes 25.01, 25.08 against 24.98, 24.94 dB, the
    #: built-in scene 30.2 against 29.8; the held-out features' mean cosine 0.01-0.02 lower.
    realtime_feature_every: int = 2
    #: Map in a worker thread while this one tracks (real time: the frame rate is the
    #: tracker's, and the map gets the iterations the spare CPU allows, `mapping_batch` at a
    #: time, on a thread pool of its own). Low overlap then makes a keyframe only once the
    #: previous one has had `map_iters_keyframe` iterations; `map_iters_frame` is unused.
    #: The tracker's reference is the map rendered after each batch at the latest tracked
    #: pose. The library's default is synchronous (a run that repeats itself to the bit); the
    #: `legslam` command's is real time (`--sync` for synchronous; README, *Real time by
    #: default*).
    mapping_thread: bool = False
    mapping_batch: int = 2
    #: With a mapping thread: the mapper's threads (0: one per core); the tracker then runs
    #: on one thread of its own.
    mapping_threads: int = 0
    #: A rendered pixel is trusted as a tracking reference where its alpha exceeds this; below
    #: `min_reference_coverage` of trusted pixels, the last keyframe is the reference instead.
    reference_alpha: float = 0.8
    min_reference_coverage: float = 0.5
    #: Every this many frames a frame is tracked against the map first; the others against
    #: the last tracked frame first (then the map; see track_policy). 0: the map never first,
    #: only where the last frame fails; 1: the map first always. With covisibility edges
    #: (synchronous runs, keyframes aligned at the tracking level), 0 against 5: a 400-frame
    #: Replica render 0.55 -> 0.47 cm ATE and 33.83 -> 33.65 dB every 5th frame, the same with
    #: Kinect-like depth noise 0.94 -> 0.52 cm and 32.38 -> 33.68 dB (against the map, each
    #: 5th frame jumped 0.5 cm from the chain of frames), 7-Scenes 4.30 -> 4.14 cm and 24.67 ->
    #: 24.91 dB. (Without covisibility edges, 5 against 1 had taken real time on the Replica
    #: render from 3.3 to 1.0 cm.)
    map_reference_every: int = 0
    #: Tracked frames' depth is fused into a signed distance volume of voxels this wide (m; 0:
    #: off), and a frame is tracked against the last fused frame's colour with the fused
    #: surface's depth (legslam.slam.surface), with this truncation distance (m). Synchronous,
    #: on against off (2026-11-28): 7-Scenes ATE 2.93 against 3.81 cm, 24.89 against 25.21 dB
    #: every 5th frame, 5.08 fps (the first version: 3.10 cm, 24.96 dB, at 4.86 against 5.34
    #: fps in one hour); with the first version, a 400-frame Replica render with Kinect-like
    #: depth noise 0.48 against 0.54 cm, 35.62 against 35.02 dB, the same render exact 0.47
    #: against 0.46 cm, 35.84 against 35.90 dB (README: *Tracking against the fused surface*).
    #: `surface_realtime`: in real time too. A worker thread ray-casts the surface from each
    #: tracked frame it is free for (a frame that comes while it is busy is passed over, not
    #: queued) and fuses every `realtime_surface_every`-th of those first; synchronous runs
    #: ray-cast every frame and fuse every `surface_every`-th. What a frame gains is the
    #: ray-cast from its predecessor's own pose, not the fusion (README: *What the rest of the
    #: 7-Scenes gap is*). Paced 7-Scenes (2026-12-07 afternoon): 3.36 (through a /tmp patch),
    #: 3.49, 3.65, 3.67 and 3.46 cm against 3.77 and 3.79 fusing and ray-casting every 3rd
    #: frame, the map 25.15, 25.06, 24.99, 25.16 and 24.84 against 24.92 and 25.06 dB; the 3.65
    #: cm run had a test suite beside it for a while and put 318 frames late, the others 4, 7, 2
    #: and 23 (21 and 22, and 2-22 in the day's other runs fusing every 3rd). The worker's
    #: engine threads run at the tracker's priority: at the mapping threads' lowered one the
    #: reference was 4.8 frames old on average (3.6 ray-casting every free frame; at the
    #: tracker's priority 2.4), and 7-Scenes stayed at 3.72 cm. Replica renders, 400 frames:
    #: Kinect-like noise 0.48 cm, 35.35 dB; exact 0.47 cm, 35.50 dB (the morning's, fusing and
    #: ray-casting every 3rd: 0.47-0.48 cm, 35.27-35.67 dB and 0.46 cm, 35.94 dB). Before it
    #: (fusing every 3rd, the frames between against the last fused), on against off: 7-Scenes
    #: 3.69 against 4.26 cm, the Kinect-noise render 0.47 against 0.54 cm, the exact one 0.46
    #: against 0.45 cm. Fusing every 2nd or every frame made more frames late for no better
    #: trajectory.
    surface_voxel: float = 0.01
    surface_truncation: float = 0.04
    surface_realtime: bool = True
    surface_every: int = 1
    realtime_surface_every: int = 3
    #: With `relocalise`: an alignment whose residual is more than this many times the recent
    #: median is refused as lost, for relocalisation to place (the camera jumped; see
    #: track_policy). On the built-in scene a jump tripled it.
    jump_residual_ratio: float = 2.5
    #: Language features: encoder (a model name or an ONNX path), its input size, the
    #: compressed dimension K, and how many keyframes' patches fit the PCA. "auto": the int8
    #: DINOv2 ViT-S/14 with a mapping thread, its full-precision original ("default")
    #: without. In real time the encoder shares the two cores with tracking and mapping: the
    #: int8 one took 19.5 instead of 28 s of a core on 7-Scenes, and runs went 8-20% more
    #: frames a second (7-Scenes, two Replica renders) with the same query scores.
    #: Synchronous runs gain no speed from it, and their maps moved by -0.58 to +0.30 dB (mean
    #: -0.2 over four runs, where the mapper's seed alone moves one 0.5 dB).
    features: bool = True
    encoder: str = "auto"
    encoder_size: int = 224
    encoder_threads: int = 1
    feature_dim: int = 64
    pca_keyframes: int = 3
    #: A PCA fitted beforehand (.npz from legslam.features.PCA.save) instead of fitting one.
    pca_path: Optional[str] = None
    #: Place recognition (legslam.slam.place_recognition; retrieval by patch tokens):
    #: `relocalise` places a lost frame in the map again, `loop_closure` closes loops over a
    #: keyframe pose graph. Either runs the encoder on keyframes, even with `features` off.
    relocalise: bool = True
    loop_closure: bool = True
    #: Retrieval: the most similar keyframes tried, at least this alike (cosine of the mean
    #: patch tokens).
    place_candidates: int = 3
    place_min_similarity: float = 0.7
    #: Coarse alignment: ORB keypoints matched when the nearest is nearer than this times the
    #: second nearest, lifted with depth; RANSAC inliers within this distance (m), and at least
    #: this many of them.
    place_match_ratio: float = 0.8
    place_ransac_threshold: float = 0.05
    place_min_inliers: int = 10
    #: Dense verification against the keyframe's view: the views overlap on at least this
    #: share of the frame's pixels, and at least this share of the pixels both see are the
    #: tracker's inliers.
    place_min_overlap: float = 0.25
    place_min_inlier_ratio: float = 0.65
    #: Loop candidates are at least this many keyframes older than the new keyframe.
    loop_min_gap: int = 15
    #: Covisibility edges (legslam.slam.covisibility): each new keyframe is aligned by the
    #: tracker with up to this many older keyframes whose views its depth lands in on at least
    #: `covisibility_min_overlap` of its pixels, and each alignment that verifies becomes a
    #: pose-graph edge (as sure as a loop edge). 0 turns them off. Synchronous, 4 against 0
    #: (with the map first every 5th frame, as before them): ATE 0.97 -> 0.45 cm and 32.68 ->
    #: 34.12 dB every 5th frame on a 400-frame Replica render, 1.38 -> 0.53 cm on the same with
    #: Kinect-like depth noise (odometry 1.15 and 1.23 cm), 7-Scenes 3.37 -> 4.05 cm (odometry
    #: 4.88) and 24.52 -> 24.92 dB, the frames agreeing better with each other under the new
    #: poses than under the dataset's (README, "Relocalisation and loop closure").
    covisibility_edges: int = 4
    covisibility_min_overlap: float = 0.3
    #: Keyframes are aligned this many pyramid levels coarser than frames are tracked (1:
    #: 160x120 for 320x240 tracking, a quarter of the work; offline, edges as accurate on
    #: both Replica renders, 0.20 against 0.17-0.19 cm median error).
    covisibility_coarser: int = 1
    #: Odometry edges between keyframes: standard deviation per metre moved (at least 10 cm
    #: counted) and per radian turned (at least 5 degrees counted); loop edges: metres and
    #: degrees. Odometry drifts 1-2% on 7-Scenes: these leave room for it, lest a true loop
    #: look like an outlier.
    odometry_sigma_translation: float = 0.1
    odometry_sigma_rotation: float = 0.1
    loop_sigma_translation: float = 0.01
    loop_sigma_rotation: float = 0.5
    mapper: MapperOptions = field(default_factory=MapperOptions)
    tracker: TrackerOptions = field(default_factory=TrackerOptions)

    def __post_init__(self):
        for name, cls in (("mapper", MapperOptions), ("tracker", TrackerOptions)):
            v = getattr(self, name)
            if isinstance(v, dict):
                setattr(self, name, cls.from_dict(v))
        self.check()

    def check(self) -> None:
        """Raises ValueError naming the first option of the wrong type or out of its range."""
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("mapper", "tracker"):
                if not isinstance(v, (MapperOptions, TrackerOptions)[f.name == "tracker"]):
                    raise ValueError(f"{f.name} must be a table of options, got {v!r}")
                v.check()
                continue
            kind = type(f.default) if f.default is not None else (str, os.PathLike)
            if f.name == "pca_path":
                ok = v is None or isinstance(v, kind)
            else:
                ok = _is(kind, v)
            if not ok:
                raise ValueError(f"{f.name} must be {_KIND_NAMES.get(kind, 'a path')}, got {v!r}")
            low, high = _RANGES.get(f.name, (None, None))
            if low is not None and not low <= v <= high:  # also false for NaN
                bound = f"at least {low}" if high == _INF else f"in [{low}, {high}]"
                raise ValueError(f"{f.name} must be {bound}, got {v}")

    def mapper_options(self, width: int) -> dict:
        """The engine's mapper options for frames `width` pixels wide: the section's, and the
        derived ones (`DERIVED`)."""
        # Train and grow at about `map_width` (full resolution for smaller inputs): what two
        # cores afford per iteration.
        level = 0
        while width >> (level + 1) >= self.map_width:
            level += 1
        features = level + 1
        while width >> (features + 1) >= self.feature_width and features < level + 2:
            features += 1
        return {**self.mapper.engine(),
                "num_features": self.feature_dim if self.features else 0,
                "sh_degree": self.sh_degree, "finest_level": level, "grow_level": level,
                "levels": level + 3, "feature_level_offset": features - level,
                "grow_stride": max(1, round((width >> level) / self.grow_width))}

    def tracker_options(self, width: int, height: int) -> dict:
        """The engine's tracker options for tracking images of width x height."""
        opts = self.tracker.engine()
        if self.tracker.levels is None:
            opts["levels"] = fitting_levels(width, height, self.tracker.finest_level)
        return opts

    def covisibility_tracker_options(self, width: int, height: int) -> dict:
        """The tracker options of keyframe alignment (`covisibility_coarser` levels coarser than
        tracking) for tracking images of width x height."""
        opts = self.tracker_options(width, height)
        opts["finest_level"] = min(4, opts["finest_level"] + self.covisibility_coarser)
        opts["levels"] = min(opts["levels"], fitting_levels(width, height, opts["finest_level"]))
        return opts

    @property
    def encoder_model(self) -> str:
        """The encoder `encoder` names ("auto" resolved for this mode)."""
        if self.encoder != "auto":
            return self.encoder
        return INT8_NAME if self.mapping_thread else "default"

    @property
    def place_recognition(self) -> bool:
        """Whether keyframes' places are kept (for relocalisation or loop closure)."""
        return self.relocalise or self.loop_closure

    @classmethod
    def from_file(cls, path, **overrides) -> "SLAMConfig":
        """Reads a .toml, .json or .yaml file (only the keys given change a default)."""
        return cls.from_dict({**cls.read_file(path), **overrides}, source=str(path))

    @staticmethod
    def read_file(path) -> dict:
        """The options a .toml, .json or .yaml config file gives, unchecked."""
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
        if not isinstance(data, dict):
            raise ValueError(f"{path}: a config file holds options by name, not {type(data).__name__}")
        return data

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> "SLAMConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{source}: unknown option(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(known))}")
        data = dict(data)
        for name, section in (("mapper", MapperOptions), ("tracker", TrackerOptions)):
            if name in data:
                data[name] = section.from_dict(data[name], source)
        return cls(**data)

    def to_dict(self) -> dict:
        return asdict(self)

    def realtime_lr_scales(self) -> dict:
        """The mapping thread's learning-rate scale by group (`MapperCore.train`'s names)."""
        g, a = self.realtime_geometry_lr_scale, self.realtime_lr_scale
        return {"means": g, "log_scales": g, "quats": g, "opacity": a, "sh": a, "features": a}


#: Each numeric option's range (inclusive).
_RANGES = {
    "track_width": (16, _INF), "map_width": (16, _INF), "grow_width": (16, _INF),
    "feature_width": (1, _INF), "sh_degree": (0, 3),
    "keyframe_translation": (0.0, _INF), "keyframe_rotation": (0.0, _INF),
    "keyframe_overlap": (0.0, 1.0), "keyframe_max_gap": (1, _INF),
    "map_iters_keyframe": (0, _INF), "map_iters_frame": (0, _INF), "final_iters": (0, _INF),
    "final_iters_per_frame": (0.0, _INF),
    "final_time": (0.0, _INF), "realtime_iters_floor": (0.0, _INF), "final_lr_factor": (1e-6, 1.0),
    "realtime_lr_scale": (1e-2, 1e2),
    "realtime_geometry_lr_scale": (1e-2, 1e2), "realtime_keyframe_min_gap": (1, _INF),
    "realtime_feature_every": (1, _INF),
    "mapping_batch": (1, _INF), "mapping_threads": (0, _INF),
    "reference_alpha": (0.0, 1.0), "min_reference_coverage": (0.0, 1.0), "map_reference_every": (0, _INF),
    "jump_residual_ratio": (1.0, _INF),
    "surface_voxel": (0.0, _INF), "surface_truncation": (1e-6, _INF),
    "surface_every": (1, _INF), "realtime_surface_every": (1, _INF),
    "encoder_size": (28, _INF), "encoder_threads": (0, _INF),
    # Checked against the encoder's own dimension once it is loaded; the bound keeps an absurd
    # value from reaching the engine's allocations where the encoder does not say.
    "feature_dim": (1, 4096),
    "pca_keyframes": (1, _INF),
    "place_candidates": (1, _INF), "place_min_similarity": (0.0, 1.0),
    "place_match_ratio": (1e-6, 1.0), "place_ransac_threshold": (1e-6, _INF),
    "place_min_inliers": (3, _INF), "place_min_inlier_ratio": (0.0, 1.0),
    "place_min_overlap": (0.0, 1.0), "loop_min_gap": (1, _INF),
    "covisibility_edges": (0, _INF), "covisibility_min_overlap": (0.0, 1.0),
    "covisibility_coarser": (0, 4),
    "odometry_sigma_translation": (1e-6, _INF), "odometry_sigma_rotation": (1e-6, _INF),
    "loop_sigma_translation": (1e-6, _INF), "loop_sigma_rotation": (1e-6, _INF),
}
