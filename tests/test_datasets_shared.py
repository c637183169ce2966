"""Loaders on the real sequences in ../shared/data: each must reproduce what the folder's
SOURCE.md states (intrinsics, depth scale, invalid values, pose convention). The pose
convention is checked by reprojecting one frame's depth into another with the loaded poses;
the SOURCE.md numbers are the reference."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_path

import legslam.datasets as D
from legslam.eval import depth_reprojection

ICL_CAMERA = (481.2, -480.0, 319.5, 239.5)  # from ICL-NUIM via SOURCE.md; the folder has no camera file


def test_sevenscenes_matches_source_md():
    p = shared_path("data", "7scenes_tsdf_fusion", "data")
    seq = D.open(p, intrinsics=(585.0, 585.0, 320.0, 240.0))  # read as it is, not registered
    assert seq.format == "7scenes" and len(seq) == 1000 and (seq.width, seq.height) == (640, 480)
    assert not seq.registers_depth
    f0, f10 = seq[0], seq[10]
    valid = f0.depth[f0.depth > 0]
    assert 0.79 <= valid.min() and valid.max() <= 3.99  # 0.80 to 3.98 m; 65535 became 0
    assert 0.05 < (f0.depth == 0).mean() < 0.2  # ~11 % invalid
    r = depth_reprojection(f0, f10)  # SOURCE.md: median 0.4-0.6 cm, 95-99 % within 5 cm
    assert r["median_cm"] < 1.0 and r["within"] > 0.95


def test_sevenscenes_depth_is_registered_to_the_colour_camera():
    p = shared_path("data", "7scenes_tsdf_fusion", "data")
    seq, raw = D.open(p), D.open(p, intrinsics=(585.0, 585.0, 320.0, 240.0))
    assert seq.registers_depth
    np.testing.assert_allclose(seq.K, [[525, 0, 320], [0, 525, 240], [0, 0, 1]])
    f0 = seq[0]
    valid = f0.depth[f0.depth > 0]
    assert 0.78 <= valid.min() and valid.max() <= 4.0
    # The depth camera's narrower view leaves the colour image's border without depth.
    assert 0.2 < (f0.depth == 0).mean() < 0.35 and f0.depth[:, :5].max() == 0
    # Geometry still agrees between frames, and colour now lies on its own surface: projected
    # into another frame through its depth, it meets that frame's colour more closely.
    for a, b in ((0, 30), (100, 140), (300, 340), (700, 740)):
        r, r_raw = depth_reprojection(seq[a], seq[b]), depth_reprojection(raw[a], raw[b])
        assert r["median_cm"] < 1.1 * r_raw["median_cm"] + 0.1 and r["within"] > 0.95 * r_raw["within"]
        assert r["colour_l1"] < 0.9 * r_raw["colour_l1"], (a, b, r["colour_l1"], r_raw["colour_l1"])
    # Poses are the colour camera's: the depth camera's moved by the fixed rig offset.
    lever = np.linalg.inv(raw.pose(0)) @ seq.pose(0)
    assert 0.02 < np.linalg.norm(lever[:3, 3]) < 0.03
    np.testing.assert_allclose(np.linalg.inv(raw.pose(500)) @ seq.pose(500), lever, atol=1e-9)


def test_sevenscenes_stride_and_downscale_keep_geometry():
    seq = D.open(shared_path("data", "7scenes_tsdf_fusion", "data"), frames=(500, 530), stride=10, downscale=2)
    assert [f.index for f in seq] == [500, 510, 520]
    a, c = seq[0], seq[2]
    assert a.depth.shape == (240, 320)
    r = depth_reprojection(a, c)
    assert r["median_cm"] < 1.5 and r["within"] > 0.9


def test_replica_reads_cam_params_from_parent_and_poses_are_c2w():
    seq = D.open(shared_path("data", "replica_office0_nvblox", "office0"))
    assert seq.format == "replica" and len(seq) == 4
    assert seq.camera_file.name == "cam_params.json" and seq.camera_file.parent.name == "replica_office0_nvblox"
    np.testing.assert_allclose(seq.K, [[600, 0, 599.5], [0, 600, 339.5], [0, 0, 1]])
    f0, f3 = seq[0], seq[3]
    d = f0.depth[f0.depth > 0]
    assert 1.0 < d.min() and d.max() < 3.7  # 1.06 to 3.63 m with scale 6553.5
    r = depth_reprojection(f0, f3)  # SOURCE.md: median 0.06 cm, 99.8 % within 5 cm
    assert r["median_cm"] < 0.2 and r["within"] > 0.99


def test_iclnuim_negative_fy_is_needed_and_handled():
    p = shared_path("data", "iclnuim_slambook2")
    seq = D.open(p, intrinsics=ICL_CAMERA, depth_scale=5000)
    assert seq.format == "folder" and len(seq) == 5
    np.testing.assert_allclose(seq.K, [[481.2, 0, 319.5], [0, 480, 239.5], [0, 0, 1]])
    r = depth_reprojection(seq[0], seq[1])  # SOURCE.md: median 4.2 cm, 64 % within 5 cm
    assert r["median_cm"] < 6 and r["within"] > 0.55
    wrong = D.open(p, intrinsics=(481.2, 480.0, 319.5, 239.5), depth_scale=5000)
    assert depth_reprojection(wrong[0], wrong[1])["median_cm"] > 20  # SOURCE.md: 47 cm


def test_parent_folder_error_points_at_the_sequence(shared_dir):
    with pytest.raises(D.DatasetNotFoundError, match="office0 \\(replica\\)"):
        D.open(shared_path("data", "replica_office0_nvblox"))
