"""The rasterizer through its Python binding: images and gradients against closed forms, and
bad input. (Every gradient is checked against finite differences in f64 in the Rust tests.)"""

import numpy as np
import pytest

import legslam

K = np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]])
W, H = 64, 48


def scene(n=40, k=6, seed=0, coeffs=1):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2, 4, n)
    means = np.c_[rng.uniform(-0.35, 0.35, n) * z, rng.uniform(-0.25, 0.25, n) * z, z]
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return dict(
        means=means.astype(np.float32),
        log_scales=rng.uniform(-3, -2, (n, 3)).astype(np.float32),
        quats=q.astype(np.float32),
        opacity_logits=rng.uniform(-1, 2, n).astype(np.float32),
        sh=rng.normal(0, 0.4, (n, coeffs, 3)).astype(np.float32),
        features=rng.normal(size=(n, k)).astype(np.float32),
    )


def test_single_gaussian_matches_closed_form():
    # An isotropic Gaussian of std s at depth z straight ahead projects to a 2D Gaussian of
    # variance (f s / z)^2 + 0.3 (the low-pass dilation) centred on the principal point.
    s, z, logit = 0.05, 2.0, 1.5
    g = dict(means=[[0, 0, z]], log_scales=[[np.log(s)] * 3], quats=[[1, 0, 0, 0]],
             opacity_logits=[logit], sh=[[0.3, -0.2, 0.1]], features=[[1.0, -2.0]])
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)
    var = (80 * s / z) ** 2 + 0.3
    o = 1 / (1 + np.exp(-logit))
    ys, xs = np.mgrid[0:H, 0:W]
    a = o * np.exp(-0.5 * ((xs - 31.5) ** 2 + (ys - 23.5) ** 2) / var)
    a = np.where(a >= 0.01, a, 0)  # the rasterizer's alpha cut-off
    np.testing.assert_allclose(out.alpha, a, atol=1e-5)
    np.testing.assert_allclose(out.depth, a * z, atol=1e-5)
    c0 = 0.28209479177387814
    color = np.maximum(c0 * np.array([0.3, -0.2, 0.1]) + 0.5, 0)
    np.testing.assert_allclose(out.color, a[..., None] * color, atol=1e-5)
    np.testing.assert_allclose(out.features, a[..., None] * np.array([1.0, -2.0]), atol=1e-5)


def test_outputs_and_gradient_shapes():
    g = scene(coeffs=4)
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)
    assert out.color.shape == (H, W, 3) and out.color.dtype == np.float32
    assert out.depth.shape == (H, W) and out.alpha.shape == (H, W)
    assert out.features.shape == (H, W, 6)
    assert out.num_pairs > 0 and (out.radii > 0).sum() > 0
    grads = out.backward(d_color=np.ones((H, W, 3)), d_depth=np.ones((H, W)))
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "features"):
        assert grads[name].shape == np.shape(g[name]), name
    assert grads["pose"].shape == (6,) and grads["means2d"].shape == (40, 2)
    only = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H, color=False, depth=False)
    assert only.color is None and only.depth is None and only.alpha is not None


def test_gradients_of_one_gaussian_match_closed_form():
    # The f64 engine tests check every gradient entry against finite differences; here the
    # binding's array layout is checked against closed forms for one isotropic Gaussian
    # straight ahead: alpha = o exp(-r^2 / (2 var)), var = (f s / z)^2 + 0.3.
    s, z, logit, f = 0.05, 2.0, 1.5, 80.0
    feat = np.array([1.0, -2.0])
    sh0 = np.array([0.3, -0.2, 0.1])
    g = dict(means=[[0.0, 0, z]], log_scales=[[np.log(s)] * 3], quats=[[1.0, 0, 0, 0]],
             opacity_logits=[logit], sh=[sh0], features=[feat])
    rng = np.random.default_rng(3)
    w_a, w_c, w_f = rng.normal(size=(H, W)), rng.normal(size=(H, W, 3)), rng.normal(size=(H, W, 2))
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H, depth=False)
    grads = out.backward(d_color=w_c, d_alpha=w_a, d_features=w_f)
    a = out.alpha.astype(np.float64)
    o = 1 / (1 + np.exp(-logit))
    c0 = 0.28209479177387814
    color = c0 * sh0 + 0.5
    per_alpha = w_a + w_c @ color + w_f @ feat          # d loss / d alpha at each pixel
    var = (f * s / z) ** 2 + 0.3
    ys, xs = np.mgrid[0:H, 0:W]
    r2 = (xs - 31.5) ** 2 + (ys - 23.5) ** 2
    expect = {
        "opacity_logits": np.sum(per_alpha * a) * (1 - o),
        "features": (w_f * a[..., None]).sum(axis=(0, 1)),
        "sh": c0 * (w_c * a[..., None]).sum(axis=(0, 1)),
        "log_scales": np.sum(per_alpha * a * 0.5 * r2 / var**2) * 2 * (f * s / z) ** 2,
        "means_x": np.sum(per_alpha * a * (xs - 31.5)) * f / (z * var),
        "means_y": np.sum(per_alpha * a * (ys - 23.5)) * f / (z * var),
    }
    got = {
        "opacity_logits": grads["opacity_logits"][0],
        "features": grads["features"][0],
        "sh": grads["sh"][0, 0],
        "log_scales": grads["log_scales"][0].sum(),    # uniform scaling of all three axes
        "means_x": grads["means"][0, 0],
        "means_y": grads["means"][0, 1],
    }
    for name in expect:
        np.testing.assert_allclose(got[name], expect[name], rtol=2e-3, atol=1e-4, err_msg=name)


