"""Semantic segmentation metrics from predicted and ground-truth label maps: per-class IoU,
mIoU, mean (per-class) accuracy and pixel accuracy, with an ignore label.

A class's IoU is TP / (TP + FP + FN) and its accuracy TP / (TP + FN); a class that occurs in
neither map (or, for accuracy, not in the ground truth) has NaN and is left out of the means,
as in the usual benchmark code (e.g. ScanNet's, mmsegmentation's).

A map is scored (`SemanticScore`) by its rendered language features: every pixel takes the class whose query its rendered feature is closest to (cosine, argmax
over the queries); a pixel where nothing is rendered (zero feature) predicts nothing, which
counts as a miss of its true class. The queries come by one of two routes:

- text (the paper's open-vocabulary protocol, `by_text`): the text query of every class in
  the sequence's class list;
- by example (`by_example`; needs no text model and is NOT open-vocabulary): class
  prototypes, the normalised mean rendered feature of each class's labelled pixels in a few
  support views. The support views are, for each class, the first evaluated view in which it
  covers at least MIN_SUPPORT_FRACTION of the image: one labelled example per class, so the
  score says how well the map's features separate the classes given that much supervision.
  A prototype pools its class's pixels over all the support views; the support views are
  left out of the scores. A class with no pixel in any support view has no prototype and is
  never predicted (its pixels elsewhere count as misses)."""

from __future__ import annotations

import numpy as np

from ..datasets.base import IGNORE_LABEL
from ..features.encoder import l2_normalize
from ..query import segment


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


# A class must cover this much of a view for that view to be its example: a few stray pixels
# (a class at the image border, label noise) would make a noisy prototype.
MIN_SUPPORT_FRACTION = 0.005


class NoPrototypes(ValueError):
    """By example, no class could be given a prototype."""


def predict(features: np.ndarray, queries: np.ndarray, class_ids) -> np.ndarray:
    """int32 H x W: per pixel, the class id of the best-scoring query (class_ids[c] for
    queries[c]); IGNORE_LABEL where nothing is rendered."""
    pred = np.asarray(class_ids, np.int32)[segment(features, queries, threshold=-np.inf)]
    pred[~features.any(axis=2)] = IGNORE_LABEL
    return pred


def class_feature_sums(features: np.ndarray, labels: np.ndarray, num_classes: int) -> np.ndarray:
    """(num_classes, K) float64: per class, the sum of the unit-length rendered features of
    its pixels; unrendered pixels and labels outside [0, num_classes) add nothing."""
    if labels.shape != features.shape[:2]:
        raise ValueError(f"labels {labels.shape} do not match the feature map {features.shape[:2]}")
    unit = l2_normalize(features).reshape(-1, features.shape[2])
    lab = labels.reshape(-1)
    sums = np.zeros((num_classes, features.shape[2]))
    for c in np.unique(lab[(lab >= 0) & (lab < num_classes)]):
        sums[c] = unit[lab == c].sum(axis=0, dtype=np.float64)
    return sums


def pick_support(pixel_counts: np.ndarray, min_pixels: float) -> list[int]:
    """pixel_counts[v, c]: the pixels of class c in view v. The positions v of the support
    views: for each class, the first view where it has at least min_pixels; sorted, distinct."""
    enough = pixel_counts >= min_pixels
    return sorted(set(enough.argmax(axis=0)[enough.any(axis=0)].tolist()))


class SemanticScore:
    """Scores views one at a time (`add`) with fixed queries, then `report`s the metrics."""

    def __init__(self, queries, class_ids, names: list[str], by_example: bool, support=()):
        self.queries, self.class_ids, self.names = queries, class_ids, names
        self.by_example, self.support = by_example, sorted(support)
        self.counts = SegmentationCounts(len(names))
        self.views = 0

    def add(self, view: int, features: np.ndarray, labels: np.ndarray) -> None:
        """Scores one view (a frame index; support views are skipped)."""
        if view in self.support:
            return
        if labels.shape != features.shape[:2]:
            raise ValueError(f"labels {labels.shape} do not match the rendered view {features.shape[:2]}")
        self.counts.add(predict(features, self.queries, self.class_ids), labels)
        self.views += 1

    def report(self) -> dict:
        """Flat metrics; by example, every key that could be mistaken for the open-vocabulary
        number carries the suffix "_by_example"."""
        m = self.counts.metrics()
        s = "_by_example" if self.by_example else ""
        out = {"semantic_route": "by_example" if self.by_example else "text", "semantic_views": self.views,
               f"miou{s}": m["miou"], f"macc{s}": m["macc"], f"pixel_acc{s}": m["pixel_acc"],
               f"iou{s}": {n: (None if np.isnan(v) else float(v)) for n, v in zip(self.names, m["iou"])}}
        if self.by_example:
            out["support_frames"] = self.support
        return out


def by_text(queries: np.ndarray, names: list[str]) -> SemanticScore:
    """Scores with one text query per class of the class list (queries[c] for names[c])."""
    return SemanticScore(queries, np.arange(len(names)), names, by_example=False)


def by_example(views, labels_of, features_of, names: list[str] | None = None,
               min_fraction: float = MIN_SUPPORT_FRACTION) -> SemanticScore:
    """Scores with class prototypes from support views (see the module doc). views: the frame
    indices evaluated; labels_of(i) / features_of(i): frame i's labels / rendered features.
    names: the class list (default: the ids as text). NoPrototypes when no class has one."""
    counts, pixels = [], 0
    for i in views:
        labels = labels_of(i)
        counts.append(np.bincount(labels[labels >= 0]))
        pixels = labels.size
    # Without a class list (or with labels beyond it) the ids the labels use are the classes.
    num_classes = max([len(names or ())] + [len(c) for c in counts])
    names = list(names or ()) + [str(c) for c in range(len(names or ()), num_classes)]
    counts = np.stack([np.pad(c, (0, num_classes - len(c))) for c in counts])
    support = [views[j] for j in pick_support(counts, min_fraction * pixels)]
    if not support:
        raise NoPrototypes(f"no class covers {100 * min_fraction:g}% of any evaluated view")
    sums = sum(class_feature_sums(features_of(i), labels_of(i), num_classes) for i in support)
    ids = np.flatnonzero(np.linalg.norm(sums, axis=1) > 0)
    if len(ids) == 0:
        raise NoPrototypes("no class has a prototype: nothing is rendered on its pixels in the support views")
    return SemanticScore(l2_normalize(sums[ids]), ids, names, by_example=True, support=support)
