"""A recording played at its camera's pace (`legslam run --pace`): frames are not handed over
before they are due, lateness is counted, and bad speeds or timestamps are dealt with."""

import math
import time

import pytest

from legslam.cli import main
from legslam.datasets import open as open_dataset
from legslam.pipeline import run
from legslam import playback
from legslam.playback import Pacer
from legslam.slam import SLAMConfig


def _play(pacer: Pacer, stamps, work=0.0) -> float:
    """Seconds it takes to hand over frames stamped `stamps`, `work` seconds spent on each."""
    t0 = time.perf_counter()
    for s in stamps:
        pacer.wait(s)
        time.sleep(work)
    return time.perf_counter() - t0


def test_frames_wait_for_their_timestamps_at_the_speed_asked():
    stamps = [10.0, 10.05, 10.1, 10.15]  # the first frame's time is the origin
    assert _play(Pacer(1.0), stamps) >= 0.15
    fast = _play(Pacer(3.0), stamps)
    assert 0.05 <= fast < 0.14, fast


def test_timestamps_going_back_or_not_numbers_are_due_at_once():
    # 0.2 s is the latest time; the backward and NaN stamps add no wait of their own.
    elapsed = _play(Pacer(1.0), [0.0, 0.2, 0.1, math.nan, 0.2])
    assert 0.2 <= elapsed < 0.35, elapsed
    # The first finite timestamp is the origin.
    assert 0.5 <= _play(Pacer(1.0), [math.nan, 0.5, 1.0]) < 0.65
    # A frame stamped back in time is not counted late for it.
    back = Pacer(1.0)
    _play(back, [0.0, 0.1, 0.0, 0.15])
    assert back.report()["late_frames"] == 0 and back.report()["max_lag_s"] < 0.03, back.report()


def test_a_gap_in_the_recording_is_waited_out_and_said(monkeypatch, caplog):
    monkeypatch.setattr(playback, "GAP_S", 0.1)
    with caplog.at_level("WARNING", logger="legslam"):
        elapsed = _play(Pacer(1.0), [0.0, 0.05, 0.3])
    assert elapsed >= 0.3
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "timestamps jump to 0.300 s: waiting 0.2" in warnings[0], warnings


def test_frames_handed_over_after_the_next_was_due_are_counted_late():
    p = Pacer(1.0)
    p.wait(0.0)
    time.sleep(0.05)  # SLAM busy with frame 0 until frame 2 is due
    p.wait(0.01)      # late: frame 2 (0.02) was due before this one was handed over
    p.wait(0.02)      # the last: no next frame to be late for
    r = p.report()
    assert r["speed"] == 1.0 and r["late_frames"] == 1, r
    assert r["max_lag_s"] >= 0.035, r
    on_time = Pacer(1.0)
    _play(on_time, [0.0, 0.02, 0.04])
    assert on_time.report()["late_frames"] == 0


@pytest.mark.parametrize("speed", [0, -1.0, math.nan, math.inf, True, "1"])
def test_a_speed_that_is_not_a_positive_number_is_refused(speed):
    with pytest.raises(ValueError, match="playback speed must be a number > 0"):
        Pacer(speed)


def test_a_paced_run_takes_the_recordings_time(small_synthetic, tmp_path):
    seq = open_dataset(small_synthetic)
    span = seq.timestamp(len(seq) - 1) - seq.timestamp(0)
    cfg = SLAMConfig(features=False, final_iters=0, final_iters_per_frame=0.0)
    free = run(seq, tmp_path / "free", cfg)["timings"]
    assert "playback" not in free
    # Slow enough that the frames take twice as long as the run without pacing did.
    speed = span / (2 * free["live_s"])
    paced = run(open_dataset(small_synthetic), tmp_path / "paced", cfg, pace=speed)["timings"]
    assert paced["live_s"] >= span / speed == pytest.approx(2 * free["live_s"])
    assert paced["playback"]["speed"] == pytest.approx(speed)
    assert 0 <= paced["playback"]["late_frames"] < len(seq)


def test_a_bad_pace_is_refused_before_any_work(small_synthetic, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(small_synthetic), "--out", str(out), "--pace", "0", "--quiet"]) == 2
    assert "--pace: the playback speed must be a number > 0" in capsys.readouterr().err
    assert not out.exists()
