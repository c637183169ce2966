"""Every frame's pose and state, and the views tracking can go back to.

Each frame is anchored to the keyframe it was placed after (its pose relative to that
keyframe's), so that keyframe poses refined by mapping carry their frames along.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["View", "KeyframeView", "Trajectory"]


@dataclass(frozen=True)
class View:
    """A frame at the tracking size with its pose: a reference tracking can fall back to."""

    pose: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class KeyframeView(View):
    """A keyframe's view, and the frame it was made from."""

    frame: int = 0


class Trajectory:
    """The poses and states ("init", "ok", "relocalised" or "lost") of the frames so far."""

    def __init__(self):
        self.poses: list[np.ndarray] = []
        self.states: list[str] = []
        #: Per frame: (the keyframe it was placed after, its pose relative to that keyframe's).
        self._anchors: list[tuple[int, np.ndarray]] = []

    def __len__(self) -> int:
        return len(self.poses)

    def record(self, pose: np.ndarray, state: str, keyframe: int, keyframe_pose: np.ndarray) -> None:
        """A frame's pose and state, anchored to keyframe number `keyframe` at `keyframe_pose`."""
        self._anchors.append((keyframe, np.linalg.inv(keyframe_pose) @ pose))
        self.poses.append(pose)
        self.states.append(state)

    def predict(self, last_tracked: np.ndarray) -> np.ndarray:
        """Constant velocity from the last two frames; after a lost or relocalised frame, the
        last tracked pose (an extrapolated velocity would carry the camera away for good)."""
        if len(self.poses) < 2 or not {"lost", "relocalised"}.isdisjoint(self.states[-2:]):
            return last_tracked
        a, b = self.poses[-2], self.poses[-1]
        return b @ np.linalg.inv(a) @ b

    def follow(self, keyframe_poses: np.ndarray) -> None:
        """Moves every frame with its keyframe, to the keyframes' (refined) poses."""
        self.poses = [keyframe_poses[k] @ rel if 0 <= k < len(keyframe_poses) else p
                      for (k, rel), p in zip(self._anchors, self.poses)]

    def keyframe_of(self, frame: int) -> int:
        """The keyframe frame number `frame` was placed after (-1 before the first)."""
        return self._anchors[frame][0]
