"""Metrics against hand-computed cases and, where installed, the reference libraries
(evo for ATE/RPE and TUM files, scikit-image for PSNR/SSIM)."""

from __future__ import annotations

import numpy as np
import pytest

import legslam.eval as E
from legslam.eval import TrajectoryError


def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def random_trajectory(n: int, rng) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = random_rotation(rng)
        T[i, :3, 3] = rng.normal(size=3)
    return T


def transformed(poses: np.ndarray, R, t, s=1.0) -> np.ndarray:
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    return out


# --- trajectories: hand cases -------------------------------------------------------------

def test_ate_hand_case_without_alignment():
    gt = np.tile(np.eye(4), (2, 1, 1))
    est = gt.copy()
    est[0, :3, 3] = [3, 0, 0]
    est[1, :3, 3] = [0, 4, 0]
    r = E.ate(gt, est, align="none")
    assert r["rmse"] == pytest.approx(np.sqrt((9 + 16) / 2))
    assert r["mean"] == pytest.approx(3.5) and r["max"] == pytest.approx(4) and r["min"] == pytest.approx(3)


def test_ate_alignment_removes_rigid_and_similarity_transforms():
    rng = np.random.default_rng(0)
    gt = random_trajectory(20, rng)
    R, t = random_rotation(rng), np.array([1.0, -2.0, 0.5])
    assert E.ate_rmse(gt, transformed(gt, R, t)) == pytest.approx(0, abs=1e-9)
    scaled = transformed(gt, R, t, s=2.5)
    assert E.ate_rmse(gt, scaled, align="sim3") == pytest.approx(0, abs=1e-9)
    assert E.ate_rmse(gt, scaled, align="se3") > 0.5
    r = E.ate(gt, scaled, align="sim3")
    assert r["scale"] == pytest.approx(1 / 2.5)
    np.testing.assert_allclose(r["aligned"], gt, atol=1e-9)


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    R, t, s = random_rotation(rng), rng.normal(size=3), 0.7
    R2, t2, s2 = E.umeyama(src, s * src @ R.T + t, with_scale=True)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-10)
    assert s2 == pytest.approx(s)


def test_rpe_hand_case():
    # gt moves 1 m along x per frame; est moves 1 m then 2 m: relative errors 0 and 1 m.
    gt = np.tile(np.eye(4), (3, 1, 1))
    gt[:, 0, 3] = [0, 1, 2]
    est = gt.copy()
    est[:, 0, 3] = [0, 1, 3]
    r = E.rpe(gt, est)
    assert r["trans"]["rmse"] == pytest.approx(np.sqrt(0.5)) and r["rot"]["max"] == pytest.approx(0)
    assert E.rpe(gt, est, delta=2)["trans"]["n"] == 1  # pairs (0, 2) only, as evo's default
    assert E.rpe(gt, est, delta=1, all_pairs=True)["trans"]["n"] == 2


def test_tum_round_trip_and_association(tmp_path):
    rng = np.random.default_rng(2)
    poses = random_trajectory(5, rng)
    stamps = np.arange(5) * 0.1 + 100.0
    E.write_tum(tmp_path / "a.txt", stamps, poses)
    t, p = E.read_tum(tmp_path / "a.txt")
    np.testing.assert_allclose(t, stamps)
    np.testing.assert_allclose(p, poses, atol=1e-8)
    ia, ib = E.associate(np.array([1.0, 2.0, 3.0]), np.array([0.995, 2.5, 3.004, 3.009]))
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 1 + 1]


def test_trajectory_errors(tmp_path):
    gt = np.tile(np.eye(4), (4, 1, 1))
    with pytest.raises(TrajectoryError, match="4 ground-truth poses but 3"):
        E.ate_rmse(gt, gt[:3])
    with pytest.raises(ValueError, match="align"):
        E.ate_rmse(gt, gt, align="sim2")
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(TrajectoryError, match="bad.txt:1"):
        E.read_tum(tmp_path / "bad.txt")
    E.write_tum(tmp_path / "a.txt", [0, 1, 2], gt[:3])
    E.write_tum(tmp_path / "b.txt", [10, 11, 12], gt[:3])
    with pytest.raises(TrajectoryError, match="no timestamps"):
        E.ate_rmse(tmp_path / "a.txt", tmp_path / "b.txt")


