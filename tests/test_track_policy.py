"""The tracking policy's order of references (slam.track_policy): the map first every
`map_every`-th frame (never with 0), the last tracked frame first otherwise, and each next
reference only when the one before failed; a render or view that serves several frames is
prepared once."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from legslam.slam.track_policy import TrackingPolicy
from legslam.slam.trajectory import View


class RecordingTracker:
    """The tracker's interface; aligns to the references named in `works` and records the
    order it was asked in."""

    def __init__(self, works=("map", "frame", "keyframe")):
        self.works, self.asked, self.prepared = set(works), [], []

    def prepare_reference(self, rgb, depth, K, pose):
        # The test's views carry their name in their first pixel; a map render has numbers.
        name = "map" if rgb.dtype != object else str(rgb.flat[0])
        self.prepared.append(name)
        return name

    def track(self, rgb, depth, K, init_pose, reference):
        self.asked.append(reference)
        lost = reference not in self.works
        return SimpleNamespace(lost=lost, pose=init_pose, residual_rms=1.0,
                               reason="lost" if lost else None)


def view(name: str) -> View:
    return View(np.eye(4), np.full((4, 4, 3), name, dtype=object), np.ones((4, 4), np.float32))


def map_render(covered: bool = True):
    """A render of the map that covers the whole view (alpha 1), or none of it."""
    return SimpleNamespace(alpha=np.full((4, 4), float(covered), np.float32),
                           depth=np.ones((4, 4), np.float32), color=np.full((4, 4, 3), 0.5, np.float32))


def track(policy: TrackingPolicy, covered: bool = True, render=None):
    render = map_render(covered) if render is None else render
    return policy.track(np.zeros((4, 4, 3)), np.ones((4, 4), np.float32), np.eye(4),
                        (np.eye(4), render), (view("frame"), view("keyframe")))


def test_the_map_comes_first_every_nth_frame_and_the_last_frame_between():
    tracker = RecordingTracker()
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5, map_every=3)
    firsts = []
    for _ in range(7):
        tracker.asked.clear()
        assert track(policy).state == "ok"
        firsts.append(tracker.asked[0])
    assert firsts == ["frame", "frame", "map", "frame", "frame", "map", "frame"]


def test_the_map_only_after_the_last_frame_fails_when_map_every_is_zero():
    tracker = RecordingTracker(works=("map",))
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5, map_every=0)
    for _ in range(6):
        tracker.asked.clear()
        assert track(policy).state == "ok"
        assert tracker.asked == ["frame", "map"]


def test_every_frame_against_the_map_when_map_every_is_one():
    tracker = RecordingTracker()
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5)
    for _ in range(3):
        tracker.asked.clear()
        track(policy)
        assert tracker.asked == ["map"]


def test_each_reference_is_tried_in_turn_until_one_aligns():
    tracker = RecordingTracker(works=("keyframe",))
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5, map_every=2)
    assert track(policy).state == "ok" and tracker.asked == ["frame", "map", "keyframe"]
    tracker.asked.clear()
    assert track(policy).state == "ok" and tracker.asked == ["map", "frame", "keyframe"]
    tracker.asked.clear()
    # Without a map reference (too little coverage) the frame and the keyframe remain.
    assert track(policy, covered=False).state == "ok" and tracker.asked == ["frame", "keyframe"]
    tracker.works.clear()
    tracker.asked.clear()
    assert track(policy).state == "lost" and tracker.asked == ["map", "frame", "keyframe"]


def test_the_map_render_is_prepared_only_when_tried_and_once():
    tracker = RecordingTracker(works=("frame",))
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5, map_every=0)
    render = map_render()
    t = track(policy, render=render)
    # Its coverage counts, but the last frame aligned: the render was never prepared.
    assert t.state == "ok" and t.coverage == 1.0 and tracker.prepared == ["frame"]
    tracker.works = {"map"}
    tracker.prepared.clear()
    for _ in range(2):  # a mapping thread's render serves several frames
        assert track(policy, render=render).state == "ok"
    assert tracker.prepared == ["frame", "map", "frame"]
    tracker.prepared.clear()
    assert track(policy).state == "ok" and tracker.prepared == ["frame", "map"]  # a new render


def test_a_view_that_serves_several_frames_is_prepared_once():
    tracker = RecordingTracker(works=("frame",))
    policy = TrackingPolicy(tracker, np.eye(3), 0.8, 0.5, map_every=0)
    surface_view = view("frame")  # the fused surface's reference, kept over several frames
    for _ in range(3):
        t = policy.track(np.zeros((4, 4, 3)), np.ones((4, 4), np.float32), np.eye(4),
                         (np.eye(4), map_render()), (surface_view, view("keyframe")))
        assert t.state == "ok"
    assert tracker.prepared == ["frame"]
    track(policy)  # another view (each frame's own): prepared anew
    assert tracker.prepared == ["frame", "frame"]
