"""Frames read on a thread of their own, a few ahead of the loop that uses them: decoding a
7-Scenes frame (two PNGs and the depth's registration to the colour camera) takes ~16 ms, a
quarter of a real-time frame's budget, and the decoders release the GIL."""

from __future__ import annotations

import queue
import threading
from typing import Iterable, Iterator, TypeVar

__all__ = ["ReadAhead"]

T = TypeVar("T")

_END = object()
#: How often a reader blocked on a full queue looks whether it was closed (seconds).
_POLL_S = 0.05


class _Failed:
    """What the source raised, handed to the consumer where the item would have been."""

    def __init__(self, error: BaseException):
        self.error = error


class ReadAhead(Iterator[T]):
    """Iterates `source` on a daemon thread, at most `depth` items ahead of the consumer. Items
    come in the source's order; whatever the source raises is raised to the consumer at the
    same place, after the items before it. `close()` (or leaving a `with` block) stops the
    reader: it reads at most one more item."""

    def __init__(self, source: Iterable[T], depth: int = 2):
        if depth < 1:
            raise ValueError(f"depth must be at least 1, got {depth}")
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._closed = threading.Event()
        self._done = False
        self._thread = threading.Thread(target=self._read, args=(iter(source),),
                                        name="legslam-read-ahead", daemon=True)
        self._thread.start()

    def _read(self, it: Iterator[T]) -> None:
        while not self._closed.is_set():
            try:
                item = next(it)
            except StopIteration:
                item = _END
            except BaseException as e:  # noqa: BLE001 (the consumer raises it)
                item = _Failed(e)
            while not self._closed.is_set():
                try:
                    self._queue.put(item, timeout=_POLL_S)
                    break
                except queue.Full:
                    continue
            if item is _END or isinstance(item, _Failed):
                return

    def __iter__(self) -> "ReadAhead[T]":
        return self

    def __next__(self) -> T:
        if self._done:
            raise StopIteration
        item = self._queue.get()
        if item is _END:
            self._done = True
            raise StopIteration
        if isinstance(item, _Failed):
            self._done = True
            raise item.error
        return item

    def close(self) -> None:
        """Stops the reader and waits for the item it is reading, if any."""
        self._done = True
        self._closed.set()
        self._thread.join()

    def __enter__(self) -> "ReadAhead[T]":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