def test_pose_translation_gradient_is_minus_the_sum_over_means():
    # At the identity pose, p_cam = mean + rho: moving the camera's world-to-camera
    # translation is moving every Gaussian, so d/d rho = sum_i d/d mean_i.
    g = scene()
    rng = np.random.default_rng(4)
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)
    grads = out.backward(d_color=rng.normal(size=(H, W, 3)), d_depth=rng.normal(size=(H, W)),
                         d_features=rng.normal(size=(H, W, 6)))
    np.testing.assert_allclose(grads["pose"][:3], grads["means"].sum(axis=0), rtol=1e-3, atol=1e-3)
    assert np.abs(grads["pose"]).max() > 1.0


@pytest.mark.parametrize("change, message", [
    (dict(means=np.zeros((40, 2))), "means must have shape Nx3"),
    (dict(log_scales=np.zeros((39, 3))), "log_scales must have shape 40x3"),
    (dict(quats=np.zeros((40, 4), bool)), "quats must be a float32 array, got dtype bool"),
    (dict(quats=np.tile([2.0, 0, 0, 0], (40, 1))), "unit quaternions"),
    (dict(features=np.zeros((39, 6))), "features must have shape 40xN"),
    (dict(sh=np.zeros((40, 5, 3))), "1, 4, 9 or 16 coefficients"),
])
def test_bad_gaussians_raise_value_error(change, message):
    g = {**scene(), **change}
    with pytest.raises(ValueError, match=message):
        legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)


def test_nan_is_named():
    g = scene()
    g["opacity_logits"][3] = np.nan
    with pytest.raises(ValueError, match="opacity_logits has a non-finite value .* Gaussian 3"):
        legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)


def test_bad_camera_and_gradients_raise_value_error():
    g = scene()
    with pytest.raises(ValueError, match="pose must have shape 4x4"):
        legslam.render(**g, K=K, pose=np.eye(3), width=W, height=H)
    with pytest.raises(ValueError, match="pose rotation must be orthonormal"):
        legslam.render(**g, K=K, pose=np.diag([2.0, 1, 1, 1]), width=W, height=H)
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        legslam.render(**g, K=np.diag([-1.0, 1, 1]), pose=np.eye(4), width=W, height=H)
    with pytest.raises(ValueError, match="width and height must be positive"):
        legslam.render(**g, K=K, pose=np.eye(4), width=0, height=H)
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H, depth=False)
    with pytest.raises(ValueError, match="d_color must have shape"):
        out.backward(d_color=np.zeros((H, W)))
    with pytest.raises(ValueError, match="not rendered"):
        out.backward(d_depth=np.zeros((H, W)))
    with pytest.raises(ValueError, match="non-finite"):
        out.backward(d_color=np.full((H, W, 3), np.nan))


@pytest.mark.parametrize("coeffs", [1, 16])
def test_empty_map_renders_black(coeffs):
    g = {k: v[:0] for k, v in scene().items()}
    g["sh"] = np.zeros((0, coeffs, 3), np.float32)  # an empty map of any degree
    out = legslam.render(**g, K=K, pose=np.eye(4), width=W, height=H)
    assert not out.color.any() and not out.alpha.any()
    assert out.backward(d_color=np.ones((H, W, 3)))["means"].shape == (0, 3)
