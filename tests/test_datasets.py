"""Loaders on small fixtures written here with cv2 and plain text, so every expected value
(depth in metres, K, poses, timestamps, labels) is known independently of the loaders."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import legslam.datasets as D
from legslam.datasets import IGNORE_LABEL, DatasetError, DatasetNotFoundError

H, W = 24, 32
RNG = np.random.default_rng(7)


def rot_z(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = t
    return T


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rgb[..., ::-1])


def write_u16(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img.astype(np.uint16))


def frames_data(n: int):
    """n (rgb, raw depth) pairs: random colour, raw depth 1000..9000 with a few zeros."""
    out = []
    for _ in range(n):
        rgb = RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)
        raw = RNG.integers(1000, 9000, (H, W)).astype(np.uint16)
        raw[0, :3] = 0
        out.append((rgb, raw))
    return out


def write_matrix(path: Path, M: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{v:.10f}" for v in row) for row in M) + "\n")


# --- TUM ---------------------------------------------------------------------------------

@pytest.fixture
def tum_dir(tmp_path):
    p = tmp_path / "rgbd_dataset_freiburg3_test"
    data = frames_data(3)
    rgb_t = [10.000, 10.033, 10.066]
    depth_t = [10.005, 10.030, 10.200]  # the third has no depth within 0.02 s
    lines_rgb, lines_depth = [], []
    for k, (rgb, raw) in enumerate(data):
        write_rgb(p / "rgb" / f"{rgb_t[k]:.6f}.png", rgb)
        write_u16(p / "depth" / f"{depth_t[k]:.6f}.png", raw)
        lines_rgb.append(f"{rgb_t[k]:.6f} rgb/{rgb_t[k]:.6f}.png")
        lines_depth.append(f"{depth_t[k]:.6f} depth/{depth_t[k]:.6f}.png")
    (p / "rgb.txt").write_text("# color images\n# file\n# timestamp filename\n" + "\n".join(lines_rgb) + "\n")
    (p / "depth.txt").write_text("# depth maps\n" + "\n".join(lines_depth) + "\n")
    # 90 degrees about z: q = (0, 0, sin 45, cos 45). Only the first frame has ground truth near it.
    s = np.sqrt(0.5)
    (p / "groundtruth.txt").write_text(f"# ground truth\n10.001 1 2 3 0 0 {s} {s}\n11.0 0 0 0 0 0 0 1\n")
    return p, data


def test_tum_association_depth_scale_intrinsics_and_quaternion(tum_dir):
    p, data = tum_dir
    seq = D.open(p)
    assert seq.format == "tum" and len(seq) == 2
    f0, f1 = seq[0], seq[1]
    assert f0.timestamp == pytest.approx(10.0) and f1.timestamp == pytest.approx(10.033)
    np.testing.assert_array_equal(f0.rgb, data[0][0])
    np.testing.assert_allclose(f1.depth, data[1][1] / 5000.0, rtol=1e-6)
    assert f0.depth[0, 0] == 0
    np.testing.assert_allclose(f0.K, [[535.4, 0, 320.1], [0, 539.2, 247.6], [0, 0, 1]])  # freiburg3
    expected = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(f0.pose, expected, atol=1e-12)
    assert f1.pose is None  # no ground truth within the tolerance
    stamps, poses = seq.gt_trajectory()
    assert stamps.tolist() == [10.0] and poses.shape == (1, 4, 4)


def test_tum_freiburg1_images_are_undistorted(tmp_path):
    p = tmp_path / "rgbd_dataset_freiburg1_xyz"
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[:, ::40] = 255  # vertical lines bend under undistortion away from the centre
    write_rgb(p / "rgb" / "1.png", rgb)
    write_u16(p / "depth" / "1.png", np.full((480, 640), 5000))
    (p / "rgb.txt").write_text("1.0 rgb/1.png\n")
    (p / "depth.txt").write_text("1.0 depth/1.png\n")
    f = D.open(p)[0]
    np.testing.assert_allclose(f.K[0, 0], 517.3)
    assert not np.array_equal(f.rgb, rgb)
    # Centre pixels barely move; depth is resampled with nearest neighbour (no new values).
    assert set(np.unique(f.depth)) <= {0.0, 1.0}


# --- Replica -----------------------------------------------------------------------------

@pytest.fixture
def replica_dir(tmp_path):
    seq = tmp_path / "office9"
    data = frames_data(3)
    for k, (rgb, raw) in enumerate(data):
        write_rgb(seq / "results" / f"frame{k:06d}.jpg", rgb)
        write_u16(seq / "results" / f"depth{k:06d}.png", raw)
    poses = [rot_z(10 * k, (k, 0, 0)) for k in range(5)]  # traj.txt is longer than the copy
    (seq / "traj.txt").write_text("\n".join(" ".join(map(str, T.ravel())) for T in poses) + "\n")
    return seq, data, poses


def test_replica_standard_camera_is_scaled_to_the_image(replica_dir):
    seq_dir, data, poses = replica_dir
    seq = D.open(seq_dir)
    assert seq.format == "replica" and len(seq) == 3 and seq.camera_file is None
    sx, sy = W / 1200, H / 680
    np.testing.assert_allclose(seq.K, [[600 * sx, 0, 600 * sx - 0.5], [0, 600 * sy, 340 * sy - 0.5], [0, 0, 1]])
    f = seq[2]
    np.testing.assert_allclose(f.depth, data[2][1] / 6553.5, rtol=1e-6)
    np.testing.assert_allclose(f.pose, poses[2])


def test_replica_reads_cam_params_from_the_parent_folder(replica_dir):
    seq_dir, _, _ = replica_dir
    cam = {"camera": {"w": W, "h": H, "fx": 30.0, "fy": 31.0, "cx": 15.5, "cy": 11.5, "scale": 1000.0}}
    (seq_dir.parent / "cam_params.json").write_text(json.dumps(cam))
    seq = D.open(seq_dir, format="replica")
    np.testing.assert_allclose(seq.K, [[30, 0, 15.5], [0, 31, 11.5], [0, 0, 1]])
    assert seq.depth_scale == 1000.0
    cam["camera"]["w"] = 2 * W
    (seq_dir.parent / "cam_params.json").write_text(json.dumps(cam))
    with pytest.raises(DatasetError, match="describes"):
        D.open(seq_dir)


# --- 7-Scenes ----------------------------------------------------------------------------

@pytest.fixture
def sevenscenes_dir(tmp_path):
    p = tmp_path / "seq-01"
    data = frames_data(2)
    data[0][1][5, 5] = 65535
    for k, (rgb, raw) in enumerate(data):
        write_rgb(p / f"frame-{k:06d}.color.png", rgb)
        write_u16(p / f"frame-{k:06d}.depth.png", raw)
        write_matrix(p / f"frame-{k:06d}.pose.txt", rot_z(5 * k, (0, k, 0)))
    return p, data


def test_sevenscenes_invalid_depth_default_camera_and_poses(sevenscenes_dir):
    p, data = sevenscenes_dir
    seq = D.open(p)
    assert seq.format == "7scenes" and len(seq) == 2
    f = seq[0]
    assert f.depth[5, 5] == 0 and f.depth[0, 0] == 0
    np.testing.assert_allclose(f.depth[1], data[0][1][1] / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(f.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    np.testing.assert_allclose(seq[1].pose, rot_z(5, (0, 1, 0)), atol=1e-9)
    write_matrix(p.parent / "camera-intrinsics.txt", np.array([[20.0, 0, 16], [0, 21, 12], [0, 0, 1]]))
    np.testing.assert_allclose(D.open(p).K[1], [0, 21, 12])


def test_sevenscenes_kinect_depth_is_registered_to_the_colour_camera(tmp_path):
    from legslam.datasets import sevenscenes as S
    from legslam.datasets.registration import register_depth

    p = tmp_path / "seq-01"
    raw = np.full((480, 640), 2000, np.uint16)
    raw[200:280, 300:340] = 1000  # a near box
    raw[:40] = 65535  # the invalid marker must not become a surface 65 m away
    raw[40:50] = 0
    write_rgb(p / "frame-000000.color.png", RNG.integers(0, 256, (480, 640, 3), dtype=np.uint8))
    write_u16(p / "frame-000000.depth.png", raw)
    write_matrix(p / "frame-000000.pose.txt", rot_z(30, (1, 2, 3)))
    seq = D.open(p)
    assert seq.registers_depth
    np.testing.assert_allclose(seq.K, S.COLOR_K)
    f = seq[0]
    motion = S.COLOR_FROM_DEPTH.copy()
    motion[:3, 3] *= 1000
    clean = np.where(raw == 65535, 0, raw)
    np.testing.assert_allclose(f.depth, register_depth(clean, S.DEFAULT_K, S.COLOR_K, motion, (640, 480)) / 1000)
    assert f.depth.max() < 2.1 and (f.depth[:40] == 0).all()
    # The colour camera's pose: where the depth camera's puts the colour camera's centre.
    np.testing.assert_allclose(f.pose, rot_z(30, (1, 2, 3)) @ np.linalg.inv(S.COLOR_FROM_DEPTH), atol=1e-12)
    np.testing.assert_allclose(seq.pose(0), f.pose)
    # Given intrinsics or another camera in camera-intrinsics.txt: read as registered.
    for kw in ({"intrinsics": (585.0, 585.0, 320.0, 240.0)}, {}):
        if not kw:
            write_matrix(p / "camera-intrinsics.txt", np.array([[570.3, 0, 320], [0, 570.3, 240], [0, 0, 1]]))
        other = D.open(p, **kw)
        assert not other.registers_depth
        np.testing.assert_allclose(other[0].depth, clean / 1000)
        np.testing.assert_allclose(other[0].pose, rot_z(30, (1, 2, 3)), atol=1e-9)


# --- ScanNet -----------------------------------------------------------------------------

@pytest.fixture
def scannet_dir(tmp_path):
    p = tmp_path / "scene0000_00"
    data = frames_data(2)
    for k, (rgb, raw) in enumerate(data):
        big = cv2.resize(rgb, (2 * W, 2 * H), interpolation=cv2.INTER_NEAREST)  # colour is larger
        write_rgb(p / "color" / f"{k}.jpg", big)
        write_u16(p / "depth" / f"{k}.png", raw)
        write_matrix(p / "pose" / f"{k}.txt", rot_z(3 * k) if k == 0 else np.full((4, 4), -np.inf))
        labels = np.zeros((H, W), np.uint16)
        labels[:, :8] = 1    # NYU40 wall -> ScanNet-20 class 0
        labels[:, 8:16] = 14  # desk -> 12
        labels[:, 16:24] = 13  # pillow: not a benchmark class
        labels[:, 24:] = 39   # otherfurniture -> 19
        write_u16(p / "label-filt" / f"{k}.png", labels)
    write_matrix(p / "intrinsic" / "intrinsic_depth.txt",
                 np.array([[25.0, 0, 15.5, 0], [0, 26.0, 11.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    return p, data


def test_scannet_resizes_colour_maps_labels_and_reads_lost_poses_as_none(scannet_dir):
    p, data = scannet_dir
    seq = D.open(p)
    assert seq.format == "scannet" and seq.class_names[12] == "desk" and len(seq.class_names) == 20
    f = seq[0]
    assert f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)
    np.testing.assert_allclose(f.K, [[25, 0, 15.5], [0, 26, 11.5], [0, 0, 1]])
    assert f.labels[0, :8].tolist() == [0] * 8 and f.labels[0, 8] == 12
    assert f.labels[0, 16] == IGNORE_LABEL and f.labels[0, 31] == 19
    assert seq[1].pose is None  # ScanNet's -inf pose
    np.testing.assert_allclose(f.pose, rot_z(0), atol=1e-9)


def test_scannet_raw_label_ids_need_the_tsv(scannet_dir):
    p, _ = scannet_dir
    write_u16(p / "label-filt" / "0.png", np.full((H, W), 1163))  # a raw ScanNet id
    with pytest.raises(DatasetError, match="scannetv2-labels.combined.tsv"):
        D.open(p)[0]
    (p.parent / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\n1163\tstand\tstand\t5\t7\n")
    assert set(np.unique(D.open(p)[0].labels)) == {6}  # NYU40 7 = table = ScanNet-20 class 6


# --- plain folder -------------------------------------------------------------------------

@pytest.fixture
def folder_dir(tmp_path):
    p = tmp_path / "capture"
    data = frames_data(4)
    for k, (rgb, raw) in enumerate(data):
        write_rgb(p / "rgb" / f"{k}.png", rgb)
        write_u16(p / "depth" / f"{k}.png", raw)
        lab = np.full((H, W), k % 3, np.uint8)
        lab[0, 0] = 255
        (p / "labels").mkdir(exist_ok=True)
        assert cv2.imwrite(str(p / "labels" / f"{k}.png"), lab)  # 8-bit: 255 is unlabelled
    (p / "classes.txt").write_text("wall\nfloor\nchair\n")
    (p / "intrinsics.txt").write_text("30 -28 15.5 10.5\n")  # fx fy cx cy, fy negative
    # 7 numbers per line: tx ty tz qx qy qz qw, line i = frame i.
    (p / "pose.txt").write_text("".join(f"{k} 0 0 0 0 0 1\n" for k in range(4)))
    return p, data


def test_folder_negative_fy_flips_rows_and_keeps_poses(folder_dir):
    p, data = folder_dir
    seq = D.open(p, depth_scale=2000)
    assert seq.format == "folder" and seq.class_names == ["wall", "floor", "chair"]
    f = seq[1]
    np.testing.assert_allclose(f.K, [[30, 0, 15.5], [0, 28, (H - 1) - 10.5], [0, 0, 1]])
    np.testing.assert_array_equal(f.rgb, data[1][0][::-1])
    np.testing.assert_allclose(f.depth, data[1][1][::-1] / 2000.0, rtol=1e-6)
    assert f.labels[-1, 0] == IGNORE_LABEL and f.labels[0, 0] == 1
    np.testing.assert_allclose(f.pose[:3, 3], [1, 0, 0])
    assert f.timestamp == pytest.approx(1 / 30)


def test_flipped_camera_gives_the_same_rays():
    # A point seen at pixel (u, v) with fy < 0 is, after the flip, at (u, H-1-v) with fy > 0.
    K = np.array([[30.0, 0, 15.5], [0, -28.0, 10.5], [0, 0, 1]])
    X = np.array([0.3, -0.2, 2.0])
    u, v, _ = K @ X / X[2]
    Kf = np.array([[30.0, 0, 15.5], [0, 28.0, (H - 1) - 10.5], [0, 0, 1]])
    uf, vf, _ = Kf @ X / X[2]
    assert uf == pytest.approx(u) and vf == pytest.approx((H - 1) - v)


def test_stride_range_max_frames_and_downscale(folder_dir):
    p, data = folder_dir
    seq = D.open(p, stride=2, frames=(1, None), max_frames=5, downscale=2)
    assert list(seq.indices) == [1, 3] and len(seq) == 2
    f = seq[-1]
    assert f.index == 3 and f.rgb.shape == (H // 2, W // 2, 3) and f.depth.shape == (H // 2, W // 2)
    # Scaling about pixel centres: c' = (c + 0.5) / 2 - 0.5.
    np.testing.assert_allclose(f.K, [[15, 0, 7.5], [0, 14, ((H - 1) - 10.5 + 0.5) / 2 - 0.5], [0, 0, 1]])
    flipped = data[3][1][::-1] / 1000.0
    np.testing.assert_allclose(f.depth, flipped[1::2, 1::2], rtol=1e-6)  # block-centre samples
    block = data[3][0][::-1].reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3))
    assert np.abs(f.rgb.astype(float) - block).max() <= 1
    with pytest.raises(IndexError):
        seq[2]
    with pytest.raises(DatasetError, match="downscale"):
        D.open(p, downscale=1.5)


def test_loading_is_lazy(folder_dir, monkeypatch):
    import legslam.datasets.folder as folder_mod

    p, _ = folder_dir
    calls = []
    real = folder_mod.read_depth
    monkeypatch.setattr(folder_mod, "read_depth", lambda path: calls.append(path) or real(path))
    seq = D.open(p)
    assert calls == []
    seq[2]
    assert [c.name for c in calls] == ["2.png"]


@pytest.mark.parametrize("fixture", ["tum_dir", "sevenscenes_dir", "folder_dir", "scannet_dir"])
def test_poses_and_timestamps_are_read_without_images(fixture, request):
    path = request.getfixturevalue(fixture)[0]
    full = list(D.open(path))  # frame k of a strided sequence is frame indices[k] of this
    seq = D.open(path, stride=2)

    def no_images(i):
        raise AssertionError(f"frame {i}'s images were read")

    seq._read = no_images
    for k, i in enumerate(seq.indices):
        assert (seq.pose(k) is None) == (full[i].pose is None)
        if full[i].pose is not None:
            np.testing.assert_array_equal(seq.pose(k), full[i].pose)
        assert seq.timestamp(k) == full[i].timestamp
    assert any(seq.pose(k) is not None for k in range(len(seq)))


# --- bad input ----------------------------------------------------------------------------

def test_nothing_recognised_lists_what_was_looked_for(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DatasetNotFoundError) as e:
        D.open(tmp_path)
    for what in ("rgb.txt", "traj.txt", "intrinsic/", "frame-XXXXXX", "depth/", ".bag", "metadata.yaml",
                 ".r3d", "rgb.mp4"):
        assert what in str(e.value)
    with pytest.raises(DatasetNotFoundError, match="missing does not exist"):
        D.open(tmp_path / "missing")
    with pytest.raises(DatasetNotFoundError, match="notes.txt: no dataset format recognised"):
        D.open(tmp_path / "notes.txt")  # a file, but no recording
    with pytest.raises(DatasetError, match="unknown dataset format"):
        D.open(tmp_path, format="kitti")


def test_corrupt_and_missing_images_name_the_file(folder_dir):
    p, _ = folder_dir
    (p / "depth" / "2.png").write_bytes(b"not a png")
    seq = D.open(p)
    with pytest.raises(DatasetError, match=r"depth[/\\]2\.png"):
        seq[2]
    (p / "rgb" / "3.png").unlink()
    with pytest.raises(DatasetError, match="pair up"):
        D.open(p)


def test_size_mismatch_nan_and_negative_depth(folder_dir):
    p, _ = folder_dir
    write_u16(p / "depth" / "1.png", np.ones((H + 2, W)))
    with pytest.raises(DatasetError, match="expected both"):
        D.open(p)[1]
    bad = np.ones((H, W), np.float32)
    bad[0, 0] = -1
    (p / "depth" / "0.png").unlink()
    np.save(p / "depth" / "0.npy", bad)
    with pytest.raises(DatasetError, match="negative"):
        D.open(p)[0]
    np.save(p / "depth" / "0.npy", np.full((H, W), np.nan, np.float32))
    with pytest.raises(DatasetError, match="NaN"):
        D.open(p)[0]
    nan_some = np.ones((H, W), np.float32)
    nan_some[1, 1] = np.nan
    np.save(p / "depth" / "0.npy", nan_some)
    d = D.open(p)[0].depth  # float depth is metres; NaN is the float way to say "invalid"
    assert d[H - 2, 1] == 0 and d[2, 2] == 1.0  # rows flipped: the fixture has fy < 0


def test_bad_poses_and_intrinsics(folder_dir):
    p, _ = folder_dir
    (p / "pose.txt").write_text("0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="1 poses for 4 frames"):
        D.open(p)
    (p / "pose.txt").write_text("".join("1 0 0 0 0 2 0 0 0 0 1 0 0 0 0 1\n" for _ in range(4)))
    with pytest.raises(DatasetError, match="not a rigid transform"):
        D.open(p)
    (p / "pose.txt").unlink()
    (p / "intrinsics.txt").unlink()
    with pytest.raises(DatasetNotFoundError, match="intrinsics="):
        D.open(p)
    assert D.open(p, intrinsics=(30, 30, 15.5, 11.5))[0].pose is None
    (p / "intrinsics.txt").write_text("30 0 nan 15\n")
    with pytest.raises(DatasetError, match="pinhole"):
        D.open(p)


def test_label_outside_classes_is_an_error(folder_dir):
    p, _ = folder_dir
    cv2.imwrite(str(p / "labels" / "0.png"), np.full((H, W), 7, np.uint8))
    with pytest.raises(DatasetError, match="classes.txt"):
        D.open(p)[0]


def test_tum_without_a_known_camera_warns(tum_dir):
    p, _ = tum_dir
    q = p.rename(p.parent / "my_recording")
    with pytest.warns(UserWarning, match="default camera"):
        seq = D.open(q)
    np.testing.assert_allclose(seq.K[0], [525, 0, 319.5])
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        D.open(q, intrinsics=(500, 500, 16, 12))  # given intrinsics: nothing to warn about
