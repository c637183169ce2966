"""A recording played as a live camera would deliver it: each frame handed over no earlier than
its timestamp says, at `speed` times the recorded speed. A run over a recording otherwise takes
its frames as fast as SLAM can; paced, the real-time mode's mapping thread gets the CPU time a
live camera's gaps between frames leave it, as it would live."""

from __future__ import annotations

import logging
import math
import numbers
import time
from typing import Optional

__all__ = ["Pacer", "pacer_for"]

log = logging.getLogger("legslam")

#: A wait longer than this (seconds) is a gap in the recording, said in a warning.
GAP_S = 5.0


def pacer_for(pace: Optional[float], live: bool) -> Optional["Pacer"]:
    """The Pacer for speed `pace` (None: no pacing). ValueError for a bad speed, and for a
    live source, which delivers frames at its own pace."""
    if pace is None:
        return None
    if live:
        raise ValueError("pacing plays a recording read by legslam at its camera's pace; a camera "
                         "(or the RealSense SDK's playback) delivers frames at its own")
    return Pacer(pace)


class Pacer:
    """Waits until each frame is due. Frame times count from the first frame's timestamp
    (seconds; the first finite one) and the moment it was handed over; a timestamp that is not a
    finite number, or earlier than one before it, is due at once. A gap in the timestamps is
    waited out, as the camera did, with a warning when it is longer than `GAP_S`. SLAM running
    behind is not made to drop frames (a live camera would): each frame waits its turn, and
    `report` says how many were handed over after the next one was already due."""

    def __init__(self, speed: float):
        if not (isinstance(speed, numbers.Real) and not isinstance(speed, bool)
                and math.isfinite(speed) and speed > 0):
            raise ValueError(f"the playback speed must be a number > 0 (1: the recording's own "
                             f"pace), got {speed!r}")
        self.speed = float(speed)
        self._origin = None  # (clock, timestamp) of the first frame with a finite timestamp
        self._due: list[float] = []
        self._handed: list[float] = []

    def wait(self, timestamp: float) -> None:
        """Returns when the frame stamped `timestamp` is due."""
        now = time.perf_counter()
        finite = math.isfinite(timestamp)
        if self._origin is None and finite:
            self._origin = (now, timestamp)
        due = now
        if finite:
            clock, first = self._origin
            due = clock + (timestamp - first) / self.speed
            if self._due:  # never before the frame before it
                due = max(due, self._due[-1])
        if due - now > GAP_S:
            log.warning("the recording's timestamps jump to %.3f s: waiting %.1f s for that frame, "
                        "as its camera delivered it", timestamp, due - now)
        if due > now:
            time.sleep(due - now)
        self._due.append(due)
        self._handed.append(time.perf_counter())

    def report(self) -> dict:
        """The speed, how many frames were handed over when the next was already due (those a
        live camera would have dropped), and the latest a frame came (seconds after its time)."""
        handed, due = self._handed, self._due
        late = sum(h > after > d for h, d, after in zip(handed, due, due[1:]))
        lag = max((h - d for h, d in zip(handed, due)), default=0.0)
        return {"speed": self.speed, "late_frames": int(late), "max_lag_s": float(lag)}
