"""A RealSense camera (datasets.realsense) through a stand-in of the SDK with pyrealsense2's
interface (a real one needs a device): frames from the built-in scene arrive in bursts, as a
camera delivers them while SLAM is busy; the camera must take the newest of each burst, count
the others as dropped, record what it took, and `legslam run realsense` must stop on Ctrl-C
and write every output as a dataset run does."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from recordings import synthetic_shots

from legslam.cli import main
from legslam.datasets import DatasetError
from legslam.datasets.realsense import RealSenseCamera
from legslam.eval import read_tum

W, H = 160, 120
DEPTH_UNITS = 0.0001  # metres per unit (a D405's; D4xx default 0.001)
FAST = ["--no-features", "--quiet", "--final-iters", "5"]


class Frame:
    def __init__(self, data, number: int, ms: float, fmt: str, kind: str):
        self.data, self.number, self.ms, self.fmt, self.kind = data, number, ms, fmt, kind

    def get_data(self):
        return self.data

    def get_frame_number(self):
        return self.number

    def get_timestamp(self):
        return self.ms

    def get_profile(self):
        return SimpleNamespace(format=lambda: self.fmt, stream_type=lambda: self.kind)


class Frameset:
    def __init__(self, colour=None, depth=None):
        self.colour, self.depth = colour, depth

    def __bool__(self):
        return self.colour is not None

    def get_color_frame(self):
        return self.colour

    def get_depth_frame(self):
        return self.depth

    def of(self, kind: str) -> Frame:
        return self.colour if kind == "color" else self.depth


class FakeSDK:
    """pyrealsense2's names that RealSenseCamera uses. `bursts`: lists of frame numbers that
    arrive together at a live camera's pipeline (a recording's sensors hand over all of them,
    each sensor from a thread of its own); `on_wait(n)` runs when the n-th burst is waited for."""

    stream = SimpleNamespace(color="color", depth="depth")
    format = SimpleNamespace(rgb8="rgb8", bgr8="bgr8", rgba8="rgba8", bgra8="bgra8", z16="z16")
    playback_status = SimpleNamespace(stopped="stopped")

    def __init__(self, shots, bursts, colour_format="rgb8", start_error=None, on_wait=None,
                 sensors=("depth", "color")):
        self.shots, self.bursts, self.colour_format = shots, [list(b) for b in bursts], colour_format
        self.sensors = sensors
        self.start_error, self.on_wait = start_error, on_wait or (lambda n: None)
        self.log, self.playing = [], []

    # -- the module's classes
    def pipeline(self):
        return Pipeline(self)

    def config(self):
        sdk = self

        class Config:
            def enable_stream(self, *a):
                sdk.log.append(("enable_stream", a))
        return Config()

    def context(self):
        sdk = self

        class Context:
            def load_device(self, path):
                sdk.log.append(("load_device", path))
                return sdk.device()
        return Context()

    def device(self):
        sdk = self

        class Sensor:
            def __init__(self, kind):
                self.kind = kind

            def get_stream_profiles(self):
                return [sdk.profile(self.kind)]

            def open(self, profiles):
                sdk.log.append(("open", self.kind))

            def start(self, callback):
                # Real time off before the sensors start, or the first frames are lost.
                sdk.log.append(("start", self.kind, ("real_time", False) in sdk.log))
                numbers = [n for burst in sdk.bursts for n in burst]
                self.playing = threading.Thread(target=lambda: [callback(sdk.frameset(n).of(self.kind))
                                                                for n in numbers])
                self.playing.start()
                sdk.playing.append(self.playing)

            def stop(self):
                self.playing.join()
                sdk.log.append(("stop", self.kind))

            def close(self):
                pass

        return SimpleNamespace(
            first_depth_sensor=lambda: SimpleNamespace(get_depth_scale=lambda: DEPTH_UNITS),
            query_sensors=lambda: [Sensor(kind) for kind in sdk.sensors],
            as_playback=lambda: SimpleNamespace(
                set_real_time=lambda on: sdk.log.append(("real_time", on)),
                pause=lambda: sdk.log.append("pause"), resume=lambda: sdk.log.append("resume"),
                current_status=lambda: "playing" if any(t.is_alive() for t in sdk.playing) else "stopped"))

    def profile(self, kind):
        """A stream's; the stand-in's depth is on the colour camera, aligned already."""
        intr = SimpleNamespace(fx=128.0, fy=129.0, ppx=79.5, ppy=59.0, width=W, height=H, coeffs=[0.0] * 5)
        same = SimpleNamespace(rotation=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], translation=[0.0, 0, 0])
        return SimpleNamespace(stream_type=lambda: kind, get_extrinsics_to=lambda other: same,
                               as_video_stream_profile=lambda: SimpleNamespace(get_intrinsics=lambda: intr))

    # -- frames
    def frameset(self, n: int) -> Frameset:
        s = self.shots[n]
        rgb = s.rgb if self.colour_format == "rgb8" else np.ascontiguousarray(s.rgb[..., ::-1])
        z16 = np.round(s.depth / DEPTH_UNITS).astype(np.uint16)
        ms = 1000.0 * s.t
        return Frameset(Frame(rgb, n, ms, self.colour_format, "color"), Frame(z16, n, ms, "z16", "depth"))


class Pipeline:
    """The SDK's pipeline of a live camera: framesets in bursts."""

    def __init__(self, sdk: FakeSDK):
        self.sdk, self.burst, self.waits = sdk, [], 0

    def start(self, cfg):
        if self.sdk.start_error:
            raise RuntimeError(self.sdk.start_error)
        return SimpleNamespace(get_device=self.sdk.device, get_stream=self.sdk.profile)

    def try_wait_for_frames(self, timeout_ms):
        self.sdk.on_wait(self.waits)
        self.waits += 1
        if not self.sdk.bursts:
            return False, Frameset()
        self.burst = self.sdk.bursts.pop(0)
        return True, self.sdk.frameset(self.burst.pop(0))

    def poll_for_frames(self):
        self.sdk.log.append("poll")
        return self.sdk.frameset(self.burst.pop(0)) if self.burst else Frameset()

    def stop(self):
        self.sdk.log.append("stop")


