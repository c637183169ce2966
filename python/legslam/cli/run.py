"""`legslam run PATH`: SLAM with language features over a sequence in any supported format."""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
from contextlib import contextmanager, nullcontext
from pathlib import Path

from ..datasets.realsense import RealSenseCamera
from ..eval import every_key
from ..pipeline import run as run_pipeline
from ..playback import pacer_for
from ..run_folder import RUN_FILES, write_json
from ..slam import SLAMConfig
from ..viewer import RerunViewer, ViewerError
from .common import UserError, add_sequence_options, at_least, open_sequence, output_dir
from .progress import Progress


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="a sequence folder (TUM, Replica, ScanNet, 7-Scenes, plain folder), a ROS1 "
                                ".bag or ROS2 bag folder, a Stray Scanner export, a Record3D .r3d; or "
                                "`realsense` for a live RealSense camera")
    add_run_options(p)
    add_sequence_options(p)
    p.add_argument("--camera", choices=["realsense"], default=None,
                   help="a live camera (as the path `realsense`); with a RealSense recording (.bag, .db3) "
                        "as the path, the RealSense SDK plays it back (instead of legslam's bag reader)")


def add_run_options(p: argparse.ArgumentParser) -> None:
    """The options of a SLAM run, shared with `legslam demo`."""
    d = SLAMConfig()
    p.add_argument("--out", default=None,
                   help="output folder (default: legslam-out/<name>); it must be empty, or hold a "
                        "previous run and --overwrite be given; never the input's folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files of a previous run in --out (only those: trajectory, "
                        "map, metrics, renders, ...); other files there are left alone")
    p.add_argument("--config", default=None, help="a .toml/.json/.yaml file overriding defaults")
    p.add_argument("--no-features", action="store_true",
                   help="no language features (the encoder, when cached, still serves "
                        "relocalisation and loop closure)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--sync", action="store_true",
                      help="synchronous: every keyframe waits for its mapping iterations (slower; "
                           "the run repeats itself to the bit; config mapping_thread = false)")
    mode.add_argument("--realtime", action="store_true",
                   help="the default unless the config file sets mapping_thread: "
                        "map in a worker thread: the frame rate is the tracker's, the map gets "
                        f"the iterations the spare CPU allows, at {d.realtime_lr_scale:g} times the "
                        f"learning rates ({d.realtime_geometry_lr_scale:g} times for the "
                        "Gaussians' positions and shapes), with no keyframe within "
                        f"{d.realtime_keyframe_min_gap} frames of the last, encoding one keyframe in "
                        f"{d.realtime_feature_every} (language features, places), ray-casting "
                        "the surface it tracks against from each frame a worker thread is free "
                        f"for and fusing one in {d.realtime_surface_every} into it, and at "
                        f"the end trains on for {d.final_time:g} times as long as the frames took "
                        f"and until the map has had {d.realtime_iters_floor:g} of a synchronous run's "
                        "iterations "
                        "(config: mapping_thread, realtime_lr_scale, realtime_geometry_lr_scale, "
                        "realtime_keyframe_min_gap, realtime_feature_every, surface_realtime, "
                        "realtime_surface_every, final_time, realtime_iters_floor)")
    p.add_argument("--pace", type=float, nargs="?", const=1.0, default=None, metavar="SPEED",
                   help="play the recording as its camera delivered it: no frame before its "
                        "timestamp says (SPEED times the recorded speed, default 1), so that "
                        "--realtime maps as it would live; timings.json says how far SLAM fell "
                        "behind (without: frames as fast as SLAM takes them)")
    p.add_argument("--final-iters", type=int, default=None, metavar="N",
                   help="mapping iterations over all keyframes once the frames have ended "
                        f"(default {d.final_iters}, and synchronous runs {d.final_iters_per_frame:g} "
                        "more per frame; more give a sharper map: config final_iters, "
                        "final_iters_per_frame)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--viewer", choices=["rerun"], default=None,
                   help="live view: frames, poses, trajectory, Gaussian centres, renders and "
                        "features in a spawned rerun viewer (pip install 'legslam[viewer]')")
    p.add_argument("--viewer-save", default=None, metavar="FILE.rrd",
                   help="with --viewer rerun: record to this file instead of spawning the "
                        "viewer (open it later with `rerun FILE.rrd`)")


def _viewer(args):
    if args.viewer is None:
        if args.viewer_save:
            raise UserError("--viewer-save needs --viewer rerun")
        return None
    try:
        return RerunViewer(save=args.viewer_save)
    except ViewerError as e:
        raise UserError(str(e)) from e


def run_config(args) -> SLAMConfig:
    """The SLAMConfig the options ask for (checked before any frame is read): real time unless
    --sync, or the config file's mapping_thread, says otherwise."""
    overrides = {"features": False} if args.no_features else {}
    if args.final_iters is not None:
        at_least("--final-iters", args.final_iters, 0)
        overrides["final_iters"] = args.final_iters
    try:
        options = SLAMConfig.read_file(args.config) if args.config else {}
        overrides["mapping_thread"] = (False if args.sync else True if args.realtime
                                       else options.get("mapping_thread", True))
        return SLAMConfig.from_dict({**options, **overrides}, source=args.config or "options")
    except (OSError, ValueError) as e:
        raise UserError(str(e)) from e