# --- trajectories: evo as the reference ---------------------------------------------------

def _noisy_pair(tmp_path, rng):
    """A smooth gt and a scaled, moved, noisy estimate that starts later with jittered stamps."""
    import cv2

    n = 60
    gt = np.tile(np.eye(4), (n, 1, 1))
    for i, a in enumerate(np.linspace(0, 2, n)):
        gt[i, :3, :3] = cv2.Rodrigues(np.array([0.1 * a, 0.3 * a, a]))[0]
        gt[i, :3, 3] = [np.cos(a), np.sin(a), 0.1 * a]
    est = transformed(gt, random_rotation(rng), rng.normal(size=3), s=1.3)
    est[:, :3, 3] += 0.02 * rng.normal(size=(n, 3))
    for i in range(n):
        est[i, :3, :3] = est[i, :3, :3] @ cv2.Rodrigues(0.01 * rng.normal(size=3))[0]
    t_gt = np.arange(n) / 30.0
    t_est = t_gt[5:] + rng.uniform(-0.004, 0.004, n - 5)
    E.write_tum(tmp_path / "gt.txt", t_gt, gt)
    E.write_tum(tmp_path / "est.txt", t_est, est[5:])
    return tmp_path / "gt.txt", tmp_path / "est.txt"


def _evo_pair(tmp_path, seed):
    """Our files and evo's associated reading of them."""
    pytest.importorskip("evo", reason="evo (the reference for ATE and RPE) is not installed")
    from evo.core import sync
    from evo.tools import file_interface

    gt_file, est_file = _noisy_pair(tmp_path, np.random.default_rng(seed))
    ref = file_interface.read_tum_trajectory_file(str(gt_file))
    est = file_interface.read_tum_trajectory_file(str(est_file))
    return (gt_file, est_file, *sync.associate_trajectories(ref, est, max_diff=0.01))


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_ate_matches_evo(tmp_path, align):
    gt_file, est_file, ref, est = _evo_pair(tmp_path, 3)
    from evo.core import metrics

    est.align(ref, correct_scale=align == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ours = E.ate(gt_file, est_file, align=align)
    assert ours["n"] == ref.num_poses
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[key] == pytest.approx(ape.get_statistic(getattr(metrics.StatisticsType, key)), rel=1e-9)


@pytest.mark.parametrize("all_pairs", [False, True])
def test_rpe_matches_evo(tmp_path, all_pairs):
    gt_file, est_file, ref, est = _evo_pair(tmp_path, 4)
    from evo.core import metrics

    ours = E.rpe(gt_file, est_file, delta=2, all_pairs=all_pairs)
    for relation, key in ((metrics.PoseRelation.translation_part, "trans"),
                          (metrics.PoseRelation.rotation_angle_deg, "rot")):
        rpe = metrics.RPE(relation, delta=2, delta_unit=metrics.Unit.frames, all_pairs=all_pairs)
        rpe.process_data((ref, est))
        assert ours[key]["rmse"] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)


def test_written_tum_reads_back_in_evo(tmp_path):
    pytest.importorskip("evo", reason="evo (the reference TUM reader) is not installed")
    from evo.tools import file_interface

    poses = random_trajectory(10, np.random.default_rng(5))
    E.write_tum(tmp_path / "t.txt", np.arange(10.0), poses)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    np.testing.assert_allclose(np.array(traj.poses_se3), poses, atol=1e-8)


# --- images -------------------------------------------------------------------------------

def test_psnr_hand_case():
    a = np.zeros((8, 8, 3), np.uint8)
    assert E.psnr(a, a + 10) == pytest.approx(10 * np.log10(255 ** 2 / 100))
    assert E.psnr(a, a) == float("inf")
    assert E.psnr(a / 255.0, (a + 51) / 255.0) == pytest.approx(10 * np.log10(1 / 0.04))
    with pytest.raises(ValueError, match="same kind"):
        E.psnr(a, a / 255.0)


