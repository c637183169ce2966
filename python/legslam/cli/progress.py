"""Progress of a run on the terminal: one self-overwriting status line on stderr (plain lines,
every few seconds, when stderr is not a terminal)."""

from __future__ import annotations

import sys
import time
from typing import Optional

__all__ = ["Progress"]


class Progress:
    """What `legslam.pipeline.run` reports, shown: every frame (`frame`) and the final mapping
    iterations (`final_iterations`)."""

    def __init__(self, total: int | None):
        """total: the frames to come (None: not known, a live camera's)."""
        self.total = total
        self.tty = sys.stderr.isatty()
        self.start = time.perf_counter()
        self._last = 0.0

    def frame(self, i: int, text: str) -> None:
        fps = (i + 1) / max(time.perf_counter() - self.start, 1e-9)
        of = "" if self.total is None else f"/{self.total}"
        self._show(f"frame {i + 1}{of}  {fps:5.2f} fps  {text}", i + 1 == self.total)

    def final_iterations(self, done: int, total: Optional[int]) -> None:
        """The mapping iterations after the last frame (minutes with a large --final-iters);
        total None while a real-time run trains on for as long as `final_time` allows."""
        of = "" if total is None else f"/{total}"
        self._show(f"final mapping iterations {done}{of}", done == total)

    def _show(self, line: str, last: bool) -> None:
        now = time.perf_counter()
        if not last and now - self._last < (0.2 if self.tty else 5.0):
            return
        self._last = now
        print(("\r" + line + "\x1b[K") if self.tty else line, end="\n" if last or not self.tty else "",
              file=sys.stderr, flush=True)
