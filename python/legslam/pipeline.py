"""A sequence in, a run folder out (see `run_folder` for its files): SLAM over every frame,
the outputs written, the run evaluated.

    result = run(legslam.datasets.open(path), "out/", SLAMConfig())
    result["metrics"], result["timings"], result["slam"]

Frames that cannot be read keep the motion model's pose (counted, left out of the figures); a
run that stops early (too many unreadable frames in a row, Ctrl-C) still writes the trajectory
and map of the frames done. Warnings go to the "legslam" logger.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .blas import one_blas_thread
from .datasets import each_readable
from .datasets.read_ahead import ReadAhead
from .eval import evaluate_run
from .playback import pacer_for
from .run_folder import (CONFIG, MAP, METRICS, PCA_FILE, RECORDING, TIMINGS, write_camera, write_json,
                         write_trajectory)
from .slam import SLAM, SLAMConfig

__all__ = ["run"]

log = logging.getLogger("legslam")


def run(seq, out_dir, config: SLAMConfig | None = None, progress=None, evaluate_every: int = 5,
        encoder=None, viewer=None, pace: float | None = None) -> dict:
    """Runs SLAM over a sequence (from legslam.datasets.open) and writes the outputs. A live
    camera (datasets.realsense.RealSenseCamera) runs in real-time mode, records its frames in
    the run folder (`recording/`) and is evaluated on them; `metrics["dropped_frames"]`
    counts the frames it delivered that SLAM did not keep up with.

    `progress`, when given, hears of every frame (`frame(index, text)`) and of the final
    mapping iterations (`final_iterations(done, total)`). `viewer` (e.g.
    legslam.viewer.RerunViewer) sees every step, `on_frame(index, frame, step, slam)`, and the
    finished map, `on_finish(slam)`; its time is part of the wall time and is reported as its
    own stage. A sequence's frames are read on a thread of their own, two ahead of SLAM
    (datasets.read_ahead). numpy's BLAS runs on one thread meanwhile (legslam.blas).

    `pace`: a recording's frames are handed to SLAM no faster than `pace` times their
    timestamps' rate (1: as the camera delivered them; legslam.playback), and `timings.json`
    reports how far SLAM fell behind (`playback`); None: as fast as SLAM takes them."""
    with one_blas_thread():
        return _run(seq, out_dir, config or SLAMConfig(), progress, evaluate_every, encoder, viewer,
                    pace)


def _run(seq, out_dir, config: SLAMConfig, progress, evaluate_every: int, encoder, viewer,
         pace: float | None) -> dict:
    live = getattr(seq, "live", False)
    pacer = pacer_for(pace, live)
    if live and not config.mapping_thread:
        log.info("a live camera runs in real-time mode (mapping_thread = true)")
        config = replace(config, mapping_thread=True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / CONFIG, config.to_dict())
    if live:
        seq.start(record_to=out / RECORDING)
        K, w, h, source = seq.K, seq.width, seq.height, out / RECORDING
        frames = seq.frames()
    else:
        if not len(seq):
            raise ValueError(f"{getattr(seq, 'path', 'the sequence')} has no frames")
        first = seq[0]
        (h, w), K, source = first.depth.shape, first.K, getattr(seq, "path", "")
        frames = each_readable(seq)
    write_camera(out, K, w, h, str(source), None if live else getattr(seq, "selection", None))
    try:
        slam = SLAM(config, K, w, h, encoder=encoder)
    except BaseException:
        if live:
            seq.close()
        raise
    if not live:
        frames = ReadAhead(frames)
    t0 = time.perf_counter()
    stamps, viewer_ms = [], []
    unreadable: set[int] = set()
    try:
        for i, f in frames:
            stamp = seq.timestamp(i) if f is None else f.timestamp
            if pacer is not None:
                pacer.wait(stamp)
            stamps.append(stamp)
            if f is None:  # lost: the motion model's pose
                unreadable.add(i)
                slam.skip()
                continue
            r = slam.step(f.rgb, f.depth)
            if viewer is not None:
                t1 = time.perf_counter()
                viewer.on_frame(i, f, r, slam)
                viewer_ms.append(1e3 * (time.perf_counter() - t1))
            if progress is not None:
                progress.frame(i, f"{r.state:4s}  kf {len(slam.keyframe_frames)}  "
                                  f"gaussians {slam.num_gaussians}{_events(slam)}")
        live_s = time.perf_counter() - t0
        if live:
            seq.close()  # the camera's streams stop, its recording is complete
        slam.finish(progress=None if progress is None else progress.final_iterations)
    except BaseException:  # interrupted, or too many unreadable frames: keep the work done
        if live:
            seq.close()
        _save_partial(slam, out, stamps)
        raise
    finally:
        if isinstance(frames, ReadAhead):
            frames.close()
    if viewer is not None:
        t1 = time.perf_counter()
        viewer.on_finish(slam)
        viewer_ms.append(1e3 * (time.perf_counter() - t1))
    wall = time.perf_counter() - t0

    _save_trajectory_and_map(slam, out, stamps)
    timings = _timing_table(slam, wall, live_s, viewer_ms)
    if pacer is not None:
        timings["playback"] = pacer.report()
    write_json(out / TIMINGS, timings)
    renders = out / "renders"
    renders.mkdir(exist_ok=True)
    metrics = {"keyframes": len(slam.keyframe_frames),
               "keyframe_frames": list(slam.keyframe_frames),
               "keyframe_reasons": list(slam.keyframe_reasons),
               "lost_frames": int(sum(s == "lost" for s in slam.states)),
               "frames_without_depth": slam.frames_without_depth,
               "frames_depth_out_of_range": slam.frames_depth_out_of_range,
               "gaussians": slam.mapper.num_gaussians, "map_full_at_frame": slam.map_full_at,
               "fps": timings["fps"],
               **slam.trajectory_events()}
    if live:  # taken from the camera as they came; evaluated on the frames recorded
        metrics["dropped_frames"] = seq.dropped
        seq = seq.recording()
    size = (slam.width, slam.height)
    metrics.update(evaluate_run(
        seq, slam.poses, lambda pose, features: slam.mapper.render(pose, slam.K, *size, features),
        every=evaluate_every, keyframes=slam.keyframe_frames, skip=unreadable,
        depth_range=slam.depth_range,
        exposures=slam.frame_exposures(), renders_dir=renders))
    write_json(out / METRICS, metrics)
    return {"metrics": metrics, "timings": timings, "out": str(out), "slam": slam}


def _events(slam: SLAM) -> str:
    """The progress line's count of relocalisations and loops closed (those a later
    optimisation dropped left out), once there are any."""
    e = slam.trajectory_events()
    n = len(e.get("relocalisations", ()))
    m = sum(c["dropped_at_frame"] is None for c in e.get("loop_closures", ()))
    return (f"  reloc {n}" if n else "") + (f"  loops {m}" if m else "")


def _timing_table(slam: SLAM, wall_s: float, live_s: float, viewer_ms: list[float]) -> dict:
    def summary(v):
        return {"mean_ms": float(np.mean(v)) if v else 0.0,
                "median_ms": float(np.median(v)) if v else 0.0,
                # A live camera's frames wait for the slow ones.
                "p95_ms": float(np.percentile(v, 95)) if v else 0.0,
                "max_ms": float(np.max(v)) if v else 0.0,
                "total_s": float(np.sum(v)) / 1e3, "count": len(v)}

    table = {k: summary(v) for k, v in slam.timings.items()}
    table["feature_extraction (per keyframe, worker thread)"] = summary(slam.feature_timings["extraction"])
    table["compression (per keyframe)"] = summary(slam.feature_timings["compression"])
    if slam.covisibility is not None:
        table["covisibility (per keyframe, within mapping)"] = summary(slam.covisibility_ms)
    for key in ("render_s", "loss_s", "backward_s", "step_s"):
        table[f"mapping.{key[:-2]}"] = {"total_s": float(sum(getattr(s, key) for s in slam.mapping_stats))}
    final = sum(s.iterations for s in slam.final_mapping_stats)
    table["mapping_iterations"] = {"while_frames_came_in": sum(s.iterations for s in slam.mapping_stats) - final,
                                   "final": final}
    if slam.config.mapping_thread:
        table["mapping.reference_render"] = {"total_s": slam.reference_render_s}
    if viewer_ms:
        table["viewer (per frame, and the final map)"] = summary(viewer_ms)
    table["wall_s"] = wall_s
    table["fps"] = len(slam.poses) / wall_s if wall_s > 0 else 0.0
    # While frames come in, before the final mapping iterations: the rate a live camera sees.
    table["live_s"] = live_s
    table["fps_live"] = len(slam.poses) / live_s if live_s > 0 else 0.0
    return table


def _save_trajectory_and_map(slam: SLAM, out: Path, stamps: list) -> None:
    # A run stopped inside a frame has its stamp but not its pose.
    write_trajectory(out, np.array(stamps[:len(slam.poses)]), np.stack(slam.poses))
    slam.gaussian_map().save(out / MAP)
    if slam.pca is not None:
        slam.pca.save(out / PCA_FILE)


def _save_partial(slam: SLAM, out: Path, stamps: list) -> None:
    """Writes the trajectory and map of the frames done before a run stopped (no final
    iterations); says so, or why it could not."""
    try:
        if not slam.poses:
            return
        slam.finish(train=False)
        _save_trajectory_and_map(slam, out, stamps)
        log.warning("stopped after %d frames: their %s and %s are in %s/", len(slam.poses),
                    "trajectory.txt", MAP, out)
    except Exception as e:  # the error that stopped the run is the one to report
        log.warning("could not save the frames done so far: %s", e)
