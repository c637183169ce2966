"""Keyframe feature extraction off the tracking path: one worker thread.

onnxruntime releases the GIL while it runs, so tracking in the calling thread keeps going while
a keyframe is encoded; `submit` only copies the frame and queues it. Jobs run in submission
order. Give the encoder fewer intra-op threads than cores if tracking must not share them.
"""

from __future__ import annotations

import queue
import threading
import time
import weakref
from dataclasses import dataclass

import numpy as np


@dataclass
class FeatureResult:
    key: object
    features: np.ndarray  # (h, w, K) float32, compressed if a PCA was given, else (h, w, D)
    extract_ms: float
    compress_ms: float


class AsyncExtractor:
    """`AsyncExtractor(encoder, pca=None)`; use as a context manager or call `close()` (at
    interpreter exit without it, the running job finishes and the queued ones are dropped).

    `submit(key, rgb)` returns at once; `poll()` hands over every finished result (in
    submission order); `get(key)` waits for one. A failed job re-raises its error there.
    `timings` keeps (key, extract_ms, compress_ms) of every finished job."""

    def __init__(self, encoder, pca=None):
        self.encoder = encoder
        self.pca = pca
        self.timings: list[tuple[object, float, float]] = []
        self._jobs: queue.Queue = queue.Queue()
        self._done: dict = {}  # key -> FeatureResult or BaseException, in finishing order
        self._pending: set = set()
        self._cond = threading.Condition()
        self._closed = False
        self._abandoned = threading.Event()
        self._worker = threading.Thread(target=self._run, name="legslam-features", daemon=True)
        self._worker.start()
        # At interpreter exit without close(), onnxruntime aborts the process if its session is
        # torn down under a running job: then the queued jobs are dropped and the running one
        # waited for.
        weakref.finalize(self, _abandon, self._abandoned, self._jobs, self._worker)

    def submit(self, key, rgb: np.ndarray) -> None:
        if self._closed:
            raise RuntimeError("AsyncExtractor is closed")
        with self._cond:
            if key in self._pending or key in self._done:
                raise ValueError(f"key {key!r} is already submitted and not yet collected")
            self._pending.add(key)
        # Copy: the caller may reuse its frame buffer while the job waits.
        self._jobs.put((key, np.array(rgb, copy=True)))

    def pending(self) -> int:
        """Jobs submitted and not finished."""
        with self._cond:
            return len(self._pending)

    def poll(self) -> list[FeatureResult]:
        """Finished results not yet collected, oldest first; never blocks. A failed job is
        raised by the poll that reaches it (the results before it come out in the poll before)."""
        out = []
        with self._cond:
            for key in list(self._done):
                if isinstance(self._done[key], BaseException):
                    if not out:
                        self._unwrap(self._done.pop(key))
                    break
                out.append(self._done.pop(key))
        return out

    def get(self, key, timeout: float | None = None) -> FeatureResult:
        """Waits for the result of `key` (TimeoutError after `timeout` seconds) and collects it."""
        with self._cond:
            if key not in self._pending and key not in self._done:
                raise KeyError(f"no job {key!r} (never submitted, or already collected)")
            if not self._cond.wait_for(lambda: key in self._done, timeout):
                raise TimeoutError(f"features for {key!r} not ready after {timeout} s")
            result = self._done.pop(key)
        return self._unwrap(result)

    @staticmethod
    def _unwrap(result):
        if isinstance(result, BaseException):
            raise result
        return result

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None or self._abandoned.is_set():
                return
            key, rgb = job
            try:
                t0 = time.perf_counter()
                features = self.encoder.encode(rgb)
                t1 = time.perf_counter()
                if self.pca is not None:
                    features = self.pca.transform(features)
                t2 = time.perf_counter()
                result = FeatureResult(key, features, (t1 - t0) * 1e3, (t2 - t1) * 1e3)
            except Exception as e:  # handed to the caller in get/poll
                result = RuntimeError(f"feature extraction for {key!r} failed: {e}")
                result.__cause__ = e
            with self._cond:
                self._pending.discard(key)
                self._done[key] = result
                if isinstance(result, FeatureResult):
                    self.timings.append((key, result.extract_ms, result.compress_ms))
                self._cond.notify_all()

    def close(self) -> None:
        """Finishes the queued jobs and stops the worker (results stay collectable)."""
        if not self._closed:
            self._closed = True
            self._jobs.put(None)
            self._worker.join()

    def __enter__(self) -> "AsyncExtractor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _abandon(abandoned: threading.Event, jobs: queue.Queue, worker: threading.Thread) -> None:
    """Stops an extractor's worker after the job it is running, dropping the queued ones."""
    abandoned.set()
    jobs.put(None)
    worker.join()
