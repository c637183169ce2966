"""ROS bags (datasets.bag) written here with rosbags' writers (tests/recordings.py) from frames
whose values are known: real 7-Scenes frames from ../shared/data, or the built-in scene's.
Each test compares what the loader returns with those frames, their camera and their stamps."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import shared_path
from recordings import DEPTH_DELAY, TUM_TOPICS, Shot, folder_shots, synthetic_shots, write_bag

import legslam.datasets as D
from legslam.cli import main
from legslam.datasets import DatasetError
from legslam.eval import read_tum

pytest.importorskip("rosbags", reason="rosbags is an optional extra: pip install 'legslam[bags]'")

STORAGES = ["ros1", "sqlite3", "mcap"]
FAST = ["--no-features", "--quiet", "--final-iters", "5"]


def bag_path(tmp_path, storage: str, name: str = "rec"):
    return tmp_path / (name + (".bag" if storage == "ros1" else ""))


@pytest.fixture(scope="module")
def real_shots():
    """4 frames of the 7-Scenes sequence, at 160x120 (depth registered to colour, as read)."""
    folder = shared_path("data", "7scenes_tsdf_fusion", "data")
    seq = D.open(folder, max_frames=4, downscale=4)
    return [Shot(f.rgb, f.depth, 1_300_000_000.25 + f.timestamp, f.pose) for f in seq], seq.K


@pytest.fixture(scope="module")
def synth():
    return synthetic_shots(4, 64, 48)


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("source", ["7scenes", "synthetic"])
def test_a_bag_round_trips_images_depth_camera_and_stamps(tmp_path, storage, source, request):
    shots, K = request.getfixturevalue("real_shots" if source == "7scenes" else "synth")
    seq = D.open(write_bag(bag_path(tmp_path, storage), shots, K, storage=storage))
    assert seq.format == "bag" and len(seq) == len(shots)
    assert (seq.rgb_topic, seq.depth_topic) == TUM_TOPICS
    np.testing.assert_allclose(seq.K, K)
    for k, s in enumerate(shots):
        f = seq[k]
        np.testing.assert_array_equal(f.rgb, s.rgb)
        assert f.depth.dtype == np.float32
        np.testing.assert_allclose(f.depth, s.depth, atol=0.0005 + 1e-6)  # 16UC1: millimetres
        assert f.timestamp == pytest.approx(s.t, abs=1e-6)  # the colour's stamp, not the log time
        assert f.pose is None
    assert seq.gt_trajectory()[0].size == 0


def test_colour_and_depth_pair_by_stamp_as_tum(tmp_path, synth):
    shots, K = synth
    seq = D.open(write_bag(tmp_path / "gap.bag", shots, K, skip_depth={1}))
    assert len(seq) == 3  # frame 1 has no depth within 0.02 s of its colour
    assert [seq.timestamp(k) for k in range(3)] == pytest.approx([shots[k].t for k in (0, 2, 3)], abs=1e-6)
    np.testing.assert_array_equal(seq[1].rgb, shots[2].rgb)
    # A depth stamped 4 ms late still pairs with its own colour, not the next one.
    assert DEPTH_DELAY < 0.02


@pytest.mark.parametrize("colour", ["bgr8", "mono8", "png", "jpeg"])
def test_colour_encodings(tmp_path, synth, colour):
    shots, K = synth
    seq = D.open(write_bag(tmp_path / "c.bag", shots, K, colour=colour))
    got, want = seq[2].rgb, shots[2].rgb
    if colour == "mono8":
        grey = cv2.cvtColor(want, cv2.COLOR_RGB2GRAY)
        np.testing.assert_array_equal(got, np.repeat(grey[..., None], 3, axis=2))
    elif colour == "jpeg":
        assert seq.rgb_topic == TUM_TOPICS[0] + "/compressed"
        jpeg = cv2.imdecode(cv2.imencode(".jpg", want[..., ::-1])[1], cv2.IMREAD_COLOR)[..., ::-1]
        np.testing.assert_array_equal(got, jpeg)  # the bytes as recorded, decoded
    else:
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("depth, atol", [("32FC1", 0.0), ("16UC1 compressedDepth", 0.0005 + 1e-6),
                                          ("32FC1 compressedDepth", 0.002)])
def test_depth_encodings(tmp_path, synth, depth, atol):
    shots, K = synth
    seq = D.open(write_bag(tmp_path / "d", shots, K, depth=depth, storage="mcap"))
    got, want = seq[1].depth, shots[1].depth
    # compressedDepth's 32FC1 quantises inverse depth: the error grows as depth squared (~1 mm at 3 m).
    np.testing.assert_allclose(got, want, atol=atol, rtol=0 if atol < 0.001 else 2e-4)
    assert np.abs(got - want).max() > 0 or depth == "32FC1"


def test_lens_distortion_in_camera_info_is_removed(tmp_path, synth):
    shots, K = synth
    dist = np.array([0.12, -0.2, 0.001, -0.002, 0.05])
    seq = D.open(write_bag(tmp_path / "dist.bag", shots, K, dist=dist))
    want = cv2.undistort(shots[0].rgb, K, dist)
    got = seq[0].rgb
    diff = np.abs(got.astype(int) - want)  # cv2.undistort interpolates in fixed point
    assert diff.max() <= 4 and diff.mean() < 1
    assert np.abs(got.astype(int) - shots[0].rgb).mean() > 2  # something was done
    fisheye = write_bag(tmp_path / "fisheye.bag", shots, K, dist=dist[:4], model="equidistant")
    with pytest.raises(DatasetError, match="cannot undistort the 'equidistant' distortion model"):
        D.open(fisheye)
    seq = D.open(fisheye, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))  # as they are
    np.testing.assert_array_equal(seq[0].rgb, shots[0].rgb)


def test_topics_are_picked_and_else_listed(tmp_path, synth, capsys):
    shots, K = synth
    # A colour topic and its compressed copy, and an infrared (mono8) topic: one colour camera.
    p = write_bag(tmp_path / "rs.bag", shots, K, topics=("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw"),
                  extra=[("/camera/color/image_raw/compressed", "jpeg"), ("/camera/infra1/image_rect_raw", "mono8")])
    seq = D.open(p)
    assert (seq.rgb_topic, seq.depth_topic) == ("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw")

    p = write_bag(tmp_path / "two.bag", shots, K, topics=("/left/image", "/depth/image"),
                  extra=[("/right/image", "rgb8")])
    with pytest.raises(DatasetError) as e:
        D.open(p)
    msg = str(e.value)
    assert "2 colour image topics (/left/image, /right/image)" in msg and "--rgb-topic" in msg
    assert "/depth/image  (sensor_msgs/Image 16UC1, 4 messages)" in msg
    seq = D.open(p, rgb_topic="/right/image", intrinsics=(50.0, 50.0, 31.5, 23.5))  # no CameraInfo of its own
    assert seq.rgb_topic == "/right/image" and seq.intrinsics == (50.0, 50.0, 31.5, 23.5)
    with pytest.raises(DatasetError, match="16UC1 images, not colour, on /depth/image"):
        D.open(p, rgb_topic="/depth/image")
    out = tmp_path / "run"
    assert main(["run", str(p), "--out", str(out), *FAST]) == 2
    assert "choose one with rgb_topic (--rgb-topic)" in capsys.readouterr().err
    assert main(["run", str(p), "--out", str(out), "--rgb-topic", "/left/image", *FAST]) == 0
    stamps, poses = read_tum(out / "trajectory.txt")
    np.testing.assert_allclose(stamps, [s.t for s in shots], atol=1e-4)  # the bag's own times
    assert "no ATE: the sequence has no ground-truth poses" in capsys.readouterr().out
    assert main(["eval", str(out)]) == 0  # the run's topic, recorded in camera.json
    with pytest.raises(DatasetError, match="takes no option rgb_topic"):
        D.open(tmp_path / "run", format="folder", rgb_topic="/x")


def look_at(pose: np.ndarray, offset) -> np.ndarray:
    """A camera beside `pose`: moved by offset (metres, in its own axes) and turned 2 degrees."""
    a = np.radians(2.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = offset
    return pose @ T


def test_depth_of_another_camera_is_registered_with_tf_static(tmp_path):
    from legslam.datasets.synthetic import intrinsics

    w, h = 96, 72
    K_c = intrinsics(w, h)
    K_d = np.array([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]])  # 80x60, another focal length
    shots, _ = synthetic_shots(3, w, h, K=K_c)
    depth_pose = [look_at(s.pose, (0.05, 0.01, 0.0)) for s in shots]
    seen, _ = synthetic_shots(3, 80, 60, K=K_d, poses=depth_pose)  # what the depth camera sees
    colour_from_depth = np.linalg.inv(shots[0].pose) @ depth_pose[0]
    link_from_colour = look_at(np.eye(4), (0.0, -0.02, 0.01))
    link_from_depth = link_from_colour @ colour_from_depth
    p = write_bag(tmp_path / "two-cameras.bag", shots, K_c,
                  depth_camera=(K_d, [s.depth for s in seen], link_from_colour, link_from_depth))
    seq = D.open(p)
    np.testing.assert_allclose(seq.K, K_c)
    for k in range(3):
        got, want = seq[k].depth, shots[k].depth  # the colour camera's own depth
        both = (got > 0) & (want > 0)
        assert both.mean() > 0.6
        assert np.median(np.abs(got[both] - want[both])) < 0.01
        # Taken unregistered (the depth camera's image resized to colour's), it is far off.
        raw = cv2.resize(seen[k].depth, (w, h), interpolation=cv2.INTER_NEAREST)
        assert np.median(np.abs(raw[both] - want[both])) > 3 * np.median(np.abs(got[both] - want[both]))

    r = write_bag(tmp_path / "no-tf.bag", shots, K_c, depth_camera=(K_d, [s.depth for s in seen], None, None))
    with pytest.raises(DatasetError, match="'depth_optical'.*'color_optical'.*no transform between"):
        D.open(r)


def test_an_older_realsense_sdk_recording_is_read_with_its_depth_units_and_extrinsics(tmp_path):
    from legslam.datasets.synthetic import intrinsics
    from recordings import write_realsense_bag

    w, h = 96, 72
    K_c, K_d = intrinsics(w, h), np.array([[90.0, 0, 59.5], [0, 90.0, 44.5], [0, 0, 1]])
    shots, _ = synthetic_shots(2, w, h, K=K_c)
    depth_pose = [look_at(s.pose, (-0.015, 0.0, 0.0)) for s in shots]  # a D435's depth camera, 1.5 cm aside
    seen, _ = synthetic_shots(2, 120, 90, K=K_d, poses=depth_pose)
    colour_from_depth = np.linalg.inv(shots[0].pose) @ depth_pose[0]
    seq = D.open(write_realsense_bag(tmp_path / "d435.bag", shots, K_c, K_d, [s.depth for s in seen],
                                     colour_from_depth, depth_units=0.0005))  # 0.5 mm: up to 32 m
    assert seq.rgb_topic == "/device_0/sensor_1/Color_0/image/data"  # not the infrared beside it
    assert seq.depth_scale == pytest.approx(2000)
    got, want = seq[1].depth, shots[1].depth
    both = (got > 0) & (want > 0)
    assert both.mean() > 0.6 and np.median(np.abs(got[both] - want[both])) < 0.01


def test_reading_a_frame_reads_only_its_messages(tmp_path, synth, monkeypatch):
    shots, K = synth
    seq = D.open(write_bag(tmp_path / "lazy.bag", shots, K))
    calls = []
    real = seq._reader.messages
    monkeypatch.setattr(seq._reader, "messages", lambda **kw: calls.append(kw) or real(**kw))
    seq[3]
    assert len(calls) == 2 and all(c["stop"] - c["start"] == 1 for c in calls)  # one message each


def test_image_rows_drop_their_padding_and_a_short_message_is_an_error():
    from types import SimpleNamespace

    from legslam.datasets.bag import _pixels

    padded = SimpleNamespace(height=2, width=2, step=8, encoding="rgb8", data=np.arange(16, dtype=np.uint8))
    np.testing.assert_array_equal(_pixels(padded, np.uint8, 3, "x")[1, 1], [11, 12, 13])  # row 1 starts at byte 8
    short = SimpleNamespace(height=4, width=5, step=15, encoding="rgb8", data=np.zeros(50, np.uint8))
    with pytest.raises(DatasetError, match="m 3: 50 bytes of data for a 5x4 rgb8 image with 15 bytes a row"):
        _pixels(short, np.uint8, 3, "m 3")
