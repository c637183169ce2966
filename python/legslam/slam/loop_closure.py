"""Loop closure: a pose graph of keyframes (`PoseGraph`), with an odometry edge from each
keyframe to the one it was tracked after, a loop edge wherever a new keyframe recognises
the place of an old one (outside the recent `loop_min_gap` keyframes; verified as
relocalisation is), and covisibility edges to the older keyframes that see the same surfaces
(`Covisibility`). The optimised graph gives each keyframe a correction; the SLAM loop moves
the map (each Gaussian with the keyframe that made it) and every frame with it.

Odometry edges carry the error odometry really makes: a standard deviation that grows with
the distance moved and the angle turned (`odometry_sigma_*`), never the near-certainty that
would make a true loop look like an outlier to the solver's robust kernel.

A loop edge kept when it was closed can still be dropped by a later optimisation, when the
edges added since contradict it: its record then says at which frame (`dropped_at_frame`),
and the poses go where the remaining edges put them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from .covisibility import Covisible
from .keyframes import rotation_deg
from .place_recognition import PlaceIndex, Recognised
from .pose_graph import PoseGraph, information, relative

__all__ = ["LoopClosure", "LoopClosed"]

log = logging.getLogger("legslam")


@dataclass(frozen=True)
class LoopClosed:
    """A loop edge between keyframes `new` and `old` kept by the optimisation, and the largest
    keyframe correction it made (a record for metrics.json); `dropped_at_frame`, the frame at
    which a later optimisation dropped it (None while it holds)."""

    frame: int
    new: int
    old: int
    similarity: float
    inlier_ratio: float
    correction_cm: float
    correction_deg: float
    ms: float
    dropped_at_frame: Optional[int] = None

    def as_dict(self) -> dict:
        return {"frame": self.frame, "keyframes": [self.old, self.new],
                "similarity": round(self.similarity, 4), "inlier_ratio": round(self.inlier_ratio, 4),
                "correction_cm": round(self.correction_cm, 3),
                "correction_deg": round(self.correction_deg, 3), "ms": round(self.ms, 1),
                "dropped_at_frame": self.dropped_at_frame}


class LoopClosure:
    """The keyframe pose graph and loop detection. `config`: the SLAMConfig (loop_* and
    odometry_sigma_* options); `places`: the keyframes' places (None: no loops are detected,
    the graph takes covisibility edges only)."""

    def __init__(self, config, places: Optional[PlaceIndex]):
        self.config, self.places = config, places
        self.graph = PoseGraph()
        #: Loops closed, and loop edges the optimisation rejected (as logged).
        self.events: list[LoopClosed] = []
        self.rejected: list[dict] = []
        #: Covisibility edges the optimisation rejected (as logged).
        self.rejected_covisible: list[dict] = []
        #: Per keyframe, the frame it was made from.
        self._frames: list[int] = []

    @property
    def held(self) -> list[LoopClosed]:
        """The loops closed that no later optimisation dropped."""
        return [e for e in self.events if e.dropped_at_frame is None]

    @property
    def poses(self) -> list[np.ndarray]:
        """Keyframe poses, as the graph's edges so far place them."""
        return self.graph.poses

    def add_keyframe(self, frame: int, pose: np.ndarray, after: Optional[int]) -> None:
        """The next keyframe (made from `frame`), tracked after keyframe `after` (the previous
        one, or the one a relocalisation placed it against; None for the first)."""
        k = self.graph.add_node(pose, fixed=not self.graph.poses)
        self._frames.append(frame)
        if after is not None:
            measured = relative(self.graph.poses[after], pose)
            self.graph.add_edge(after, k, measured, self._odometry_information(measured))

    def _odometry_information(self, rel: np.ndarray) -> np.ndarray:
        c = self.config
        moved = float(np.linalg.norm(rel[:3, 3]))
        turned = np.radians(rotation_deg(np.eye(4), rel))
        return information(c.odometry_sigma_translation * max(moved, 0.1),
                           c.odometry_sigma_rotation * max(turned, np.radians(5.0)))

    def detect(self, keyframe: int) -> Optional[Recognised]:
        """A verified loop from `keyframe` (its place known) to an old keyframe, or None."""
        if self.places is None:
            return None
        old = [k for k in self.places.places if k <= keyframe - self.config.loop_min_gap]
        if not old or keyframe not in self.places.places:
            return None
        return self.places.recognise(self.places.places[keyframe], among=old)

    def close(self, keyframe: int, found: Recognised, ms: float) -> Optional[np.ndarray]:
        """Adds the loop edge `found` (keyframe's pose as recognised against `found.keyframe`)
        and optimises. Returns each keyframe's correction (n x 4 x 4, world to world), or None
        when the edge was rejected (then dropped and logged)."""
        t0 = time.perf_counter()
        old = found.keyframe
        measured = relative(self.graph.poses[old], found.pose)
        edge = self.graph.add_edge(old, keyframe, measured, self._loop_information(), kind="loop")
        before, rejected = self._optimise()
        ms += 1e3 * (time.perf_counter() - t0)
        if edge in rejected:
            self.graph.poses = list(before)  # the other edges held them there
            return None
        corrections, shift_cm, turn_deg = self._corrections(before)
        event = LoopClosed(self._frames[keyframe], keyframe, old, found.similarity,
                           found.inlier_ratio, shift_cm, turn_deg, ms)
        self.events.append(event)
        log.info("loop closed: keyframe %d (frame %d) with keyframe %d; keyframes moved up to %.2f cm "
                 "and %.2f deg (%.0f ms)", keyframe, event.frame, old, event.correction_cm,
                 event.correction_deg, ms)
        return corrections

    def add_covisible(self, found: list[Covisible]) -> Optional[np.ndarray]:
        """Adds the covisibility edges `found` and optimises. Returns each keyframe's correction
        (n x 4 x 4, world to world), or None when there was no edge to add."""
        if not found:
            return None
        for c in found:
            self.graph.add_edge(c.new, c.old, c.measurement, self._loop_information(), kind="covisibility")
        before, _ = self._optimise()
        return self._corrections(before)[0]

    @property
    def covisible(self) -> int:
        """The covisibility edges in the graph (those rejected so far are not)."""
        return sum(e.kind == "covisibility" for e in self.graph.edges)

    def _loop_information(self) -> np.ndarray:
        c = self.config
        return information(c.loop_sigma_translation, np.radians(c.loop_sigma_rotation))

    def _optimise(self) -> tuple[np.ndarray, set]:
        """Optimises the graph; returns the poses before, and the indices (among the edges as
        they were) of the edges it rejected, which are recorded by kind."""
        before = np.stack(self.graph.poses)
        edges = list(self.graph.edges)
        result = self.graph.optimize()
        now = self._frames[-1] if self._frames else None
        for k in result.rejected:  # logged by the graph
            e = edges[k]
            record = {"frame": self._frames[max(e.i, e.j)], "keyframes": sorted([e.i, e.j]),
                      "chi2": round(float(result.chi2[k]), 2)}
            if e.kind != "loop":
                self.rejected_covisible.append(record)
                continue
            self.rejected.append({**record, "dropped_at_frame": now})
            self._drop(e.i, e.j, now)
        return before, set(result.rejected)

    def _drop(self, old: int, new: int, frame: Optional[int]) -> None:
        """Marks the loop closed between `old` and `new`, if it was, as dropped at `frame`."""
        for n, ev in enumerate(self.events):
            if (ev.old, ev.new) == (old, new) and ev.dropped_at_frame is None:
                self.events[n] = replace(ev, dropped_at_frame=frame)
                log.warning("the loop closed at frame %d (keyframes %d and %d) was dropped at frame "
                            "%s: the edges added since contradict it", ev.frame, old, new, frame)

    def _corrections(self, before: np.ndarray) -> tuple[np.ndarray, float, float]:
        """Each keyframe's correction from `before` to the graph's poses (world to world), and
        the largest shift (cm) and turn (degrees) among them."""
        after = np.stack(self.graph.poses)
        shift = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
        turn = [rotation_deg(a, b) for a, b in zip(before, after)]
        return after @ np.linalg.inv(before), 100 * float(shift.max()), float(max(turn))
