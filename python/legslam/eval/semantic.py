"""Semantic segmentation metrics from predicted and ground-truth label maps: per-class IoU,
mIoU, mean (per-class) accuracy and pixel accuracy, with an ignore label.

A class's IoU is TP / (TP + FP + FN) and its accuracy TP / (TP + FN); a class that occurs in
neither map (or, for accuracy, not in the ground truth) has NaN and is left out of the means,
as in the usual benchmark code (e.g. ScanNet's, mmsegmentation's)."""

from __future__ import annotations

import numpy as np

from ..datasets.base import IGNORE_LABEL


def _counts(pred, gt, num_classes: int, ignore_index: int) -> tuple:
    """(confusion (C, C) int64 with rows = ground truth and columns = prediction, misses (C,)):
    pixels whose ground truth is ignore_index are skipped; a pixel predicted as ignore_index
    ("no prediction") is a miss of its ground-truth class and a false positive of none."""
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"label maps differ in shape: {pred.shape} vs {gt.shape}")
    keep = gt != ignore_index
    g, p = gt[keep].astype(np.int64), pred[keep].astype(np.int64)
    for name, x, allowed in (("ground-truth", g, ()), ("predicted", p, (ignore_index,))):
        bad = (x < 0) | (x >= num_classes)
        bad &= ~np.isin(x, allowed)
        if bad.any():
            raise ValueError(f"{name} label {x[bad][0]} is outside [0, {num_classes}) "
                             f"and is not the ignore label {ignore_index}")
    hit = p != ignore_index
    cm = np.bincount(g[hit] * num_classes + p[hit], minlength=num_classes ** 2)
    return cm.reshape(num_classes, num_classes), np.bincount(g[~hit], minlength=num_classes)


class SegmentationCounts:
    """The counts behind segmentation_metrics, summed over any number of views (`add` one
    view at a time) so that metrics over a whole sequence need no view kept in memory."""

    def __init__(self, num_classes: int, ignore_index: int = IGNORE_LABEL):
        self.num_classes, self.ignore_index = num_classes, ignore_index
        self.confusion = np.zeros((num_classes, num_classes), np.int64)
        self.misses = np.zeros(num_classes, np.int64)

    def add(self, pred, gt) -> "SegmentationCounts":
        cm, misses = _counts(pred, gt, self.num_classes, self.ignore_index)
        self.confusion += cm
        self.misses += misses
        return self

    def metrics(self) -> dict:
        """As segmentation_metrics, over every view added."""
        cm = self.confusion
        tp = np.diag(cm).astype(np.float64)
        gt_count = cm.sum(1) + self.misses
        pred_count = cm.sum(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = tp / (gt_count + pred_count - tp)
            acc = tp / gt_count
        total = gt_count.sum()
        if total == 0:
            raise ValueError("every ground-truth pixel is ignored")
        nanmean = lambda x: float(np.nanmean(x)) if np.isfinite(x).any() else float("nan")  # noqa: E731
        return {"iou": iou, "miou": nanmean(iou), "acc": acc, "macc": nanmean(acc),
                "pixel_acc": float(tp.sum() / total), "confusion": cm.copy()}


def segmentation_metrics(pred, gt, num_classes: int, ignore_index: int = IGNORE_LABEL) -> dict:
    """{"iou": (C,) per-class IoU, "miou", "acc": (C,) per-class accuracy, "macc",
    "pixel_acc", "confusion": (C, C)}; class means over the classes that are not NaN."""
    return SegmentationCounts(num_classes, ignore_index).add(pred, gt).metrics()


def miou(pred, gt, num_classes: int, ignore_index: int = IGNORE_LABEL) -> float:
    """Mean IoU over the classes present in the prediction or the ground truth."""
    return segmentation_metrics(pred, gt, num_classes, ignore_index)["miou"]
