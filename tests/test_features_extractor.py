"""AsyncExtractor: submit never waits for extraction; results come back complete and in order."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from test_features_tiny_models import make_encoder

from legslam.features import PCA, AsyncExtractor, Encoder


class SlowEncoder:
    """A tiny real ONNX encoder that also sleeps, standing in for a slow keyframe encode."""

    def __init__(self, path, delay=0.2):
        self.inner = Encoder(path, input_size=28)
        self.delay = delay
        self.started = threading.Event()

    def encode(self, rgb):
        self.started.set()
        time.sleep(self.delay)
        return self.inner.encode(rgb)


def _frames(n):
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (40, 50, 3), dtype=np.uint8) for _ in range(n)]


def test_submit_returns_while_a_job_runs_and_results_are_right(tmp_path):
    enc = SlowEncoder(make_encoder(tmp_path / "e.onnx"))
    frames = _frames(4)
    with AsyncExtractor(enc) as ex:
        ex.submit(0, frames[0])
        assert enc.started.wait(5)
        t0 = time.perf_counter()
        for i in range(1, 4):
            ex.submit(i, frames[i])
        assert time.perf_counter() - t0 < 0.05  # a job takes >= 0.2 s
        assert ex.pending() >= 3
        first = ex.get(0, timeout=10)
        np.testing.assert_array_equal(first.features, enc.inner.encode(frames[0]))
        got = []
        while len(got) < 3:
            got += ex.poll()
            time.sleep(0.01)
    assert [r.key for r in got] == [1, 2, 3]
    for r in got:
        np.testing.assert_array_equal(r.features, enc.inner.encode(frames[r.key]))
        assert r.extract_ms >= 200 and r.compress_ms < 5  # no PCA: compression is a no-op
    assert [t[0] for t in ex.timings] == [0, 1, 2, 3]


def test_frames_are_copied_at_submit(tmp_path):
    enc = SlowEncoder(make_encoder(tmp_path / "e.onnx"), delay=0.1)
    frame = _frames(1)[0]
    expected = enc.inner.encode(frame)
    with AsyncExtractor(enc) as ex:
        ex.submit("kf", frame)
        frame[:] = 0  # the caller reuses its buffer
        np.testing.assert_array_equal(ex.get("kf", timeout=10).features, expected)


def test_pca_compression_is_applied_and_timed(tmp_path):
    enc = Encoder(make_encoder(tmp_path / "e.onnx"), input_size=28)
    frames = _frames(3)
    pca = PCA(3).fit(np.concatenate([enc.encode(f).reshape(-1, 8) for f in frames]))
    with AsyncExtractor(enc, pca) as ex:
        ex.submit(7, frames[1])
        r = ex.get(7, timeout=10)
    assert r.features.shape == (2, 2, 3)
    np.testing.assert_allclose(r.features, pca.transform(enc.encode(frames[1])), rtol=1e-5, atol=1e-6)
    assert r.compress_ms > 0


def test_errors_reach_the_caller_and_the_worker_survives(tmp_path):
    enc = Encoder(make_encoder(tmp_path / "e.onnx"), input_size=28)
    with AsyncExtractor(enc) as ex:
        ex.submit("bad", np.zeros((10, 10), np.uint8))
        ex.submit("good", _frames(1)[0])
        with pytest.raises(RuntimeError, match="'bad' failed: expected a uint8 RGB"):
            ex.get("bad", timeout=10)
        assert ex.get("good", timeout=10).features.shape == (2, 2, 8)
        with pytest.raises(KeyError):
            ex.get("never")
        ex.submit("again", _frames(1)[0])
        with pytest.raises(ValueError, match="already submitted"):
            ex.submit("again", _frames(1)[0])
    with pytest.raises(RuntimeError, match="closed"):
        ex.submit("late", _frames(1)[0])


def test_exit_without_close_waits_for_the_running_job_and_drops_the_queued(tmp_path):
    # onnxruntime aborts the process when its session is torn down under a running job, as a
    # script that stops without closing (an error, a forgotten close) would make it.
    log = tmp_path / "done.txt"
    script = tmp_path / "leave.py"
    script.write_text(f"""
import threading, time
import numpy as np
from legslam.features import AsyncExtractor

class Slow:
    started = threading.Event()
    def encode(self, rgb):
        self.started.set()
        time.sleep(0.5)
        with open({str(log)!r}, "a") as f:
            f.write(f"{{int(rgb[0, 0, 0])}}\\n")
        return np.zeros((2, 2, 4), np.float32)

enc = Slow()
ex = AsyncExtractor(enc)
for i in range(3):
    ex.submit(i, np.full((4, 4, 3), i, np.uint8))
assert enc.started.wait(5)
""")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert log.read_text().split() == ["0"]
