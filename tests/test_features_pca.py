"""legslam.features.PCA against numpy's SVD; incremental fitting equals batch fitting."""

from __future__ import annotations

import numpy as np
import pytest

from legslam.features import PCA


def _data(n=600, d=24, seed=0):
    rng = np.random.default_rng(seed)
    # Distinct variances per direction so the components are well separated.
    basis = np.linalg.qr(rng.standard_normal((d, d)))[0]
    return (rng.standard_normal((n, d)) * np.linspace(5, 0.1, d)) @ basis.T + rng.standard_normal(d)


def test_matches_numpy_svd():
    x = _data()
    pca = PCA(6).fit(x)
    centred = x - x.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    # Same subspace, same directions up to sign.
    np.testing.assert_allclose(np.abs((pca.components @ vt[:6].T).diagonal()), 1.0, atol=1e-5)
    np.testing.assert_allclose(pca.explained_variance, s[:6] ** 2 / (len(x) - 1), rtol=1e-6)
    np.testing.assert_allclose(pca.mean, x.mean(axis=0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(pca.components @ pca.components.T, np.eye(6), atol=1e-5)


def test_incremental_equals_batch():
    x = _data()
    batch = PCA(8).fit(x)
    inc = PCA(8)
    for chunk in np.array_split(x, 7):
        inc.partial_fit(chunk)
    assert inc.n_samples == batch.n_samples == len(x)
    np.testing.assert_allclose(inc.components, batch.components, atol=1e-5)
    np.testing.assert_allclose(inc.transform(x), batch.transform(x), rtol=1e-4, atol=1e-4)


def test_transform_inverse_and_shapes():
    x = _data().astype(np.float32)
    pca = PCA(24).fit(x)  # all components: exact reconstruction
    grid = x[:60].reshape(6, 10, 24)
    y = pca.transform(grid)
    assert y.shape == (6, 10, 24) and y.dtype == np.float32
    np.testing.assert_allclose(pca.inverse_transform(y), grid, atol=1e-3)
    few = PCA(3).fit(x)
    assert few.transform(grid).shape == (6, 10, 3) and few.inverse_transform(few.transform(grid)).shape == grid.shape


def test_save_load_roundtrip_and_continue_fitting(tmp_path):
    x = _data()
    pca = PCA(5).partial_fit(x[:300])
    pca.save(tmp_path / "pca.npz")
    loaded = PCA.load(tmp_path / "pca.npz")
    assert loaded.n_components == 5 and loaded.n_samples == 300
    np.testing.assert_array_equal(loaded.transform(x), pca.transform(x))
    loaded.partial_fit(x[300:])
    np.testing.assert_allclose(loaded.components, PCA(5).fit(x).components, atol=1e-5)


def test_bad_input_is_rejected(tmp_path):
    pca = PCA(4)
    with pytest.raises(ValueError, match="not fitted"):
        pca.transform(np.zeros((2, 8)))
    with pytest.raises(ValueError, match="exceeds"):
        PCA(9).fit(np.zeros((10, 8)))
    with pytest.raises(ValueError, match="floating"):
        pca.fit(np.zeros((10, 8), dtype=np.int32))
    with pytest.raises(ValueError, match="at least 2"):
        PCA(1).fit(np.ones((1, 8))).components
    pca.fit(_data(d=8))
    with pytest.raises(ValueError, match="last dimension 8"):
        pca.transform(np.zeros((3, 7), np.float32))
    with pytest.raises(ValueError, match="last dimension 4"):
        pca.inverse_transform(np.zeros((3, 5), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        pca.partial_fit(np.full((3, 8), np.nan))
    with pytest.raises(ValueError, match="NaN"):
        pca.transform(np.full((3, 8), np.inf))
    np.savez(tmp_path / "other.npz", a=1)
    with pytest.raises(ValueError, match="not a legslam PCA"):
        PCA.load(tmp_path / "other.npz")


def test_a_file_that_is_not_a_saved_pca_is_named(tmp_path):
    PCA(3).fit(_data(d=8)).save(tmp_path / "pca.npz")
    whole = (tmp_path / "pca.npz").read_bytes()
    for name, content in (("text.npz", b"garbage\n"), ("cut.npz", whole[: len(whole) // 2])):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=f"{name} is (not a legslam|a damaged) PCA file"):
            PCA.load(tmp_path / name)
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(ValueError, match="one array, not an .npz archive"):
        PCA.load(tmp_path / "one.npy")


def test_fitting_runs_blas_on_one_thread(monkeypatch):
    # Beside the mapping and encoder threads, OpenBLAS's own threads stalled the fit for
    # seconds; the limit must hold while the scatter and eigendecomposition run.
    from threadpoolctl import threadpool_info

    import legslam.features.pca as pca_module

    def blas_threads():
        return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}

    seen = []
    eigh = np.linalg.eigh

    def watched(a):
        seen.append(blas_threads())
        return eigh(a)

    monkeypatch.setattr(pca_module.np.linalg, "eigh", watched)
    before = blas_threads()
    x = np.random.default_rng(0).normal(size=(300, 40)).astype(np.float32)
    PCA(8).fit(x).components
    assert seen == [{1}]
    assert blas_threads() == before  # and is lifted afterwards
