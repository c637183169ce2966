"""Where keyframes go and how the map is trained while frames come in, behind one interface:
`InlineMapping` trains after every frame (the frame waits for it), `ThreadedMapping` trains in
a worker thread so that tracking alone sets the frame rate.

With a thread, the tracker (main thread) queues keyframes and feature grids; the worker
applies them, trains the map in small batches on whatever keyframes it has and, after every
`REFERENCE_EVERY`-th batch (every batch while the tracker counts the map's coverage), renders
the map at the latest tracked pose as the tracker's next reference. While the
worker runs, only it touches the mapper; the engine releases the GIL, so both threads compute
at once.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Optional

import numpy as np

__all__ = ["InlineMapping", "MapReference", "ThreadedMapping"]

#: The mapping thread renders the tracker's reference after every this-many-th batch, and after
#: every batch while the map's coverage counts for keyframes (the newest keyframe has had its
#: iterations) or a correction has moved the map since the last render. The frames align with
#: the last frame first and fall back to the render only when that fails (none of 1000 paced
#: 7-Scenes frames did), while a render after every batch took ~13% of the thread's time.
REFERENCE_EVERY = 4


class InlineMapping:
    """Mapping in the caller's thread: `iters_keyframe` iterations after a keyframe,
    `iters_frame` after any other tracked frame; references rendered on demand."""

    def __init__(self, mapper, K_track: np.ndarray, track_size: tuple, iters_keyframe: int,
                 iters_frame: int):
        self._mapper = mapper
        self._K_track, self._track_size = K_track, track_size
        self._iters = (iters_frame, iters_keyframe)
        #: The engine's report of every training call.
        self.stats: list = []
        self.reference_s = 0.0
        #: Counts the calls that change the map (a `MapReference` holds while it stays).
        self.version = 0

    def add_keyframe(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> int:
        """Adds a keyframe (colour float32 in [0, 1]); returns its id."""
        self.version += 1
        return self._mapper.add_keyframe(rgb, depth, K, pose)[0]

    def set_features(self, kf_id: int, grid: np.ndarray) -> None:
        self._mapper.set_features(kf_id, grid)

    def correct_keyframes(self, corrections: np.ndarray) -> None:
        """Moves keyframe k by corrections[k] and the Gaussians it made with it."""
        self.version += 1
        self._mapper.correct_keyframes(corrections)

    def after_frame(self, pose: np.ndarray, keyframe: bool) -> None:
        """A frame was tracked at `pose`: train."""
        self.version += 1
        self.stats.append(self._mapper.train(self._iters[keyframe]))

    def reference(self, predicted: np.ndarray) -> tuple:
        """(pose, render at the tracking size) to track against: the map at `predicted`, its
        colour and depth rendered only when asked for (`MapReference`)."""
        return predicted, MapReference(self, predicted)

    def keeps_up(self) -> bool:
        """Whether the newest keyframe has had its iterations: always, inline."""
        return True

    @property
    def empty(self) -> bool:
        return self._mapper.num_gaussians == 0

    @property
    def num_gaussians(self) -> int:
        return self._mapper.num_gaussians

    def stop(self) -> None:
        """Nothing runs in the background: the mapper is the caller's already."""


class MapReference:
    """The map rendered at a pose: alpha at once, colour and depth on first use. Every frame
    needs the alpha (how much of the view the map covers), the colour only when the frame fails
    to align with the last one (none of 1000 synchronous 7-Scenes frames did). Without colour
    the render skips the Gaussians' SH colour and its compositing: the same alpha, ~11% less
    time. Valid until `mapping` changes the map (the tracking of one frame does not)."""

    def __init__(self, mapping: "InlineMapping", pose: np.ndarray):
        self._mapping, self._version = mapping, mapping.version
        self._args = (pose, mapping._K_track, *mapping._track_size)
        self.alpha = mapping._mapper.render(*self._args, color=False).alpha
        self._full = None

    @property
    def color(self) -> np.ndarray:
        return self._render().color

    @property
    def depth(self) -> np.ndarray:
        return self._render().depth

    def _render(self):
        if self._full is None:
            if self._mapping.version != self._version:
                raise RuntimeError("the map changed since this reference's alpha was rendered")
            self._full = self._mapping._mapper.render(*self._args)
        return self._full


