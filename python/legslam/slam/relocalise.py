"""Relocalisation: a lost frame (the camera jumped beyond the tracker's basin, or was
covered) is placed in the map by recognising a keyframe's place (`PlaceIndex`); the
trajectory then resumes in the map's frame. Lost frames are never mapped meanwhile (the SLAM
loop maps only tracked frames), so a loss cannot damage the map."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .place_recognition import Place, PlaceIndex, Recognised
from .trajectory import View

__all__ = ["Relocaliser", "Relocalisation"]

log = logging.getLogger("legslam")


@dataclass(frozen=True)
class Relocalisation:
    """A frame placed again after `lost` frames, against keyframe `keyframe` (a record for
    metrics.json)."""

    frame: int
    keyframe: int
    lost: int
    similarity: float
    inliers: int
    inlier_ratio: float
    ms: float

    def as_dict(self) -> dict:
        return {"frame": self.frame, "keyframe": self.keyframe, "lost_frames": self.lost,
                "similarity": round(self.similarity, 4), "keypoint_inliers": self.inliers,
                "inlier_ratio": round(self.inlier_ratio, 4), "ms": round(self.ms, 1)}


class Relocaliser:
    """Places lost frames: the frame's patch tokens from `encoder` (in the calling thread,
    only while lost), then `places.recognise`. `events` lists the relocalisations."""

    def __init__(self, places: PlaceIndex, encoder, K_track: np.ndarray):
        self.places, self.encoder, self.K = places, encoder, K_track
        self.events: list[Relocalisation] = []
        self._lost_since: Optional[int] = None

    def lost(self, frame: int, rgb: np.ndarray, small: View) -> Optional[Recognised]:
        """Frame `frame` (full-size `rgb`, `small` at the tracking size) was lost: its pose in
        the map, or None while no place verifies."""
        if self._lost_since is None:
            self._lost_since = frame
        if not len(self.places):
            return None
        t0 = time.perf_counter()
        query = Place.of(-1, self.encoder.encode(rgb), small, self.K)
        found = self.places.recognise(query)
        if found is None:
            return None
        event = Relocalisation(frame, found.keyframe, frame - self._lost_since, found.similarity,
                               found.inliers, found.inlier_ratio, 1e3 * (time.perf_counter() - t0))
        self.events.append(event)
        self._lost_since = None
        log.info("frame %d relocalised against keyframe %d after %d lost frames (similarity %.3f, "
                 "%d keypoint inliers, inlier ratio %.2f)", frame, found.keyframe, event.lost,
                 found.similarity, found.inliers, found.inlier_ratio)
        return found

    def tracked(self) -> None:
        """A frame was tracked: a loss, if any, is over."""
        self._lost_since = None
