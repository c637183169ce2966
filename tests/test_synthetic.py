"""The built-in scene: deterministic, readable by the loader, geometrically exact (depth is
z-depth consistent with the poses and the room's known planes), photometrically consistent
across views, labelled, and moving like a hand-held camera."""

from __future__ import annotations

import filecmp
import os

import numpy as np
import pytest

import legslam.datasets as D
from legslam.datasets import synthetic as S
from legslam.eval import depth_reprojection


def world_points(frame) -> np.ndarray:
    """HxWx3 world points of a frame's depth, back-projected by hand."""
    K, h, w = frame.K, *frame.depth.shape
    v, u = np.mgrid[0:h, 0:w]
    z = frame.depth
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    return cam @ frame.pose[:3, :3].T + frame.pose[:3, 3]


def test_same_seed_same_bytes_other_seed_other_scene(small_synthetic, tmp_path):
    again = S.generate(tmp_path / "again", n_frames=12, width=160, height=120, seed=0)
    names = ["camera.json", "classes.txt", "groundtruth.txt", "color/000011.png", "depth/000005.png",
             "labels/000000.png"]
    match, mismatch, errors = filecmp.cmpfiles(small_synthetic, again, names, shallow=False)
    assert mismatch == [] and errors == []
    other = S.generate(tmp_path / "other", n_frames=2, width=160, height=120, seed=1)
    assert not filecmp.cmp(small_synthetic / "color/000000.png", other / "color/000000.png", shallow=False)


def test_reads_back_through_open(small_synthetic):
    seq = D.open(small_synthetic)
    assert seq.format == "folder" and len(seq) == 12 and (seq.width, seq.height) == (160, 120)
    assert seq.class_names == S.CLASS_NAMES
    f = seq[3]
    assert f.rgb.dtype == np.uint8 and f.rgb.shape == (120, 160, 3)
    assert (f.depth > 0).all()  # a closed room: every ray hits something
    assert f.pose is not None and f.timestamp == pytest.approx(3 / 30)
    np.testing.assert_allclose(f.K, [[128, 0, 79.5], [0, 128, 59.5], [0, 0, 1]])
    seen = np.unique(np.concatenate([seq[i].labels.ravel() for i in range(0, 12, 4)]))
    for name in ("wall", "floor", "table", "chair"):
        assert S.CLASS_NAMES.index(name) in seen


def test_depth_is_z_depth_on_the_known_room_planes(small_synthetic):
    # Floor pixels back-project to z = 0, ceiling to the room height, walls to their planes,
    # to within the 16-bit depth quantisation: only right if depth is z-depth (not ray
    # length) and the poses are camera-to-world in OpenCV axes.
    f = D.open(small_synthetic)[7]
    X = world_points(f)
    floor = f.labels == S.CLASS_NAMES.index("floor")
    wall = f.labels == S.CLASS_NAMES.index("wall")
    assert floor.sum() > 100 and wall.sum() > 100
    assert np.abs(X[floor][:, 2]).max() < 2e-3
    to_wall = np.min(np.abs(np.concatenate([X[wall][:, :2] - S.ROOM_MIN[:2], X[wall][:, :2] - S.ROOM_MAX[:2]], 1)), 1)
    assert to_wall.max() < 2e-3


def test_depth_agrees_between_frames(small_synthetic):
    seq = D.open(small_synthetic)
    r = depth_reprojection(seq[0], seq[8])
    # Nearest-pixel lookup at 160x120 costs a few mm on slanted surfaces; wrong intrinsics or
    # pose conventions cost decimetres.
    assert r["median_cm"] < 1.0 and r["within"] > 0.9 and r["overlap"] > 0.8


def test_colour_is_the_same_from_every_view(small_synthetic):
    # Lambertian shading under fixed lights: a surface point keeps its colour across frames.
    seq = D.open(small_synthetic)
    a, b = seq[0], seq[6]
    X = world_points(a).reshape(-1, 3)
    Xb = (X - b.pose[:3, 3]) @ b.pose[:3, :3]
    u = np.round(b.K[0, 0] * Xb[:, 0] / Xb[:, 2] + b.K[0, 2]).astype(int)
    v = np.round(b.K[1, 1] * Xb[:, 1] / Xb[:, 2] + b.K[1, 2]).astype(int)
    ok = (u >= 0) & (u < 160) & (v >= 0) & (v < 120)
    ok[ok] &= np.abs(b.depth[v[ok], u[ok]] - Xb[ok, 2]) < 0.01  # visible in b, not occluded
    diff = np.abs(a.rgb.reshape(-1, 3)[ok].astype(int) - b.rgb[v[ok], u[ok]].astype(int))
    assert ok.mean() > 0.6 and np.median(diff) <= 2


def test_camera_moves_like_a_hand_held_one_inside_the_room():
    poses = S.camera_path(100, np.random.default_rng(0))
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    deg = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert 0.01 <= step.min() and step.max() <= 0.03
    assert 0.2 <= deg.min() and deg.max() <= 1.5 and deg.mean() >= 0.4
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1)
    pos = poses[:, :3, 3]
    assert (pos > S.ROOM_MIN + 0.5).all() and (pos < S.ROOM_MAX - 0.5).all()
    # Clear of all furniture: outside every part's bounding box by 0.3 m.
    for p in S.build_scene(np.random.default_rng(0)):
        lo, hi = S._bounds(p).min(0) - 0.3, S._bounds(p).max(0) + 0.3
        assert not ((pos > lo) & (pos < hi)).all(1).any(), p


def test_default_scene_is_generated_once_and_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("LEGSLAM_CACHE", str(tmp_path))
    p = S.default_scene(n_frames=2, width=32, height=24)
    assert p.parent.parent == tmp_path and (p / "scene.json").is_file()
    assert all((f.depth > 0).all() for f in D.open(p))
    stamp = os.stat(p / "color" / "000000.png").st_mtime_ns
    assert S.default_scene(n_frames=2, width=32, height=24) == p
    assert os.stat(p / "color" / "000000.png").st_mtime_ns == stamp
    assert [q.name for q in p.parent.iterdir()] == [p.name]  # no temporary folder left behind
    assert S.default_scene(n_frames=3, width=32, height=24) != p  # other parameters, other scene


def test_generate_replaces_an_old_scene_but_not_other_files(tmp_path):
    S.generate(tmp_path / "scene", n_frames=3, width=32, height=24)
    S.generate(tmp_path / "scene", n_frames=2, width=32, height=24)
    assert len(D.open(tmp_path / "scene")) == 2
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="not empty"):
        S.generate(tmp_path / "mine", n_frames=2, width=32, height=24)