@pytest.fixture(scope="module")
def shots():
    return synthetic_shots(12, W, H)[0]


def test_a_live_camera_takes_the_newest_frame_counts_the_dropped_and_records(tmp_path, shots):
    sdk = FakeSDK(shots, [[0], [1, 2], [3], [4, 5, 6], [7], [8]])
    cam = RealSenseCamera(sdk=sdk, max_frames=5)
    cam.start(record_to=tmp_path / "rec")
    np.testing.assert_allclose(cam.K, [[128, 0, 79.5], [0, 129, 59], [0, 0, 1]])
    taken = list(cam.frames())
    assert [f.index for _, f in taken] == [0, 1, 2, 3, 4] and cam.dropped == 3
    numbers = [0, 2, 3, 6, 7]
    for (k, f), n in zip(taken, numbers):
        np.testing.assert_array_equal(f.rgb, shots[n].rgb)
        np.testing.assert_allclose(f.depth, shots[n].depth, atol=DEPTH_UNITS / 2 + 1e-6)
        assert f.timestamp == pytest.approx(shots[n].t, abs=1e-6)
    assert ("enable_stream", ("color", 640, 480, "rgb8", 30)) in sdk.log and sdk.log[-1] == "stop"
    rec = cam.recording()  # the frames taken, read back
    assert len(rec) == 5 and rec.depth_scale == pytest.approx(1 / DEPTH_UNITS)
    for k, n in enumerate(numbers):
        np.testing.assert_array_equal(rec[k].rgb, shots[n].rgb)
        np.testing.assert_allclose(rec[k].depth, taken[k][1].depth, atol=1e-6)
        assert rec.timestamp(k) == pytest.approx(shots[n].t, abs=1e-5)


def test_a_recording_played_back_gives_every_frame(tmp_path, shots):
    bag = tmp_path / "rec.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")  # the stand-in does not read it
    sdk = FakeSDK(shots, [[0], [1], [2], [3]], colour_format="bgr8")
    cam = RealSenseCamera(bag, sdk=sdk)
    cam.start()
    taken = [f for _, f in cam.frames()]
    assert len(taken) == 4 and cam.dropped == 0 and "poll" not in sdk.log
    assert ("load_device", str(bag)) in sdk.log and ("real_time", False) in sdk.log
    # Paused while the sensors start: the first started would play, and the other lose frames.
    starts = [sdk.log.index(("start", kind, True)) for kind in ("color", "depth")]
    assert sdk.log.index("pause") < min(starts) and max(starts) < sdk.log.index("resume")
    assert ("stop", "color") in sdk.log and ("stop", "depth") in sdk.log
    np.testing.assert_array_equal(taken[3].rgb, shots[3].rgb)  # bgr8 turned around


def test_a_recording_without_depth_is_refused_by_name(tmp_path, shots):
    bag = tmp_path / "colour-only.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    cam = RealSenseCamera(bag, sdk=FakeSDK(shots, [[0]], sensors=("color",)))
    with pytest.raises(DatasetError, match=r"colour-only\.bag: the recording has no depth stream"):
        cam.start()


