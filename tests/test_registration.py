"""Depth registered to the colour camera (datasets.registration, in the engine), against a
plain pixel-by-pixel reference."""

from __future__ import annotations

import numpy as np
import pytest

from legslam.datasets.base import make_K
from legslam.datasets.registration import register_depth


def plain_register(depth, K_d, K_c, T, size):
    """Pixel by pixel: lift, move, project, keep the nearest."""
    w, h = size
    out = np.zeros((h, w), np.float64)
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            z = float(depth[v, u])
            if z <= 0:
                continue
            x = np.array([(u - K_d[0, 2]) / K_d[0, 0] * z, (v - K_d[1, 2]) / K_d[1, 1] * z, z])
            p = T[:3, :3] @ x + T[:3, 3]
            if p[2] <= 0:
                continue
            uc = int(np.floor(K_c[0, 0] * p[0] / p[2] + K_c[0, 2] + 0.5))  # halves round up
            vc = int(np.floor(K_c[1, 1] * p[1] / p[2] + K_c[1, 2] + 0.5))
            if 0 <= uc < w and 0 <= vc < h and (out[vc, uc] == 0 or p[2] < out[vc, uc]):
                out[vc, uc] = p[2]
    return out


def small_rotation(rng, angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_an_identical_camera_leaves_depth_as_it_is():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (30, 40)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0
    K = make_K(35.0, 36.0, 19.5, 14.5)
    np.testing.assert_array_equal(register_depth(depth, K, K, np.eye(4), (40, 30)), depth)


def test_a_plane_seen_from_a_camera_beside_it_shifts_by_the_parallax():
    # A wall 2000 mm away, the colour camera 50 mm to the right (+x): the wall keeps its
    # depth and its left edge moves left by f * 50 / 2000 = 10 pixels.
    depth = np.zeros((40, 80), np.uint16)
    depth[:, 30:] = 2000
    K = make_K(400.0, 400.0, 39.5, 19.5)
    T = np.eye(4)
    T[0, 3] = -50.0  # colour point = depth point - camera offset
    out = register_depth(depth, K, K, T, (80, 40))
    assert out.dtype == np.uint16
    assert set(np.unique(out)) == {0, 2000}
    assert (out[:, 20:70] == 2000).all() and (out[:, :20] == 0).all()


@pytest.mark.parametrize("seed", range(4))
def test_matches_the_pixel_by_pixel_reference(seed):
    rng = np.random.default_rng(seed)
    h, w = 24, 32
    depth = rng.uniform(0.8, 3.0, (h, w)).astype(np.float32)  # the engine's precision
    depth[rng.random((h, w)) < 0.15] = 0
    depth[5:12, 8:20] = rng.uniform(0.3, 0.5)  # a near box that hides what is behind it
    K_d = make_K(30.0, 30.0, 15.5, 11.5)
    # A shorter colour focal length packs several depth pixels into one: the nearest must win.
    K_c = make_K(rng.uniform(18, 30), rng.uniform(18, 30), rng.uniform(14, 18), rng.uniform(10, 13))
    T = np.eye(4)
    T[:3, :3] = small_rotation(rng, 0.03)
    T[:3, 3] = rng.normal(0, 0.05, 3)
    out = register_depth(depth, K_d, K_c, T, (w + 4, h + 2))
    ref = plain_register(depth, K_d, K_c, T, (w + 4, h + 2))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, ref, rtol=1e-6)
    assert (ref > 0).mean() > 0.3  # not an empty case


def test_integer_depth_is_rounded_and_a_surface_behind_the_camera_is_dropped():
    depth = np.full((4, 4), 1000, np.uint16)
    K = make_K(4.0, 4.0, 1.5, 1.5)
    T = np.eye(4)
    T[2, 3] = 0.4  # 0.4 mm further away: rounds back to 1000
    np.testing.assert_array_equal(register_depth(depth, K, K, T, (4, 4)), depth)
    T[2, 3] = -2000.0  # the colour camera 2 m in front of the wall
    assert not register_depth(depth, K, K, T, (4, 4)).any()
