"""Keyframe features, off the tracking path: an encoder in a worker thread, a PCA fitted on the
first keyframes' patches (or loaded), and the compressed grids handed to the map; the raw
patch tokens to place recognition."""

from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np

from ..features import PCA, AsyncExtractor, Encoder

__all__ = ["FeatureFeed"]


class FeatureFeed:
    """Features for keyframes: `submit` a keyframe's colour, `collect` what is ready (each
    grid goes to `sink(keyframe id, grid)` once there is a PCA; with no sink, no language
    features are made), `drain` at the end. `tokens(keyframe id, unit patch tokens h x w x D)`,
    when given, hears of each keyframe as it is encoded. `timings` gets "extraction" and
    "compression" milliseconds per keyframe.

    `settled` (synchronous runs, which collect once a frame): `collect` hands over exactly the
    keyframes submitted before the collect before it, waiting for those not encoded yet, so that
    what the map and place recognition get at each frame does not depend on how busy the machine
    is. A keyframe's features then come at the frame after it, as they do on an idle machine
    (its mapping iterations take longer than its encoding)."""

    def __init__(self, config, sink: Optional[Callable[[int, np.ndarray], None]], timings: dict,
                 encoder=None, tokens: Optional[Callable[[int, np.ndarray], None]] = None,
                 settled: bool = False):
        c = config
        self.config, self.sink, self.timings, self.tokens = c, sink, timings, tokens
        self.settled, self._due, self._fresh = settled, [], []  # settled: keys by when submitted
        if encoder is None:
            encoder = Encoder(c.encoder_model, input_size=c.encoder_size, threads=c.encoder_threads)
        dim = getattr(encoder, "dim", None)
        if dim is not None and c.feature_dim > dim:
            raise ValueError(f"feature_dim is {c.feature_dim}, more than the {dim} dimensions the "
                             f"encoder ({getattr(encoder, 'path', c.encoder_model)}) gives: at most {dim}")
        self.encoder = encoder
        self.extractor = AsyncExtractor(encoder)
        self.pca = PCA.load(c.pca_path) if c.pca_path and sink is not None else None
        if self.pca is not None and self.pca.n_components != c.feature_dim:
            raise ValueError(f"{c.pca_path} compresses to {self.pca.n_components} dimensions, "
                             f"feature_dim is {c.feature_dim}")
        self._waiting: list = []  # (keyframe id, raw features) until the PCA is fitted

    def submit(self, kf_id: int, rgb: np.ndarray) -> None:
        self.extractor.submit(kf_id, rgb)
        if self.settled:
            self._fresh.append(kf_id)

    def collect(self, everything: bool = False) -> None:
        """Hands over what is ready (settled: what is due; `everything`: all submitted)."""
        if self.settled:
            keys = self._due + self._fresh if everything else self._due
            self._due, self._fresh = ([], []) if everything else (self._fresh, [])
            results = [self.extractor.get(key) for key in keys]
        else:
            results = self.extractor.poll()
        for r in results:
            self._take(r)

    def drain(self) -> None:
        """Waits for every submitted keyframe and hands over its grid (fitting the PCA on
        what there is, if it was still waiting for more keyframes)."""
        self.extractor.close()
        self.collect(everything=True)
        if self._waiting and self.pca is None and self.sink is not None:
            self._fit()
        self._flush()

    def _take(self, r) -> None:
        self.timings["extraction"].append(r.extract_ms)
        if self.tokens is not None:
            self.tokens(int(r.key), r.features)
        if self.sink is None:
            return
        self._waiting.append((r.key, r.features))
        if self.pca is None and len(self._waiting) >= self.config.pca_keyframes:
            self._fit()
        self._flush()

    def _fit(self) -> None:
        pca = PCA(self.config.feature_dim)
        for _, raw in self._waiting:
            pca.partial_fit(raw.reshape(-1, raw.shape[-1]))
        self.pca = pca

    def _flush(self) -> None:
        """Compresses the waiting grids and hands them over, once there is a PCA."""
        if self.pca is None:
            return
        for key, raw in self._waiting:
            t0 = time.perf_counter()
            grid = np.ascontiguousarray(self.pca.transform(raw), dtype=np.float32)
            self.timings["compression"].append(1e3 * (time.perf_counter() - t0))
            self.sink(int(key), grid)
        self._waiting.clear()