def test_a_recording_without_extrinsics_is_refused_and_its_streams_stopped(tmp_path, shots):
    bag = tmp_path / "no-extrinsics.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    sdk = FakeSDK(shots, [[0], [1]])
    profile = sdk.profile

    def without_extrinsics(kind):
        def missing(other):
            raise RuntimeError("Requested extrinsics are not available!")
        return SimpleNamespace(**{**vars(profile(kind)), "get_extrinsics_to": missing})
    sdk.profile = without_extrinsics
    with pytest.raises(DatasetError, match=r"no-extrinsics\.bag: depth cannot be registered to colour: no "
                                           r"extrinsics between the two streams \(Requested extrinsics"):
        RealSenseCamera(bag, sdk=sdk).start()
    assert ("stop", "color") in sdk.log and ("stop", "depth") in sdk.log


def test_legslam_run_realsense_stops_on_ctrl_c_and_writes_everything(tmp_path, shots, monkeypatch, capsys):
    def ctrl_c(n):
        if n == 7:  # as a user would, while the camera streams
            os.kill(os.getpid(), signal.SIGINT)
    sdk = FakeSDK(shots, [[0], [1], [2, 3], [4], [5], [6], [7, 8], [9], [10], [11]], on_wait=ctrl_c)
    monkeypatch.setitem(sys.modules, "pyrealsense2", sdk)
    out = tmp_path / "live"
    assert main(["run", "realsense", "--out", str(out), *FAST]) == 0
    captured = capsys.readouterr()
    assert "stopping: the frames taken are being finished" in captured.err
    assert "dropped 2 (not kept up with)" in captured.out
    assert "no ATE: the sequence has no ground-truth poses" in captured.out
    stamps, poses = read_tum(out / "trajectory.txt")
    # The newest of each burst; Ctrl-C came during the 8th wait, whose frame is the last taken.
    np.testing.assert_allclose(stamps, [shots[n].t for n in (0, 1, 3, 4, 5, 6, 8, 9)], atol=1e-4)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["dropped_frames"] == 2 and metrics["frames"] == 8 and "ate_rmse_cm" not in metrics
    assert json.loads((out / "config.json").read_text())["mapping_thread"] is True
    assert len(list((out / "recording" / "color").iterdir())) == 8 and (out / "map.ply").is_file()
    assert main(["eval", str(out)]) == 0  # evaluated again from its recording


