"""A run's figures, computed one way whether the map is live (`legslam run`) or read back from
its folder (`legslam eval`): the trajectory against the sequence's ground truth (ATE, RPE) and
the map rendered at the estimated poses of every N-th frame and of the keyframes (PSNR, SSIM,
depth L1, and mIoU when given a semantic scorer). Lengths are in centimetres throughout.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from ..datasets import DatasetError
from ..render import feature_rgb
from .image import ViewScores, psnr
from .trajectory import ate, rpe

__all__ = ["evaluate_run", "every_key"]

log = logging.getLogger("legslam")


def every_key(every: int) -> str:
    """The key of the figures of every `every`-th frame ("every_5")."""
    return f"every_{every}"


def evaluate_run(seq, poses, render: Callable, *, every: int = 5, keyframes=None, skip=(),
                 depth_range=(0.0, np.inf), exposures: Optional[np.ndarray] = None,
                 renders_dir: Optional[Path] = None, n_renders: int = 4, semantic=None) -> dict:
    """The figures of a run over `seq`, whose frame k was placed at `poses[k]`.

    render(pose, features) -> an object with `color`, `depth` (and `features`) images: the map.
    keyframes: frame numbers of the keyframes (their figures are "at_keyframes"), if known.
    skip: frames the run could not read, left out of every figure (with any that cannot be read
    now: "unreadable_frames"). depth_range: the depth (m) the run used; depth outside it is
    not compared (as the run kept it out of the map). exposures: per frame the
    gain and bias (2 x 3) of its keyframe's exposure (adds "psnr_exposed"). renders_dir: where
    to write a few renders beside their input frames. semantic: a scorer (eval.semantic's
    SemanticScore) given the rendered features of every N-th frame.
    """
    n = len(poses)
    skip = set(skip)
    out: dict = {"frames": n, "every": every}
    out.update(_trajectory_figures(seq, poses, [k for k in range(n) if k not in skip]))
    picked = [k for k in range(0, n, every) if k not in skip]
    show = set(picked[:: max(1, len(picked) // n_renders)][:n_renders]) if renders_dir else set()
    views = [(every_key(every), picked)]
    if keyframes is not None:
        views.append(("at_keyframes", list(keyframes)))
    for name, frames in views:
        scores, exposed = ViewScores(), []
        count = 0
        for k in frames:
            try:
                f = seq[k]
            except DatasetError as e:  # as the run did: left out, with a warning
                log.warning("frame %d left out of the figures: %s", k, e)
                skip.add(k)
                continue
            score_semantic = semantic is not None and name != "at_keyframes"
            r = render(poses[k], k in show or score_semantic)
            color = np.clip(r.color, 0, 1)
            low, high = depth_range
            scores.add(color, r.depth, f.rgb, np.where((f.depth >= low) & (f.depth <= high), f.depth, 0))
            count += 1
            if exposures is not None:
                gain, bias = exposures[k]
                exposed.append(psnr(np.clip(r.color * gain + bias, 0, 1),
                                    f.rgb.astype(np.float32) / 255.0, data_range=1.0))
            if score_semantic and f.labels is not None:
                semantic.add(k, r.features, f.labels)
            if k in show and name != "at_keyframes":
                _save_png(renders_dir / f"frame{k:06d}_input_render.png",
                          np.concatenate([f.rgb, _to_u8(color)], axis=1))
                if getattr(r, "features", None) is not None:
                    _save_png(renders_dir / f"frame{k:06d}_features.png", feature_rgb(r.features))
        out[name] = {**scores.means(), "count": count}
        if exposures is not None:
            out[name]["psnr_exposed"] = float(np.mean(exposed)) if exposed else None
    out["unreadable_frames"] = sorted(skip)
    if semantic is not None:
        out.update(semantic.report())
    return out


def _trajectory_figures(seq, poses, frames: list) -> dict:
    """ATE and RPE (cm, degrees) over those of `frames` that have a ground-truth pose, with a
    note when some have none (RPE then pairs consecutive frames with one)."""
    with_gt = [(k, p) for k in frames if (p := seq.pose(k)) is not None]
    missing = len(frames) - len(with_gt)
    if len(with_gt) < 3:
        why = "the sequence has no ground-truth poses" if not with_gt else "fewer than 3 frames have a ground-truth pose"
        return {"ate_note": f"no ATE: {why}"}
    truth = np.stack([p for _, p in with_gt])
    estimate = np.stack([poses[k] for k, _ in with_gt])
    a, r = ate(truth, estimate), rpe(truth, estimate)
    out = {"ate_rmse_cm": 100 * a["rmse"], "ate_mean_cm": 100 * a["mean"],
           "rpe_trans_rmse_cm": 100 * r["trans"]["rmse"], "rpe_rot_rmse_deg": r["rot"]["rmse"]}
    if missing:
        first = [k for k in frames if seq.pose(k) is None][:5]
        out["ate_note"] = (f"over the {len(with_gt)} of {len(frames)} frames with a ground-truth pose "
                           f"(none for frame{'s' if missing > 1 else ''} "
                           f"{', '.join(map(str, first))}{' ...' if missing > 5 else ''})")
    return out


def _save_png(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