def run_output_dir(path, source, overwrite: bool) -> Path:
    """The output folder of a run, checked before any work: never the input's folder or one
    that holds it; empty, or holding a run that --overwrite replaces (its files only)."""
    p = Path(path)
    out, src = p.resolve(), Path(source).resolve()
    if out == src or out in src.parents:
        raise UserError(f"the output folder {p} is (or holds) the input {source}: the run would "
                        "write over its files; give another --out")
    if p.is_dir() and any(p.iterdir()):
        if not overwrite:
            raise UserError(f"the output folder {p} is not empty (a previous run?): give --overwrite "
                            "to replace that run's files, or another --out")
        for name in RUN_FILES:
            old = p / name
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink(missing_ok=True)
    return output_dir(p)


def run_sequence(seq, name: str, args, config: SLAMConfig) -> int:
    """Runs SLAM over `seq` (a Sequence, or a live camera) into --out (default
    legslam-out/NAME) and prints the figures."""
    live = getattr(seq, "live", False)
    try:  # checked before --out is made
        pacer_for(args.pace, live)
    except ValueError as e:
        raise UserError(f"--pace: {e}") from e
    out = run_output_dir(args.out or Path("legslam-out") / name, seq.path, args.overwrite)
    viewer = _viewer(args)
    progress = None if args.quiet else Progress(None if live else len(seq))
    try:
        with stopping_on_interrupt(seq) if live else nullcontext():
            result = run_pipeline(seq, out, config, progress=progress, viewer=viewer, pace=args.pace)
    # The encoder model not in the cache, the first frame or too many in a row unreadable, a
    # config the camera or encoder cannot take, a camera that cannot start.
    except (FileNotFoundError, ValueError, ViewerError) as e:
        raise UserError(str(e)) from e
    m, t = result["metrics"], result["timings"]
    unreadable = f" ({len(m['unreadable_frames'])} unreadable)" if m["unreadable_frames"] else ""
    dropped = f"  dropped {m['dropped_frames']} (not kept up with)" if live else ""
    print(f"frames {m['frames']}{dropped}  keyframes {m['keyframes']}  lost {m['lost_frames']}{unreadable}  "
          f"gaussians {m['gaussians']}  {t['fps']:.2f} fps ({t['fps_live']:.2f} while frames came in)")
    if m["gaussians"] == 0:
        print(f"warning: the map is empty: of {m['frames']} frames, {m['frames_without_depth']} had "
              f"no depth and {m['frames_depth_out_of_range']} depth outside depth_min..depth_max "
              "(check the depth files and their scale)", file=sys.stderr)
    if "ate_rmse_cm" in m:
        print(f"ATE RMSE {m['ate_rmse_cm']:.2f} cm")
    if "ate_note" in m:
        print(f"note: ATE {m['ate_note']}" if "ate_rmse_cm" in m else f"note: {m['ate_note']}")
    n = m["every"]
    e = m[every_key(n)]

    def fmt(v, spec):  # a figure no frame could give (no readable frame, no valid depth) is None
        return "n/a" if v is None else format(v, spec)
    print(f"PSNR {fmt(e['psnr'], '.2f')} dB  SSIM {fmt(e['ssim'], '.3f')}  depth L1 "
          f"{fmt(e['depth_l1_cm'], '.2f')} cm  (map rendered at frames 0, {n}, {2 * n}, ...)")
    if "playback" in t:
        p = t["playback"]
        print(f"played at {p['speed']:g}x the recorded pace: {p['late_frames']} frames came after the "
              f"next was due (a live camera would have dropped them), at most {p['max_lag_s']:.2f} s late")
    print("per-stage mean ms/frame: " + "  ".join(
        f"{k} {t[k]['mean_ms']:.1f}" for k in ("preprocessing", "tracking", "mapping")))
    print(f"outputs in {out}/: trajectory.txt map.ply metrics.json timings.json renders/")
    write_json(out / "summary.json", {"metrics": m, "fps": t["fps"]})
    return 0


@contextmanager
def stopping_on_interrupt(camera):
    """Within: the first Ctrl-C ends a live camera's frames, and the run finishes as a
    sequence's does (final iterations, every output); a second one interrupts."""
    def stop(signum, frame):
        signal.signal(signal.SIGINT, previous)
        print("stopping: the frames taken are being finished (Ctrl-C again to stop now)", file=sys.stderr)
        camera.stop()

    previous = signal.signal(signal.SIGINT, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _camera(args):
    """The live camera (or the RealSense SDK's playback) the arguments ask for, or None."""
    path = Path(args.path)
    if args.camera is None and not (args.path == "realsense" and not path.exists()):
        return None
    if args.path != "realsense" and not (path.is_file() and path.suffix in (".bag", ".db3")):
        raise UserError(f"--camera realsense reads a live camera (path `realsense`) or a RealSense recording "
                        f"(.bag, .db3), not {args.path}")
    ignored = [o for o, v in (("--stride", args.stride != 1), ("--downscale", args.downscale != 1),
                              ("--intrinsics", args.intrinsics), ("--rgb-topic", args.rgb_topic),
                              ("--depth-topic", args.depth_topic), ("--min-confidence", args.min_confidence)) if v]
    if ignored:
        raise UserError(f"{', '.join(ignored)} cannot be used with a RealSense camera (the device gives its own)")
    at_least("--max-frames", args.max_frames)
    return RealSenseCamera(None if args.path == "realsense" else path, max_frames=args.max_frames)


def run(args) -> int:
    camera = _camera(args)
    if camera is not None:
        if args.sync:
            raise UserError("--sync cannot be used with a live camera: it does not wait for the map")
        args.realtime = True
        return run_sequence(camera, camera.name, args, run_config(args))
    config = run_config(args)
    seq = open_sequence(args)
    return run_sequence(seq, Path(args.path).resolve().name, args, config)
