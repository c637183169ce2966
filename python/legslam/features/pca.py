"""PCA that compresses D-dim features (and queries) to K dims, fitted incrementally.

`partial_fit` accumulates the sample count, sum and D x D scatter matrix in float64, so fitting
in any number of batches gives exactly the batch result (D is 384 or 768: the scatter matrix is
at most 4.7 MB). The components are the top-K eigenvectors of the covariance, signs fixed so the
largest-magnitude entry of each is positive (deterministic across runs).
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..blas import one_blas_thread


def _as_samples(x, dim: int | None, what: str) -> np.ndarray:
    """[..., D] floating array -> [N, D] view; ValueError on bad dtype, D mismatch or NaN/inf."""
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"{what}: expected floating-point features, got dtype {x.dtype}")
    if x.ndim < 1 or (dim is not None and x.shape[-1] != dim):
        raise ValueError(f"{what}: expected features with last dimension {dim}, got shape {x.shape}")
    flat = x.reshape(-1, x.shape[-1])
    if not np.isfinite(flat).all():
        raise ValueError(f"{what}: features contain NaN or inf")
    return flat


class PCA:
    def __init__(self, n_components: int = 64):
        if n_components < 1:
            raise ValueError(f"n_components must be >= 1, got {n_components}")
        self.n_components = int(n_components)
        self.n_samples = 0
        self._sum = None  # float64 [D]
        self._scatter = None  # float64 [D, D], sum of x x^T
        self._solution = None  # (mean, components, explained_variance), solved lazily

    @property
    def mean(self) -> np.ndarray:
        """float32 [D]"""
        return self._solved()[0]

    @property
    def components(self) -> np.ndarray:
        """float32 [K, D], orthonormal rows"""
        return self._solved()[1]

    @property
    def explained_variance(self) -> np.ndarray:
        """float64 [K], descending"""
        return self._solved()[2]

    @property
    def dim(self) -> int | None:
        return None if self._sum is None else self._sum.shape[0]

    def partial_fit(self, x) -> "PCA":
        """Adds samples x [..., D] (any leading shape) to the fit."""
        flat = _as_samples(x, self.dim, "PCA.partial_fit").astype(np.float64)
        if self._sum is None:
            d = flat.shape[1]
            if self.n_components > d:
                raise ValueError(f"n_components={self.n_components} exceeds the feature dimension {d}")
            self._sum = np.zeros(d)
            self._scatter = np.zeros((d, d))
        self.n_samples += flat.shape[0]
        self._sum += flat.sum(axis=0)
        with one_blas_thread():  # beside SLAM's pools (legslam.blas)
            self._scatter += flat.T @ flat
        self._solution = None
        return self

    def fit(self, x) -> "PCA":
        self.n_samples, self._sum, self._scatter = 0, None, None
        return self.partial_fit(x)

    def _solved(self) -> tuple:
        if self._solution is None:
            self._solution = self._solve()
        return self._solution

    def _solve(self) -> tuple:
        if self._sum is None:
            raise ValueError("PCA is not fitted: call fit/partial_fit or PCA.load first")
        if self.n_samples < 2:
            raise ValueError(f"PCA needs at least 2 samples, has {self.n_samples}")
        mean = self._sum / self.n_samples
        cov = (self._scatter - self.n_samples * np.outer(mean, mean)) / (self.n_samples - 1)
        with one_blas_thread():  # beside SLAM's pools (legslam.blas)
            evals, evecs = np.linalg.eigh(cov)  # ascending
        top = evecs[:, ::-1][:, : self.n_components].T
        signs = np.sign(top[np.arange(top.shape[0]), np.abs(top).argmax(axis=1)])
        components = (top * signs[:, None]).astype(np.float32)
        return mean.astype(np.float32), components, np.maximum(evals[::-1][: self.n_components], 0.0)

    def transform(self, x) -> np.ndarray:
        """[..., D] -> [..., K] float32 (centred, projected on the components)."""
        mean, components, _ = self._solved()
        x = np.asarray(x)
        flat = _as_samples(x, self.dim, "PCA.transform").astype(np.float32, copy=False)
        return ((flat - mean) @ components.T).reshape(*x.shape[:-1], self.n_components)

    def inverse_transform(self, y) -> np.ndarray:
        """[..., K] -> [..., D] float32, the reconstruction from K components."""
        mean, components, _ = self._solved()
        y = np.asarray(y)
        flat = _as_samples(y, self.n_components, "PCA.inverse_transform").astype(np.float32, copy=False)
        return (flat @ components + mean).reshape(*y.shape[:-1], self.dim)

    def save(self, path) -> None:
        """Writes an .npz that `PCA.load` reads back, fit statistics included (fitting can go on);
        whole or not at all (a temporary file renamed over `path`)."""
        mean, components, explained_variance = self._solved()
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        np.savez(
            tmp,
            n_components=self.n_components,
            n_samples=self.n_samples,
            sum=self._sum,
            scatter=self._scatter,
            mean=mean,
            components=components,
            explained_variance=explained_variance,
        )
        tmp.replace(path)

    @classmethod
    def load(cls, path) -> "PCA":
        """Reads what `save` wrote; ValueError naming the file when it is anything else
        (FileNotFoundError when there is none)."""
        try:
            z = np.load(path, allow_pickle=False)
        except (ValueError, EOFError, zipfile.BadZipFile) as e:
            raise ValueError(f"{path} is not a legslam PCA file ({e})") from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"{path} is not a legslam PCA file (one array, not an .npz archive)")
        with z:
            missing = {"n_components", "n_samples", "sum", "scatter", "mean", "components", "explained_variance"}
            missing -= set(z.files)
            if missing:
                raise ValueError(f"{path} is not a legslam PCA file: missing {sorted(missing)}")
            try:
                pca = cls(int(z["n_components"]))
                pca.n_samples = int(z["n_samples"])
                pca._sum, pca._scatter = z["sum"], z["scatter"]
                # The saved solution, not a re-solve: loading must reproduce the same transform.
                pca._solution = (z["mean"], z["components"], z["explained_variance"])
            except (ValueError, EOFError, OSError, zipfile.BadZipFile, zlib.error) as e:  # damaged
                raise ValueError(f"{path} is a damaged PCA file ({e})") from None
        return pca
