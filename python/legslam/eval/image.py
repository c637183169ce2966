"""Image metrics of rendered against captured views: PSNR, SSIM, depth L1, LPIPS.

Images are HxW or HxWxC arrays of equal shape and dtype kind. data_range defaults to 255 for
uint8 and 1.0 for float images (the engine's [0, 1] convention)."""

from __future__ import annotations

import numpy as np


class MetricUnavailable(RuntimeError):
    """A metric that needs something this installation does not have."""


def _pair(a, b, data_range):
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if (a.dtype == np.uint8) != (b.dtype == np.uint8):
        raise ValueError(f"compare images of the same kind, got {a.dtype} and {b.dtype} "
                         "(convert uint8 to float / 255 first)")
    if data_range is None:
        data_range = 255.0 if a.dtype == np.uint8 else 1.0
    return a.astype(np.float64), b.astype(np.float64), float(data_range)


def psnr(a, b, data_range=None) -> float:
    """Peak signal-to-noise ratio in dB; inf for identical images."""
    a, b, r = _pair(a, b, data_range)
    mse = np.mean((a - b) ** 2)
    return float("inf") if mse == 0 else float(10.0 * np.log10(r * r / mse))


def ssim(a, b, data_range=None) -> float:
    """Mean SSIM with an 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, population
    covariances, averaged over channels: Wang et al. 2004, and the number skimage's
    structural_similarity gives with gaussian_weights=True, use_sample_covariance=False.
    The 5-pixel border, where the window would leave the image, is excluded."""
    import cv2

    a, b, r = _pair(a, b, data_range)
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3 or min(a.shape[:2]) < 11:
        raise ValueError(f"SSIM needs HxW or HxWxC images of at least 11x11 pixels, got shape {a.shape}")
    g = cv2.getGaussianKernel(11, 1.5, cv2.CV_64F)
    c1, c2 = (0.01 * r) ** 2, (0.03 * r) ** 2

    def blur(x):
        return cv2.sepFilter2D(x, cv2.CV_64F, g, g, borderType=cv2.BORDER_REFLECT)[5:-5, 5:-5]

    scores = []
    for c in range(a.shape[2]):
        x, y = np.ascontiguousarray(a[..., c]), np.ascontiguousarray(b[..., c])
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        scores.append(s.mean())
    return float(np.mean(scores))


def depth_l1_cm(pred, gt) -> float | None:
    """Mean |pred - gt| in centimetres over pixels with valid ground truth (gt > 0, finite);
    None when there is none (nothing to compare). A pixel the prediction leaves empty (0)
    counts with its full error; a non-finite prediction is an error, not a pixel to skip."""
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"depth maps differ in shape: {pred.shape} vs {gt.shape}")
    valid = np.isfinite(gt) & (gt > 0)
    if not valid.any():
        return None
    if not np.all(np.isfinite(pred[valid])):
        raise ValueError("the predicted depth has non-finite values where the ground truth is valid")
    return float(np.abs(pred[valid] - gt[valid]).mean() * 100.0)


class ViewScores:
    """PSNR, SSIM and depth L1 of renders against the frames they stand for, gathered view by
    view; `means()` gives each figure's mean, None where no view gave one (no view at all, or
    none with valid depth)."""

    def __init__(self):
        self.values: dict[str, list[float]] = {"psnr": [], "ssim": [], "depth_l1_cm": []}

    def add(self, color, depth, rgb_u8, gt_depth) -> None:
        """`color` in [0, 1] (clipped by the caller), `rgb_u8` the frame's 8-bit colour."""
        target = np.asarray(rgb_u8, dtype=np.float32) / 255.0
        self.values["psnr"].append(psnr(color, target, data_range=1.0))
        self.values["ssim"].append(ssim(color, target, data_range=1.0))
        l1 = depth_l1_cm(depth, gt_depth)
        if l1 is not None:  # frames without valid depth have none
            self.values["depth_l1_cm"].append(l1)

    def means(self) -> dict:
        """Each figure's mean. A render equal to its frame has an infinite PSNR (an all-black
        frame and an empty map, say), which no mean can hold: PSNR is then None, with a note."""
        out = {k: float(np.mean(v)) if v else None for k, v in self.values.items()}
        infinite = int(np.isinf(self.values["psnr"]).sum())
        if infinite:
            out["psnr"] = None
            out["psnr_note"] = (f"undefined: {infinite} of {len(self.values['psnr'])} renders equal "
                                "their frames exactly (infinite PSNR)")
        return out


def lpips(a, b, net: str = "alex") -> float:
    """LPIPS (Zhang et al. 2018) between two RGB images, lower is closer.

    It needs the `lpips` package (PyTorch) and its network weights, which legslam does not
    ship and cannot fetch offline; without them this raises MetricUnavailable."""
    try:
        import lpips as lp  # optional: pulls in torch
        import torch
    except ImportError:
        raise MetricUnavailable("LPIPS needs the optional 'lpips' package (PyTorch) and its pretrained "
                                "network weights, which are not available offline; install it with "
                                "`pip install lpips` where there is internet access") from None
    a, b, r = _pair(a, b, None)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"LPIPS takes HxWx3 RGB images, got shape {a.shape}")
    to_t = lambda x: torch.from_numpy(x / r * 2.0 - 1.0).permute(2, 0, 1)[None].float()  # noqa: E731
    with torch.no_grad():
        return float(lp.LPIPS(net=net, verbose=False)(to_t(a), to_t(b)))