class ThreadedMapping:
    """Mapping in a worker thread, `batch` iterations at a time over the keyframes it has,
    with the Gaussians' learning rates `lr_scale` times the mapper's (a number, or a dict by
    group as `MapperCore.train` takes it). The tracker counts the map's coverage once the
    newest keyframe has had `coverage_iters` iterations (`keeps_up`)."""

    def __init__(self, mapper, K_track: np.ndarray, track_size: tuple, batch: int = 2,
                 lr_scale=1.0, coverage_iters: int = 15):
        self._mapper = mapper
        self._K_track, self._track_size = K_track, track_size
        self._batch = batch
        self._lr_scale = lr_scale
        self._commands: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._reference: Optional[tuple] = None  # (pose, render, corrections applied before it)
        # Keyframe corrections queued, and applied by the worker: a render from before the
        # latest is no reference (the map moved since).
        self._corrections_queued = 0
        self._corrections_applied = 0
        self._reference_pose: Optional[np.ndarray] = None
        self._first_id = mapper.num_keyframes
        self._submitted = 0
        self._applied = 0
        self._num_gaussians = mapper.num_gaussians
        self._iterations_since_keyframe = 0
        self._coverage_iters = coverage_iters
        self._error: Optional[BaseException] = None
        self._stopping = threading.Event()
        #: The engine's report of every batch, and seconds spent rendering references.
        self.stats: list = []
        self.reference_s = 0.0
        self._thread = threading.Thread(target=self._run, name="legslam-mapping", daemon=True)
        self._thread.start()

    # --- called by the tracker ---------------------------------------------------------------

    def add_keyframe(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> int:
        """Queues a keyframe; returns the id the mapper will give it."""
        self._check()
        kf_id = self._first_id + self._submitted
        self._submitted += 1
        self._commands.put(("add_keyframe", (rgb, depth, K, pose)))
        return kf_id

    def set_features(self, kf_id: int, grid: np.ndarray) -> None:
        self._check()
        self._commands.put(("set_features", (kf_id, grid)))

    def correct_keyframes(self, corrections: np.ndarray) -> None:
        """Queues moving keyframe k by corrections[k] and the Gaussians it made with it."""
        self._check()
        self._corrections_queued += 1
        self._commands.put(("correct_keyframes", (np.array(corrections),)))

    def after_frame(self, pose: np.ndarray, keyframe: bool) -> None:
        """A frame was tracked at `pose`: the next reference is rendered there."""
        self._reference_pose = pose

    def reference(self, predicted: np.ndarray) -> tuple:
        """(pose, render at the tracking size) of the latest batch, (None, None) before the
        first and until the map has taken the latest keyframe correction."""
        self._check()
        with self._lock:
            if self._reference is None or self._reference[2] != self._corrections_queued:
                return None, None
            return self._reference[:2]

    @property
    def pending(self) -> bool:
        """Whether queued keyframes have not reached the map yet."""
        return self._applied < self._submitted

    def keeps_up(self) -> bool:
        """Whether every queued keyframe is in the map and the latest has had
        `coverage_iters` iterations since."""
        return not self.pending and self._iterations_since_keyframe >= self._coverage_iters

    @property
    def empty(self) -> bool:
        return not self.pending and self._num_gaussians == 0

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
        if name == "correct_keyframes":
            self._corrections_applied += 1
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
        m, batches = self._mapper, 0
        try:
            while not self._stopping.is_set():
                idle = m.num_keyframes == 0 or m.num_gaussians == 0
                self._drain(wait=0.02 if idle else 0.0)
                if m.num_keyframes == 0 or m.num_gaussians == 0:
                    continue
                self.stats.append(m.train(self._batch, lr_scale=self._lr_scale))
                self._iterations_since_keyframe += self._batch
                self._num_gaussians = m.num_gaussians
                batches += 1
                pose, applied = self._reference_pose, self._corrections_applied
                last = self._reference
                due = (last is None or last[2] != applied or self.keeps_up()
                       or batches % REFERENCE_EVERY == 0)
                if pose is not None and due:
                    t0 = time.perf_counter()
                    r = m.render(pose, self._K_track, *self._track_size)
                    self.reference_s += time.perf_counter() - t0
                    with self._lock:
                        self._reference = (pose, r, applied)
            self._drain(wait=0.0)
            self._num_gaussians = m.num_gaussians
        except BaseException as e:  # surfaced to the tracker by _check
            self._error = e