def test_no_sdk_or_no_camera_is_said(tmp_path, shots, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # not installed
    assert main(["run", "realsense", "--out", str(tmp_path / "a"), *FAST]) == 2
    assert "pip install 'legslam[realsense]'" in capsys.readouterr().err
    # Installed, but a library it links is missing: that is said, not "install it".
    broken = tmp_path / "site" / "pyrealsense2"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text(
        'raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")\n')
    monkeypatch.delitem(sys.modules, "pyrealsense2")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    assert main(["run", "realsense", "--out", str(tmp_path / "a2"), *FAST]) == 2
    err = capsys.readouterr().err
    assert "pyrealsense2) is installed but cannot load: libusb-1.0.so.0" in err and "apt-get install libusb" in err
    assert "pip install" not in err
    monkeypatch.setitem(sys.modules, "pyrealsense2", FakeSDK(shots, [], start_error="No device connected"))
    assert main(["run", "realsense", "--out", str(tmp_path / "b"), *FAST]) == 2
    assert "cannot start a RealSense camera: No device connected (is one connected" in capsys.readouterr().err
    assert main(["run", "realsense", "--stride", "2", "--out", str(tmp_path / "c"), *FAST]) == 2
    assert "--stride cannot be used with a RealSense camera" in capsys.readouterr().err
    with pytest.raises(DatasetError, match="colour frames in yuyv cannot be read"):
        cam = RealSenseCamera(sdk=FakeSDK(shots, [[0]], colour_format="yuyv"))
        cam.start()
        next(cam.frames())


def test_pace_and_sync_are_refused_with_a_camera(tmp_path, shots, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pyrealsense2", FakeSDK(shots, [[0], [1]]))
    out = tmp_path / "live"
    assert main(["run", "realsense", "--pace", "--out", str(out), *FAST]) == 2
    assert "a camera (or the RealSense SDK's playback) delivers frames at its own" in capsys.readouterr().err
    assert not out.exists()
    # Nor does it wait for the map.
    assert main(["run", "realsense", "--sync", "--out", str(out), *FAST]) == 2
    assert "--sync cannot be used with a live camera" in capsys.readouterr().err
    assert not out.exists()


def test_a_camera_that_stops_delivering_stops_the_run_with_its_work_kept(tmp_path, shots, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pyrealsense2", FakeSDK(shots, [[0], [1], [2], [3]]))  # then nothing
    out = tmp_path / "unplugged"
    assert main(["run", "realsense", "--out", str(out), *FAST]) == 2
    assert "no frames from the RealSense camera for 5 s (disconnected?)" in capsys.readouterr().err
    assert len(read_tum(out / "trajectory.txt")[1]) == 4 and (out / "map.ply").is_file()


def test_the_sdk_plays_back_its_own_recording_and_the_bag_reader_reads_it_too(tmp_path):
    """A recording the real SDK writes (from a software device), of a depth camera turned 2
    degrees and 1.5 cm aside: read by legslam's bag reader and played back through the SDK,
    both must give every frame, with the colour camera's depth."""
    # ImportError too: an SDK that is installed but cannot load its libraries (libusb) skips.
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 is an optional extra: pip install 'legslam[realsense]' "
                        "(and it needs libusb)", exc_type=ImportError)
    pytest.importorskip("rosbags", reason="rosbags is an optional extra: pip install 'legslam[bags]'")
    from recordings import record_realsense
    from test_bags import look_at

    from legslam.datasets import open as open_dataset
    from legslam.datasets.synthetic import intrinsics

    w, h, n = 96, 72, 6
    K_c, K_d = intrinsics(w, h), np.array([[90.0, 0, 59.5], [0, 90.0, 44.5], [0, 0, 1]])
    shots, _ = synthetic_shots(n, w, h, K=K_c)
    depth_pose = [look_at(s.pose, (-0.015, 0.0, 0.0)) for s in shots]
    seen, _ = synthetic_shots(n, 120, 90, K=K_d, poses=depth_pose)
    rec = record_realsense(tmp_path / "turned.db3", shots, K_c, K_d, [s.depth for s in seen],
                           np.linalg.inv(shots[0].pose) @ depth_pose[0], depth_units=0.0005)

    def close(got, want, tolerance):
        both = (got > 0) & (want > 0)
        return both.mean() > 0.6 and np.median(np.abs(got[both] - want[both])) < tolerance

    seq = open_dataset(rec)
    assert seq.format == "bag" and len(seq) == n and seq.depth_scale == pytest.approx(2000)
    np.testing.assert_allclose(seq.K, K_c)
    for k in range(n):
        np.testing.assert_array_equal(seq[k].rgb, shots[k].rgb)
        assert close(seq[k].depth, shots[k].depth, 0.01)

    cam = RealSenseCamera(rec)
    cam.start()
    played = [f for _, f in cam.frames()]
    np.testing.assert_allclose(cam.K, K_c, atol=1e-4)
    assert len(played) == n and cam.dropped == 0
    for f, s in zip(played, shots):
        assert f.timestamp == pytest.approx(s.t, abs=1e-3)
        np.testing.assert_array_equal(f.rgb, s.rgb)
        assert close(f.depth, s.depth, 0.01)

    cam = RealSenseCamera(rec, max_frames=2)  # stopped while the playback waits to hand over more
    cam.start()
    assert [f.index for _, f in cam.frames()] == [0, 1]


def test_colour_and_depth_arriving_apart_are_paired_by_nearest_timestamp():
    """As a recording's two sensors hand frames over: depth a few ms off colour, one depth
    frame missing, depth running behind colour, a stray depth frame between two colour ones."""
    from legslam.datasets.realsense import Image, Pairing

    def img(n, t):
        return Image(n, t, np.zeros((1, 1)), "z16")

    colour = [img(n, n / 30) for n in range(10)]
    depth = [img(n, n / 30 + 0.004 * (-1) ** n) for n in range(10) if n != 4] + [img(99, 6.5 / 30)]
    depth.sort(key=lambda d: d.t)
    arrivals = [(True, c) for c in colour[:5]] + [(False, d) for d in depth[:6]]
    arrivals += [x for pair in zip([(True, c) for c in colour[5:9]], [(False, d) for d in depth[6:]]) for x in pair]
    arrivals.append((True, colour[9]))
    pairing, pairs = Pairing(), []
    for is_colour, x in arrivals:
        pairing.add(is_colour, x)
        while (p := pairing.pop()) is not None:
            pairs.append(p)
    assert len(pairs) == 8  # the last colour frame waits for depth that could still be nearer
    while (p := pairing.pop(ended=True)) is not None:
        pairs.append(p)
    assert [(c.number, d.number) for c, d in pairs] == [(n, n) for n in range(10) if n != 4]
    assert pairing.unpaired == 1 and not pairing.colour
