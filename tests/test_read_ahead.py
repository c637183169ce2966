"""Frames read ahead on a thread (datasets.read_ahead): the source's order and errors, a bounded
lead, and a reader that stops when closed."""

from __future__ import annotations

import itertools
import threading
import time

import pytest

from legslam.datasets import DatasetError
from legslam.datasets.read_ahead import ReadAhead


def wait_for(condition, timeout=5.0) -> bool:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


class Source:
    """Counts its items as the reader takes them (on the reader's thread)."""

    def __init__(self, n=None, fail_at=None):
        self.read, self.threads = [], set()
        self.n, self.fail_at = n, fail_at

    def __iter__(self):
        for i in (itertools.count() if self.n is None else range(self.n)):
            self.threads.add(threading.get_ident())
            if i == self.fail_at:
                raise DatasetError(f"frame {i} is corrupt")
            self.read.append(i)
            yield i


def test_items_come_in_order_read_on_another_thread():
    src = Source(n=200)
    with ReadAhead(src, depth=3) as frames:
        assert list(frames) == list(range(200))
        assert list(frames) == []  # exhausted stays exhausted
    assert src.threads and threading.get_ident() not in src.threads


def test_an_error_reaches_the_consumer_after_the_items_before_it():
    frames = ReadAhead(Source(n=10, fail_at=4))
    got = []
    with pytest.raises(DatasetError, match="frame 4 is corrupt"):
        for i in frames:
            got.append(i)
    assert got == [0, 1, 2, 3]
    with pytest.raises(StopIteration):
        next(frames)
    frames.close()


def test_the_reader_runs_ahead_by_at_most_its_depth():
    src = Source()
    frames = ReadAhead(src, depth=2)
    assert next(frames) == 0
    # Without being asked, the reader takes the next ones ...
    assert wait_for(lambda: len(src.read) >= 3)
    time.sleep(0.2)
    # ... but no more than the queue holds plus the one it waits to hand over.
    assert len(src.read) <= 1 + 2 + 1
    assert [next(frames) for _ in range(3)] == [1, 2, 3]
    frames.close()


def test_close_stops_the_reader():
    src = Source()
    frames = ReadAhead(src, depth=2)
    assert next(frames) == 0
    frames.close()
    assert not frames._thread.is_alive()
    n = len(src.read)
    time.sleep(0.1)
    assert len(src.read) == n <= 4
    with pytest.raises(StopIteration):
        next(frames)


def test_depth_must_be_positive():
    with pytest.raises(ValueError, match="depth"):
        ReadAhead([1], depth=0)
