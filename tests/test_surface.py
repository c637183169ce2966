"""The fused surface a frame is tracked against (legslam.slam.surface): on the built-in scene,
fusing noisy views brings the reference depth closer to the truth than one view's; every frame
is ray-cast from its pose, every n-th fused first; a pose-graph correction leaves the surface
where the camera sees it; in the background (real time) a worker fuses what the tracker would,
never queues a frame behind a busy worker, raises a failed fusion to the tracker, and a
correction during one reaches its reference; the SLAM option turns it on and off. The engine's
tests (crates/legslam-core/tests/track_tsdf.rs) check the volume itself against analytic
scenes."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from legslam import _core
from legslam.datasets import open as open_dataset
from legslam.slam import SLAM, SLAMConfig
from legslam.slam.surface import HOLE_CELL, Surface
from legslam.slam.trajectory import View


def views(scene, noise: float, seed: int = 0):
    """The scene's frames as views at their true poses, depth with Gaussian noise (m)."""
    rng = np.random.default_rng(seed)
    seq = open_dataset(scene)
    out = []
    for i in range(len(seq)):
        f = seq[i]
        d = np.where(f.depth > 0, f.depth + noise * rng.standard_normal(f.depth.shape), 0)
        out.append((View(f.pose, f.rgb, d.astype(np.float32)), f.depth, f.K))
    return out


def fused(surface: Surface, frame: int, view: View) -> View:
    """`view` added to `surface` as frame `frame`: the reference it makes."""
    surface.add(frame, view)
    assert surface.reference[0] == frame
    return surface.reference[1]


def median_error(depth, truth):
    both = (depth > 0) & (truth > 0)
    assert both.mean() > 0.5
    return float(np.median(np.abs(depth[both] - truth[both])))


def test_fused_views_give_depth_nearer_the_truth_than_one_view(small_synthetic):
    frames = views(small_synthetic, noise=0.01)
    surface = Surface(0.01, 0.04, (0.1, 10.0), frames[0][2])
    for i, (view, _, _) in enumerate(frames[:-1]):
        surface.add(i, view)
    last, truth, _ = frames[-1]
    ref = fused(surface, len(frames) - 1, last)
    assert ref.pose is last.pose and ref.rgb is last.rgb
    one, many = median_error(last.depth, truth), median_error(ref.depth, truth)
    assert many < 0.5 * one, f"fused {many * 100:.2f} cm against one view's {one * 100:.2f} cm"


