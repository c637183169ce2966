"""A live view of a run in rerun (https://rerun.io, `pip install 'legslam[viewer]'`).

Every frame: the input colour and depth under a pinhole camera at the estimated pose, the
trajectory so far (and the ground truth, where the sequence has it), the loops closed (an
edge between the keyframes each joined) and the map's size. At
keyframes (not while a mapping thread owns the map) and at the end, the costlier views: the
Gaussian centres in their colours, the map rendered at the current pose, and its language
features as colour.

The pipeline calls `on_frame` after every SLAM step and `on_finish` once at the end; rerun is
imported here only, so a run without a viewer never loads it.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import numpy as np

from .render import feature_basis, feature_rgb

log = logging.getLogger("legslam")

#: The point cloud shows an evenly spread subset of at most this many Gaussians.
MAX_POINTS = 50_000
_SH_C0 = 0.28209479177387814  # the degree-0 SH basis: colour = 0.5 + C0 * DC coefficient


class ViewerError(RuntimeError):
    """The viewer cannot start: the message says what to install or do instead."""


def _import_rerun():
    try:
        import rerun
    except ImportError as e:
        raise ViewerError("--viewer rerun needs the rerun SDK: pip install 'legslam[viewer]' "
                          f"(or pip install rerun-sdk) ({e})") from None
    return rerun


def _spawn(rr, rec, layout) -> None:
    """Starts the viewer app, found beside this Python (a venv's bin/, even when not on PATH)
    or on PATH."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewerError("no display for the rerun viewer: record with --viewer-save FILE.rrd "
                          "and open the file where there is one (`rerun FILE.rrd`)")
    beside = Path(sys.executable).with_name("rerun")
    try:
        rr.spawn(recording=rec, default_blueprint=layout,
                 executable_path=str(beside) if beside.is_file() else None)
    except RuntimeError as e:
        raise ViewerError(f"could not start the rerun viewer: {e}") from None


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


class RerunViewer:
    """Logs a run to a spawned rerun viewer, or to the file `save` (.rrd; `rerun FILE` opens
    it later)."""

    def __init__(self, save=None):
        self.rr = rr = _import_rerun()
        import rerun.blueprint as rrb

        layout = rrb.Blueprint(rrb.Horizontal(
            rrb.Spatial3DView(name="map", origin="world"),
            rrb.Vertical(
                rrb.Spatial2DView(name="colour", origin="world/camera/image",
                                  contents="$origin/rgb"),
                rrb.Spatial2DView(name="depth", origin="world/camera/image",
                                  contents="$origin/depth"),
                rrb.TimeSeriesView(name="gaussians", origin="stats")),
            rrb.Vertical(rrb.Spatial2DView(name="render", origin="map/render"),
                         rrb.Spatial2DView(name="features", origin="map/features")),
            column_shares=[3, 1, 1]))
        self.rec = rr.RecordingStream("legslam")
        if save is None:
            _spawn(rr, self.rec, layout)
        else:
            try:
                self.rec.save(save, default_blueprint=layout)
            except RuntimeError as e:  # e.g. no such folder
                raise ViewerError(f"cannot record to {save}: {e}") from None
        # legslam's cameras look along +z with y down (OpenCV), and so does its world frame.
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self._gt: list[np.ndarray] = []
        self._gt_anchor = None  # maps ground truth into the run's frame: first poses coincide
        self._basis = None  # fixed once features exist, so their colours stay put
        self._loops_drawn: list = []

    def on_frame(self, index: int, frame, step, slam) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=index)
        if index == 0:
            rec.log("world/camera/image", rr.Pinhole(
                image_from_camera=slam.K, resolution=[slam.width, slam.height]), static=True)
        pose = step.pose
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        rec.log("world/camera/image/rgb", rr.Image(frame.rgb))
        rec.log("world/camera/image/depth", rr.DepthImage(frame.depth, meter=1.0))
        rec.log("world/trajectory", rr.LineStrips3D(
            [np.stack(slam.poses)[:, :3, 3]], colors=[255, 160, 0]))
        if frame.pose is not None:
            if index == 0:
                self._gt_anchor = pose @ np.linalg.inv(frame.pose)
            if self._gt_anchor is not None:
                self._gt.append((self._gt_anchor @ frame.pose)[:3, 3])
                rec.log("world/ground_truth", rr.LineStrips3D([self._gt], colors=[0, 200, 80]))
        rec.log("stats/gaussians", rr.Scalars(slam.num_gaussians))
        self._log_loops(slam)
        if step.keyframe and not slam.mapping_in_thread:  # else the thread owns the map
            self._log_map(slam, pose)

    def on_finish(self, slam) -> None:
        """The map after the final mapping iterations, at the last frame's time; then closes
        the recording (the .rrd file is complete after this)."""
        self._log_map(slam, slam.poses[-1])
        try:
            self.rec.flush()
        except RuntimeError as e:  # the viewer window was closed: the run's outputs still count
            log.warning("viewer: %s", e)
        self.rec.disconnect()

    def _log_loops(self, slam) -> None:
        """Each loop that holds as a line between its two keyframes (at their corrected poses),
        logged again when a loop is added or dropped."""
        loops = slam.loops
        held = [] if loops is None else [(e.old, e.new) for e in loops.held]
        if held == self._loops_drawn:
            return
        self._loops_drawn = held
        centres = np.stack(loops.poses)[:, :3, 3]
        self.rec.log("world/loop_edges", self.rr.LineStrips3D(
            [centres[list(pair)] for pair in held], colors=[230, 40, 230]))

    def _log_map(self, slam, pose) -> None:
        rr, rec = self.rr, self.rec
        m = slam.mapper.export()
        n = len(m["means"])
        keep = np.linspace(0, n - 1, min(n, MAX_POINTS)).astype(np.int64)
        colours = _u8(0.5 + _SH_C0 * m["sh"][keep, 0, :])
        rec.log("world/gaussians", rr.Points3D(m["means"][keep], colors=colours))
        # At tracking resolution (about what the map trains at): a fraction of a full-size render.
        (w, h), features = slam.track_size, slam.pca is not None
        r = slam.render(pose, slam.K_track, w, h, features=features)
        rec.log("map/render", rr.Image(_u8(r["color"])))
        if features:
            if self._basis is None:
                self._basis = feature_basis(r["features"])
            rec.log("map/features", rr.Image(feature_rgb(r["features"], self._basis)))