def test_ssim_hand_case_constant_images():
    # Constant images: variances vanish, SSIM = (2 m1 m2 + C1) / (m1^2 + m2^2 + C1) * C2 / C2.
    a, b = np.full((20, 20), 100, np.uint8), np.full((20, 20), 150, np.uint8)
    c1 = (0.01 * 255) ** 2
    assert E.ssim(a, b) == pytest.approx((2 * 100 * 150 + c1) / (100 ** 2 + 150 ** 2 + c1))
    assert E.ssim(a, a) == pytest.approx(1.0)


def test_psnr_ssim_match_skimage():
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image (the SSIM/PSNR reference) is not installed")
    import cv2

    rng = np.random.default_rng(6)
    a = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (5, 5), 1.0)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    ref = skm.structural_similarity(a, b, data_range=255, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
    assert E.ssim(a, b) == pytest.approx(ref, abs=1e-9)
    af, bf = a / 255.0, b / 255.0
    ref = skm.structural_similarity(af[..., 0], bf[..., 0], data_range=1.0, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
    assert E.ssim(af[..., 0], bf[..., 0]) == pytest.approx(ref, abs=1e-9)
    assert E.psnr(a, b) == pytest.approx(skm.peak_signal_noise_ratio(a, b, data_range=255))


def test_depth_l1_hand_case():
    gt = np.array([[1.0, 2.0], [0.0, np.nan]])
    pred = np.array([[1.1, 0.0], [5.0, 3.0]])
    assert E.depth_l1_cm(pred, gt) == pytest.approx((10 + 200) / 2)  # an empty prediction counts
    with pytest.raises(ValueError, match="non-finite"):
        E.depth_l1_cm(np.array([[np.nan, 1], [1, 1]]), gt)
    assert E.depth_l1_cm(pred, np.zeros((2, 2))) is None  # no valid ground truth: no figure


def test_view_scores_average_each_figure_over_the_views_that_have_it():
    rng = np.random.default_rng(3)
    rgb = [rng.integers(0, 256, (16, 16, 3), dtype=np.uint8) for _ in range(2)]
    color = [np.clip(c / 255.0 + rng.normal(0, 0.05, c.shape), 0, 1) for c in rgb]
    depth = [np.full((16, 16), 2.0), np.zeros((16, 16))]  # the second frame has no valid depth
    scores = E.ViewScores()
    assert scores.means() == {"psnr": None, "ssim": None, "depth_l1_cm": None}
    for c, r, d in zip(color, rgb, depth):
        scores.add(c, np.full((16, 16), 2.1), r, d)
    means = scores.means()
    assert means["psnr"] == pytest.approx(np.mean([E.psnr(c, r / 255.0) for c, r in zip(color, rgb)]))
    assert means["ssim"] == pytest.approx(np.mean([E.ssim(c, r / 255.0) for c, r in zip(color, rgb)]))
    assert means["depth_l1_cm"] == pytest.approx(10.0)  # the first frame's alone


def test_lpips_without_its_network_says_so():
    try:
        import lpips  # noqa: F401
    except ImportError:
        with pytest.raises(E.MetricUnavailable, match="offline"):
            E.lpips(np.zeros((16, 16, 3), np.uint8), np.zeros((16, 16, 3), np.uint8))
    else:
        pytest.skip("the lpips package is installed here")


# --- semantics ----------------------------------------------------------------------------

def test_segmentation_hand_case():
    gt = np.array([[0, 0, 1, 1], [2, 2, -1, -1]])
    pred = np.array([[0, 1, 1, 1], [2, -1, 0, 3]])
    r = E.segmentation_metrics(pred, gt, num_classes=4)
    # class 0: TP 1, FN 1, FP 0 -> IoU 1/2; class 1: TP 2, FP 1 -> 2/3; class 2: TP 1, FN 1
    # (predicted "nothing") -> 1/2; class 3 occurs nowhere that counts -> NaN.
    np.testing.assert_allclose(r["iou"][:3], [1 / 2, 2 / 3, 1 / 2])
    assert np.isnan(r["iou"][3]) and np.isnan(r["acc"][3])
    assert r["miou"] == pytest.approx((1 / 2 + 2 / 3 + 1 / 2) / 3)
    np.testing.assert_allclose(r["acc"][:3], [1 / 2, 1, 1 / 2])
    assert r["macc"] == pytest.approx(2 / 3) and r["pixel_acc"] == pytest.approx(4 / 6)
    assert E.miou(gt, gt, 4) == 1.0
    with pytest.raises(ValueError, match="outside"):
        E.segmentation_metrics(pred + 10, gt, num_classes=4)


def test_segmentation_counts_over_views_equal_the_metrics_of_all_pixels_at_once():
    rng = np.random.default_rng(0)
    gts = [rng.integers(-1, 5, (6, 7)) for _ in range(3)]
    preds = [rng.integers(-1, 5, (6, 7)) for _ in range(3)]
    counts = E.SegmentationCounts(5)
    for p, g in zip(preds, gts):
        counts.add(p, g)
    whole = E.segmentation_metrics(np.concatenate(preds), np.concatenate(gts), 5)
    summed = counts.metrics()
    np.testing.assert_array_equal(summed["confusion"], whole["confusion"])
    np.testing.assert_allclose(summed["iou"], whole["iou"])
    assert summed["miou"] == whole["miou"] and summed["pixel_acc"] == whole["pixel_acc"]
    with pytest.raises(ValueError, match="every ground-truth pixel is ignored"):
        E.SegmentationCounts(5).add(preds[0], np.full((6, 7), -1)).metrics()


# --- geometry check -----------------------------------------------------------------------

def test_depth_reprojection_on_a_plane():
    from legslam.datasets import Frame

    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 2.0, np.float32)
    a = Frame(rgb=None, depth=depth, K=K, pose=np.eye(4), timestamp=0, index=0)
    T = np.eye(4)
    T[0, 3] = 0.2  # sideways: a fronto-parallel plane keeps its depth
    b = Frame(rgb=None, depth=depth, K=K, pose=T, timestamp=0, index=1)
    r = E.depth_reprojection(a, b)
    assert r["median_cm"] == pytest.approx(0, abs=1e-6) and r["within"] == 1.0
    assert r["overlap"] == pytest.approx(59 / 64, abs=0.02)  # 0.2 m at 2 m is 5 px of 64 out of view
    assert r["colour_l1"] is None  # frames without colour
    b.depth = depth + 0.1
    assert E.depth_reprojection(a, b)["median_cm"] == pytest.approx(10, abs=1e-4)
    # Colour that varies along x: a pixel lands 5 columns to the left in b, 5 levels apart.
    ramp = np.repeat(np.arange(64, dtype=np.uint8)[None, :, None], 48, 0).repeat(3, 2)
    a.rgb, b.rgb = ramp, ramp
    assert E.depth_reprojection(a, b)["colour_l1"] == pytest.approx(5, abs=1e-9)


def test_view_agreement_ranks_the_true_poses_first_wherever_the_trajectory_is_anchored(small_synthetic):
    import cv2

    from legslam.datasets import open as open_dataset

    seq = open_dataset(small_synthetic)
    true = np.stack([seq[i].pose for i in range(len(seq))])
    rng = np.random.default_rng(3)
    # Each pose off by ~2 cm and ~1 degree, as a drifting tracker's would be.
    off = true.copy()
    for p in off:
        p[:3, :3] = p[:3, :3] @ cv2.Rodrigues(rng.normal(0, 0.01, 3))[0]
        p[:3, 3] += rng.normal(0, 0.012, 3)
    got = E.view_agreement(seq, {"true": true, "off": off}, every=1)
    assert got["true"][0] == got["off"][0] >= 10  # the same pairs, chosen by the first trajectory
    assert got["true"][1] < 0.5 * got["off"][1]  # depth disagreement (cm)
    assert got["true"][2] < got["off"][2]  # colour difference where the surfaces meet
    # Only relative poses enter: the whole trajectory moved and turned changes nothing.
    R, t = cv2.Rodrigues(np.array([0.2, 0.5, -0.1]))[0], np.array([0.3, -0.2, 1.0])
    moved = E.view_agreement(seq, {"true": transformed(true, R, t), "off": transformed(off, R, t)}, every=1)
    for name in got:
        assert moved[name][0] == got[name][0]
        np.testing.assert_allclose(moved[name][1:], got[name][1:], rtol=1e-6)
    # A span keeps every pair inside it: frames 3, 4 and 5 of range(0, 6).
    assert E.view_agreement(seq, {"true": true}, every=1, frames=range(0, 6))["true"][0] == 3
