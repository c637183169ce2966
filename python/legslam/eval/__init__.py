"""Evaluation in the field's standard metrics: trajectory (ATE, RPE; evo's conventions),
images (PSNR, SSIM, depth L1, optional LPIPS), semantics (IoU, mIoU, mean accuracy, and the
scoring of a map's language features), and `evaluate_run`: all of a run's figures, one way."""

from .consistency import depth_reprojection, view_agreement
from .image import MetricUnavailable, ViewScores, depth_l1_cm, lpips, psnr, ssim
from .run import evaluate_run, every_key
from .semantic import (NoPrototypes, SegmentationCounts, SemanticScore, by_example, by_text, miou,
                       segmentation_metrics)
from .trajectory import TrajectoryError, associate, ate, ate_rmse, read_tum, rpe, umeyama, write_tum

__all__ = ["ate", "ate_rmse", "rpe", "read_tum", "write_tum", "associate", "umeyama",
           "TrajectoryError", "psnr", "ssim", "depth_l1_cm", "ViewScores", "lpips", "MetricUnavailable",
           "segmentation_metrics", "SegmentationCounts", "miou", "depth_reprojection", "view_agreement",
           "evaluate_run", "every_key", "SemanticScore", "NoPrototypes", "by_text", "by_example"]
