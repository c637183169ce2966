"""Mapping in a worker thread, so that tracking alone sets the frame rate.

The tracker (main thread) queues keyframes and feature grids; the worker applies them, trains
the map in small batches on whatever keyframes it has and, after each batch, renders the map at
the latest tracked pose as the tracker's next reference. While the worker runs, only it touches
the mapper; the engine releases the GIL, so both threads compute at once.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Optional

import numpy as np


class MappingThread:
    def __init__(self, mapper, K_track: list, track_size: tuple, batch: int = 2):
        self._mapper = mapper
        self._K_track, self._track_size = K_track, track_size
        self._batch = batch
        self._commands: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._reference: Optional[tuple] = None  # (pose, render dict)
        self._reference_pose: Optional[np.ndarray] = None
        self._first_id = mapper.num_keyframes
        self._submitted = 0
        self._applied = 0
        self._num_gaussians = mapper.num_gaussians
        self._iterations_since_keyframe = 0
        self._error: Optional[BaseException] = None
        self._stopping = threading.Event()
        #: Per-batch mapper.train() reports, and seconds spent on tracking references.
        self.stats: list[dict] = []
        self.reference_s = 0.0
        self._thread = threading.Thread(target=self._run, name="legslam-mapping", daemon=True)
        self._thread.start()

    # --- called by the tracker ---------------------------------------------------------------

    def add_keyframe(self, rgb: np.ndarray, depth: np.ndarray, K: list, pose: np.ndarray) -> tuple:
        """Queues a keyframe; returns (the id the mapper will give it, None: how many Gaussians
        it adds is known only once the worker has applied it)."""
        self._check()
        kf_id = self._first_id + self._submitted
        self._submitted += 1
        self._commands.put(("add_keyframe", (rgb, depth, K, pose)))
        return kf_id, None

    def set_features(self, kf_id: int, grid: np.ndarray) -> None:
        self._check()
        self._commands.put(("set_features", (kf_id, grid)))

    def track_at(self, pose: np.ndarray) -> None:
        """The pose the next reference is rendered at (the latest tracked one)."""
        self._reference_pose = pose

    def reference(self) -> Optional[tuple]:
        """(pose, render at the tracking size) of the latest batch, or None before the first."""
        self._check()
        with self._lock:
            return self._reference

    @property
    def pending(self) -> bool:
        """Whether queued keyframes have not reached the map yet."""
        return self._applied < self._submitted

    def trained(self, iterations: int) -> bool:
        """Whether every queued keyframe is in the map and the latest has had this many
        iterations since: the mapper keeps up."""
        return not self.pending and self._iterations_since_keyframe >= iterations

    @property
    def num_gaussians(self) -> int:
        return self._num_gaussians

    def stop(self) -> None:
        """Applies what is queued, stops the worker and hands the mapper back."""
        self._stopping.set()
        self._thread.join()
        self._check()

    # --- the worker --------------------------------------------------------------------------

    def _check(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the mapping thread failed: {self._error}") from self._error

    def _apply(self, command: tuple) -> None:
        name, args = command
        getattr(self._mapper, name)(*args)
        if name == "add_keyframe":
            self._iterations_since_keyframe = 0
            self._applied += 1
            self._num_gaussians = self._mapper.num_gaussians

    def _drain(self, wait: float) -> None:
        try:
            self._apply(self._commands.get(timeout=wait) if wait > 0 else self._commands.get_nowait())
            while True:
                self._apply(self._commands.get_nowait())
        except queue.Empty:
            pass

    def _run(self) -> None:
        m = self._mapper
        try:
            while not self._stopping.is_set():
                idle = m.num_keyframes == 0 or m.num_gaussians == 0
                self._drain(wait=0.02 if idle else 0.0)
                if m.num_keyframes == 0 or m.num_gaussians == 0:
                    continue
                self.stats.append(m.train(self._batch))
                self._iterations_since_keyframe += self._batch
                self._num_gaussians = m.num_gaussians
                pose = self._reference_pose
                if pose is not None:
                    t0 = time.perf_counter()
                    r = m.render(pose, self._K_track, *self._track_size)
                    self.reference_s += time.perf_counter() - t0
                    with self._lock:
                        self._reference = (pose, r)
            self._drain(wait=0.0)
            self._num_gaussians = m.num_gaussians
        except BaseException as e:  # surfaced to the tracker by _check
            self._error = e
