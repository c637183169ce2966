"""Saving and loading a Gaussian map as a 3DGS-layout PLY."""

import numpy as np
import pytest

from legslam.map import GaussianMap


def random_map(n=30, coeffs=4, k=5, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return GaussianMap(
        means=(rng.normal(size=(n, 3)) + [0, 0, 3]).astype(np.float32),
        log_scales=rng.uniform(-3, -2, (n, 3)).astype(np.float32),
        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        sh=rng.normal(size=(n, coeffs, 3)).astype(np.float32),
        features=rng.normal(size=(n, k)).astype(np.float32),
    )


@pytest.mark.parametrize("coeffs, k", [(1, 0), (4, 5), (16, 64)])
def test_ply_round_trip(tmp_path, coeffs, k):
    m = random_map(coeffs=coeffs, k=k)
    path = m.save(tmp_path / "map.ply")
    back = GaussianMap.load(path)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "features"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name), err_msg=name)


def test_ply_header_follows_the_3dgs_layout(tmp_path):
    m = random_map(coeffs=4, k=2)
    head = m.save(tmp_path / "map.ply").read_bytes().split(b"end_header")[0].decode()
    props = [line.split()[-1] for line in head.splitlines() if line.startswith("property")]
    expect = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
              + [f"f_rest_{i}" for i in range(9)] + ["opacity"]
              + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
              + ["f_lang_0", "f_lang_1"])
    assert props == expect
    assert "format binary_little_endian 1.0" in head
    # 3DGS stores f_rest channel by channel: f_rest_0..2 are red's degree-1 coefficients.
    raw = np.frombuffer((tmp_path / "map.ply").read_bytes().split(b"end_header\n")[1], dtype="<f4")
    row0 = raw[: len(expect)]
    np.testing.assert_array_equal(row0[9:12], m.sh[0, 1:, 0])


def test_rendering_a_loaded_map_matches_the_original(tmp_path):
    m = random_map(coeffs=1, k=3)
    back = GaussianMap.load(m.save(tmp_path / "m.ply"))
    K = np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]])
    a = m.render(np.eye(4), K, 64, 48)
    b = back.render(np.eye(4), K, 64, 48)
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(a.features, b.features)
    assert a.alpha.max() > 0.1


def test_load_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="no map file"):
        GaussianMap.load(tmp_path / "missing.ply")
    (tmp_path / "bad.ply").write_bytes(b"not a ply\n")
    with pytest.raises(ValueError, match="not a PLY"):
        GaussianMap.load(tmp_path / "bad.ply")
    (tmp_path / "mesh.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + np.zeros(3, "<f4").tobytes())
    with pytest.raises(ValueError, match="not a Gaussian-splat PLY"):
        GaussianMap.load(tmp_path / "mesh.ply")


def test_a_damaged_map_file_is_named(tmp_path):
    path = random_map(n=20).save(tmp_path / "map.ply")
    whole = path.read_bytes()
    path.write_bytes(whole[:-7])
    with pytest.raises(ValueError, match=r"map.ply is cut short: its 20 Gaussians need \d+ bytes"):
        GaussianMap.load(path)
    path.write_bytes(whole[:whole.index(b"end_header")])
    with pytest.raises(ValueError, match="no end_header"):
        GaussianMap.load(path)
    path.write_bytes(whole.replace(b"element vertex 20", b"element vertex lots"))
    with pytest.raises(ValueError, match="bad PLY header line 'element vertex lots'"):
        GaussianMap.load(path)
