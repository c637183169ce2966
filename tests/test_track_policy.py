"""The tracking policy's order of references (slam.track_policy): the map first every
`map_every`-th frame (never with 0), the last tracked frame first otherwise, and each next
reference only when the one before failed."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from legslam.slam.track_policy import TrackingPolicy
from legslam.slam.trajectory import View


class RecordingTracker:
    """The tracker's interface; aligns to the references named in `works` and records the
    order it was asked in."""

    def __init__(self, works=("map", "frame", "keyframe")):
        self.works, self.asked = set(works), []

    def prepare_reference(self, rgb, depth, K, pose):
        return str(rgb.flat[0])  # the test's views carry their name in their first pixel

    def track(self, rgb, depth, K, init_pose, reference):
        self.asked.append(reference)
        lost = reference not in self.works
        return SimpleNamespace(lost=lost, pose=init_pose, residual_rms=1.0,
                               reason="lost" if lost else None)


def view(name: str) -> View:
    return View(np.eye(4), np.full((4, 4, 3), name, dtype=object), np.ones((4, 4), np.float32))


def track(policy: TrackingPolicy, map_reference="map"):
    policy._map_reference = lambda pose, render: (np.ones((4, 4), bool), map_reference)
    return policy.track(np.zeros((4, 4, 3)), np.ones((4, 4), np.float32), np.eye(4),
                        (np.eye(4), object()), (view("frame"), view("keyframe")))


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
    assert track(policy, map_reference=None).state == "ok" and tracker.asked == ["frame", "keyframe"]
    tracker.works.clear()
    tracker.asked.clear()
    assert track(policy).state == "lost" and tracker.asked == ["map", "frame", "keyframe"]
