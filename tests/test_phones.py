"""Phone captures: Stray Scanner exports (datasets.stray) and Record3D archives
(datasets.record3d), written here as the apps write them (tests/recordings.py) from the
built-in scene ray cast twice: colour at the camera's resolution, depth at the LiDAR's half
resolution. The loaders must give the depth as cast, the colour shrunk to it, the camera
scaled to it, and the poses (OpenCV axes) the scene was cast from, whatever axes the apps
wrote them in."""

from __future__ import annotations

import zipfile

import cv2
import numpy as np
import pytest
from recordings import synthetic_shots, write_r3d, write_stray

import legslam.datasets as D
from legslam.cli import main
from legslam.datasets import DatasetError
from legslam.datasets.synthetic import intrinsics

W, H = 160, 120  # colour; depth is W/2 x H/2
N = 6
FAST = ["--no-features", "--quiet", "--final-iters", "5"]


@pytest.fixture(scope="module")
def capture():
    """(colour shots, K of colour, depth shots at half resolution, their K, confidence maps)."""
    K = intrinsics(W, H)
    shots, _ = synthetic_shots(N, W, H, K=K)
    # The same camera at half the pixels, about pixel centres: u' = (u + 0.5) / 2 - 0.5.
    K_d = np.array([[K[0, 0] / 2, 0, (K[0, 2] + 0.5) / 2 - 0.5], [0, K[1, 1] / 2, (K[1, 2] + 0.5) / 2 - 0.5], [0, 0, 1]])
    depth, _ = synthetic_shots(N, W // 2, H // 2, K=K_d, poses=[s.pose for s in shots])
    rng = np.random.default_rng(1)
    confidence = [rng.choice([0, 1, 2], size=(H // 2, W // 2), p=[0.1, 0.2, 0.7]) for _ in range(N)]
    return shots, K, depth, K_d, confidence


def reprojection_error(a, b) -> float:
    """Median |z| difference (m) of frame a's depth moved into frame b by their poses and
    compared with b's depth there: small only when the poses place the cameras as they were."""
    v, u = np.nonzero(a.depth)
    z = a.depth[v, u]
    pa = np.stack([(u - a.K[0, 2]) / a.K[0, 0] * z, (v - a.K[1, 2]) / a.K[1, 1] * z, z, np.ones_like(z)])
    pb = np.linalg.inv(b.pose) @ a.pose @ pa
    ub = np.round(b.K[0, 0] * pb[0] / pb[2] + b.K[0, 2]).astype(int)
    vb = np.round(b.K[1, 1] * pb[1] / pb[2] + b.K[1, 2]).astype(int)
    inside = (pb[2] > 0) & (ub >= 0) & (ub < b.depth.shape[1]) & (vb >= 0) & (vb < b.depth.shape[0])
    zb = b.depth[vb[inside], ub[inside]]
    seen = zb > 0
    return float(np.median(np.abs(pb[2][inside][seen] - zb[seen])))


def check_frames(seq, capture, min_confidence: int) -> None:
    shots, K, depth, K_d, confidence = capture
    np.testing.assert_allclose(seq.K, K_d, atol=1e-9)
    assert (seq.width, seq.height) == (W // 2, H // 2) and len(seq) == N
    for k in range(N):
        f = seq[k]
        kept = confidence[k] >= min_confidence
        np.testing.assert_allclose(f.depth[kept], depth[k].depth[kept], atol=0.0005 + 1e-6)
        assert not f.depth[~kept].any()
        np.testing.assert_allclose(f.pose, shots[k].pose, atol=1e-5)
        assert f.timestamp == pytest.approx(shots[k].t, abs=1e-5)
    # The poses the scene was cast from (above), and the depth, camera and poses agree.
    assert reprojection_error(seq[0], seq[5]) < 0.015  # pixel rounding at 80x60


def test_a_stray_scanner_export(tmp_path, capture):
    shots, K, depth, _, confidence = capture
    p = write_stray(tmp_path / "stray", shots, K, depth, confidence)
    seq = D.open(p)
    assert seq.format == "stray"
    check_frames(seq, capture, 2)
    check_frames(D.open(p, min_confidence=1), capture, 1)
    # The colour: the video's frame (lossy mp4v) shrunk to the depth's size.
    want = cv2.resize(shots[4].rgb, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    assert np.abs(seq[4].rgb.astype(int) - want).mean() < 6
    # Frames read in any order are the same frames (the video seeks back, skips ahead).
    again = D.open(p)
    for k in (5, 1, 2, 0):
        np.testing.assert_array_equal(again[k].rgb, seq[k].rgb)


def test_a_stray_export_without_confidence_keeps_all_depth(tmp_path, capture, caplog):
    shots, K, depth, _, _ = capture
    seq = D.open(write_stray(tmp_path / "stray", shots, K, depth))
    np.testing.assert_allclose(seq[2].depth, depth[2].depth, atol=0.0005 + 1e-6)
    assert "no confidence/ folder, so all depth is used" in caplog.text


def test_a_record3d_archive(tmp_path, capture):
    shots, K, depth, _, confidence = capture
    p = write_r3d(tmp_path / "scan.r3d", shots, K, depth, confidence)
    seq = D.open(p)
    assert seq.format == "record3d" and seq.name == "scan"
    check_frames(seq, capture, 2)
    jpeg = cv2.imdecode(cv2.imencode(".jpg", shots[1].rgb[..., ::-1])[1], cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(seq[1].rgb, cv2.resize(jpeg, (W // 2, H // 2), interpolation=cv2.INTER_AREA))


def test_record3d_nan_depth_is_invalid_and_a_cut_archive_is_named(tmp_path, capture):
    shots, K, depth, _, _ = capture
    holes = [type(d)(d.rgb, np.where(np.arange(d.depth.size).reshape(d.depth.shape) % 7 == 0, np.nan, d.depth)
                     .astype(np.float32), d.t, d.pose) for d in depth]
    seq = D.open(write_r3d(tmp_path / "holes.r3d", shots, K, holes))
    f = seq[0]
    assert np.isfinite(f.depth).all() and (f.depth == 0).sum() == np.isnan(holes[0].depth).sum()
    data = (tmp_path / "holes.r3d").read_bytes()
    cut = tmp_path / "cut.r3d"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=f"cannot read {cut} as a Record3D export"):
        D.open(cut)
    with zipfile.ZipFile(tmp_path / "small.r3d", "w") as z:  # depth of another size than dw x dh
        z.writestr("metadata", '{"w": 160, "h": 120, "dw": 80, "dh": 60, "K": [128, 0, 0, 0, 128, 0, 79.5, 59.5, 1]}')
        z.writestr("rgbd/0.jpg", cv2.imencode(".jpg", shots[0].rgb)[1].tobytes())
        import lzfse
        z.writestr("rgbd/0.depth", lzfse.compress(np.zeros((30, 40), np.float32).tobytes()))
    with pytest.raises(DatasetError, match="rgbd/0.depth holds 1200 values, not the 80x60 of the depth"):
        D.open(tmp_path / "small.r3d")[0]


@pytest.mark.parametrize("kind", ["stray", "record3d"])
def test_legslam_run_on_a_phone_capture_scores_against_its_poses(tmp_path, capture, capsys, kind):
    shots, K, depth, _, confidence = capture
    p = (write_stray(tmp_path / "stray", shots, K, depth, confidence) if kind == "stray"
         else write_r3d(tmp_path / "scan.r3d", shots, K, depth, confidence))
    out = tmp_path / "run"
    assert main(["run", str(p), "--out", str(out), "--min-confidence", "1", *FAST]) == 0
    assert "ATE RMSE" in capsys.readouterr().out  # the phone's poses are the ground truth