def test_a_correction_leaves_the_surface_where_the_camera_sees_it(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    K = frames[0][2]
    plain, corrected, moved = (Surface(0.01, 0.04, (0.1, 10.0), K) for _ in range(3))
    for i, (view, _, _) in enumerate(frames[:6]):
        for surface in (plain, corrected, moved):
            surface.add(i, view)
    # The pose graph moves the world by C: poses after it are C @ pose.
    c, s = np.cos(0.1), np.sin(0.1)
    C = np.array([[c, -s, 0, 0.2], [s, c, 0, -0.1], [0, 0, 1, 0.05], [0, 0, 0, 1.0]])
    poses = [C @ v.pose for v, _, _ in frames[:6]]
    corrected.correct(C, poses)
    # The reference (frame 5) follows its frame.
    assert corrected.reference[0] == 5 and np.allclose(corrected.reference[1].pose, poses[5])
    view = frames[6][0]
    expected = fused(plain, 6, view).depth
    got = fused(corrected, 6, View(C @ view.pose, view.rgb, view.depth)).depth
    assert np.abs(got - expected).max() < 1e-3
    # Without the correction the moved pose would see another surface.
    stale = fused(moved, 6, View(C @ view.pose, view.rgb, view.depth)).depth
    assert np.abs(stale - expected).max() > 0.01


def test_every_nth_frame_is_fused_and_every_frame_is_ray_cast_from_its_pose(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    K = frames[0][2]
    surface = Surface(0.01, 0.04, (0.1, 10.0), K, every=3)
    gate = surface._core = Gated(surface._core)
    gate.open.set()
    # What the volume holds: the frames fused so far, in a volume of its own.
    volume = _core.TsdfCore(0.01, 0.04, 64.0, 0.1, 10.0)
    h, w = frames[0][0].depth.shape
    for i, (view, _, _) in enumerate(frames[:12]):
        surface.add(i, view, now=i == 8)
        # Frames 0, 3, 6 fused; 8 relocalised (at once), and the count starts again from it.
        if i in (0, 3, 6, 8, 11):
            volume.integrate(view.depth, K, view.pose)
        cast = volume.raycast(K, w, h, view.pose, view.depth, HOLE_CELL)
        ref = surface.reference
        assert ref[0] == i and ref[1].rgb is view.rgb and ref[1].pose is view.pose
        assert np.array_equal(ref[1].depth, np.where(cast > 0, cast, view.depth))
    assert gate.fused == 5
    with pytest.raises(ValueError, match="every"):
        Surface(0.01, 0.04, (0.1, 10.0), frames[0][2], every=0)


def settled(surface: Surface, frame: int) -> View:
    """The reference of `frame` once the background worker has made it."""
    deadline = time.monotonic() + 30
    while surface.reference is None or surface.reference[0] != frame:
        assert time.monotonic() < deadline, f"frame {frame} was not ray-cast in 30 s"
        time.sleep(0.001)
    return surface.reference[1]


class Gated:
    """A volume whose fusions wait until `open` is set; counts them and its ray-casts."""

    def __init__(self, core):
        self.core, self.open, self.fused, self.cast = core, threading.Event(), 0, 0

    def integrate(self, *args):
        assert self.open.wait(30), "the test never opened the gate"
        self.fused += 1
        return self.core.integrate(*args)

    def raycast(self, *args):
        self.cast += 1
        return self.core.raycast(*args)

    @property
    def memory_bytes(self):
        return self.core.memory_bytes


def test_a_background_surface_fuses_what_the_tracker_would(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    K = frames[0][2]
    inline = Surface(0.01, 0.04, (0.1, 10.0), K)
    background = Surface(0.01, 0.04, (0.1, 10.0), K, background=True, threads=1)
    for i, (view, _, _) in enumerate(frames[:5]):
        expected = fused(inline, i, view)
        background.add(i, view)
        got = settled(background, i)
        assert got.rgb is view.rgb and got.pose is view.pose
        assert np.array_equal(got.depth, expected.depth)
    background.close()
    assert background.memory_bytes == inline.memory_bytes


def test_a_frame_that_comes_while_the_worker_is_busy_is_not_queued(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    surface = Surface(0.01, 0.04, (0.1, 10.0), frames[0][2], every=2, background=True)
    gate = surface._core = Gated(surface._core)
    surface.add(0, frames[0][0])
    # Frames 1-3 come while frame 0's fusion holds the worker: passed over.
    for i in (1, 2, 3):
        surface.add(i, frames[i][0])
        assert surface.reference is None
    gate.open.set()
    settled(surface, 0)
    # The next frame is due a fusion at once (frame 2's was); then every 2nd, and the frames
    # between are ray-cast only.
    for i in (4, 5, 6):
        surface.add(i, frames[i][0])
        settled(surface, i)
    assert (gate.fused, gate.cast) == (3, 4)
    surface.close()


def test_a_correction_during_a_fusion_reaches_its_reference(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    K = frames[0][2]
    surface, plain = (Surface(0.01, 0.04, (0.1, 10.0), K, background=b) for b in (True, False))
    gate = surface._core = Gated(surface._core)
    gate.open.set()
    for i, (view, _, _) in enumerate(frames[:5]):
        surface.add(i, view)
        plain.add(i, view)
        settled(surface, i)
    gate.open.clear()
    surface.add(5, frames[5][0])
    plain.add(5, frames[5][0])
    c, s = np.cos(0.1), np.sin(0.1)
    C = np.array([[c, -s, 0, 0.2], [s, c, 0, -0.1], [0, 0, 1, 0.05], [0, 0, 0, 1.0]])
    poses = [C @ v.pose for v, _, _ in frames[:6]]
    surface.correct(C, poses)
    # Until frame 5 is fused the reference is frame 4's, moved with it.
    assert surface.reference[0] == 4 and np.allclose(surface.reference[1].pose, poses[4])
    gate.open.set()
    ref = settled(surface, 5)
    assert np.allclose(ref.pose, poses[5])
    assert np.array_equal(ref.depth, plain.reference[1].depth)
    # The next frame, in the corrected world, sees what it saw before the correction.
    view = frames[6][0]
    surface.add(6, View(C @ view.pose, view.rgb, view.depth))
    assert np.abs(settled(surface, 6).depth - fused(plain, 6, view).depth).max() < 1e-3
    surface.close()


def test_a_failed_fusion_in_the_background_is_raised_to_the_tracker(small_synthetic):
    frames = views(small_synthetic, noise=0.005)
    surface = Surface(0.01, 0.04, (0.1, 10.0), frames[0][2], background=True)
    view = frames[0][0]
    surface.add(0, View(np.full((4, 4), np.nan), view.rgb, view.depth))
    with pytest.raises(ValueError, match="pose"):
        settled(surface, 0)
    # The worker goes on with the next frame, and the failed one left the volume as it was.
    surface.add(1, frames[1][0])
    fresh = Surface(0.01, 0.04, (0.1, 10.0), frames[0][2])
    assert np.array_equal(settled(surface, 1).depth, fused(fresh, 1, frames[1][0]).depth)
    surface.close()


def test_real_time_fuses_in_the_background(small_synthetic):
    seq = open_dataset(small_synthetic)
    f = seq[0]
    slam = SLAM(SLAMConfig(features=False, relocalise=False, loop_closure=False, mapping_thread=True,
                           realtime_surface_every=1, final_time=0.0),
                f.K, f.rgb.shape[1], f.rgb.shape[0])
    for i in range(4):
        slam.step(seq[i].rgb, seq[i].depth)
    slam.finish(train=False)
    assert slam.surface.reference is not None
    assert slam.trajectory_events()["surface_memory_mb"] > 0
    assert set(slam.states[1:]) == {"ok"}


def test_the_slam_option_turns_the_surface_on_and_off(small_synthetic):
    seq = open_dataset(small_synthetic)
    f = seq[0]
    base = dict(features=False, relocalise=False, loop_closure=False)
    on = SLAM(SLAMConfig(**base), f.K, f.rgb.shape[1], f.rgb.shape[0])
    off = SLAM(SLAMConfig(surface_voxel=0, **base), f.K, f.rgb.shape[1], f.rgb.shape[0])
    assert on.surface is not None and off.surface is None
    realtime = SLAM(SLAMConfig(mapping_thread=True, surface_realtime=False, **base), f.K,
                    f.rgb.shape[1], f.rgb.shape[0])
    assert realtime.surface is None
    # In real time it fuses every realtime_surface_every-th frame; synchronous runs every
    # surface_every-th.
    cadence = dict(surface_every=2, realtime_surface_every=4, **base)
    timed = SLAM(SLAMConfig(mapping_thread=True, **cadence), f.K, f.rgb.shape[1], f.rgb.shape[0])
    synchronous = SLAM(SLAMConfig(**cadence), f.K, f.rgb.shape[1], f.rgb.shape[0])
    assert (timed.surface.every, synchronous.surface.every) == (4, 2)
    for slam in (realtime, timed, synchronous):
        slam.finish(train=False)
    for i in range(3):
        on.step(seq[i].rgb, seq[i].depth)
    assert on.surface.memory_bytes > 0
    assert on.trajectory_events()["surface_memory_mb"] > 0
    assert "surface_memory_mb" not in off.trajectory_events()


def test_a_zero_minimum_depth_fuses_every_positive_depth(small_synthetic):
    seq = open_dataset(small_synthetic)
    f = seq[0]
    slam = SLAM(SLAMConfig(features=False, relocalise=False, loop_closure=False,
                           mapper={"depth_min": 0.0}), f.K, f.rgb.shape[1], f.rgb.shape[0])
    for i in range(2):
        slam.step(seq[i].rgb, seq[i].depth)
    assert slam.surface.memory_bytes > 0


@pytest.mark.parametrize("options, message", [
    ({"surface_voxel": -0.01}, "surface_voxel"),
    ({"surface_voxel": 0.05, "surface_truncation": 0.01}, "truncation"),
    ({"surface_every": 0}, "surface_every"),
    ({"realtime_surface_every": -1}, "realtime_surface_every"),
])
def test_a_bad_surface_option_names_itself(small_synthetic, options, message):
    f = open_dataset(small_synthetic)[0]
    with pytest.raises(ValueError, match=message):
        SLAM(SLAMConfig(features=False, **options), f.K, f.rgb.shape[1], f.rgb.shape[0])


def test_the_volume_refuses_bad_input():
    tsdf = _core.TsdfCore(0.01, 0.04, 64.0, 0.1, 10.0)
    K = np.array([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="depth"):
        tsdf.integrate(np.ones((24, 32), np.float64), K, np.eye(4))
    with pytest.raises(ValueError, match="pose"):
        tsdf.integrate(np.ones((24, 32), np.float32), K, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="near"):
        tsdf.raycast(K, 32, 24, np.eye(4), np.ones((24, 31), np.float32))
    with pytest.raises(ValueError, match="voxel"):
        _core.TsdfCore(0.0, 0.04, 64.0, 0.1, 10.0)
