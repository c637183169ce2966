"""`legslam run`: a sequence in, a SLAM run's outputs out, with progress on the terminal.

Outputs in the run folder: trajectory.txt (TUM, one pose per input frame), map.ply (3DGS layout
+ f_lang_* features), pca.npz (the feature compression, for text queries), camera.json (the
intrinsics and image size), metrics.json, timings.json, config.json, and renders/ (renders beside the input frames, and the rendered
features as colour).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from .datasets import each_readable
from .slam import SLAM, SLAMConfig

__all__ = ["run", "evaluate", "feature_rgb", "feature_basis"]


class Progress:
    """One self-overwriting status line on stderr (plain lines when it is not a terminal)."""

    def __init__(self, total: int, enabled: bool = True):
        self.total, self.enabled = total, enabled
        self.tty = sys.stderr.isatty()
        self.start = time.perf_counter()
        self._last = 0.0

    def update(self, i: int, text: str) -> None:
        fps = (i + 1) / max(time.perf_counter() - self.start, 1e-9)
        self._show(f"frame {i + 1}/{self.total}  {fps:5.2f} fps  {text}", i + 1 == self.total)

    def final_iterations(self, done: int, total: int) -> None:
        """The mapping iterations after the last frame (minutes with a large --final-iters)."""
        self._show(f"final mapping iterations {done}/{total}", done == total)

    def _show(self, line: str, last: bool) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not last and now - self._last < (0.2 if self.tty else 5.0):
            return
        self._last = now
        print(("\r" + line + "\x1b[K") if self.tty else line, end="\n" if last or not self.tty else "",
              file=sys.stderr, flush=True)


def feature_basis(features: np.ndarray) -> np.ndarray:
    """K x 3: the first three principal directions of HxWxK features (from about 5000 pixels)."""
    x = features.reshape(-1, features.shape[-1]).astype(np.float64)
    centred = x - x.mean(0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(x) // 5000)], full_matrices=False)
    return vt[:3].T


def feature_rgb(features: np.ndarray, basis: np.ndarray | None = None) -> np.ndarray:
    """HxWxK features -> HxWx3 uint8: their projection on `basis` (default: their own first
    three principal directions) as colour."""
    h, w, k = features.shape
    x = features.reshape(-1, k).astype(np.float64)
    y = x @ (feature_basis(features) if basis is None else basis)
    lo, hi = np.percentile(y, 2, axis=0), np.percentile(y, 98, axis=0)
    y = np.clip((y - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return (y.reshape(h, w, 3) * 255).astype(np.uint8)


def _save_png(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def evaluate(slam: SLAM, seq, every: int = 5, renders_dir: Path | None = None,
             n_renders: int = 4, skip=()) -> dict:
    """Renders the final map at the estimated pose of every `every`-th frame and of every
    keyframe; PSNR, SSIM and depth L1 against the input, and ATE when ground truth exists.
    Frames in `skip` (unreadable) are left out of every figure."""
    from .eval import ViewScores, ate, psnr

    n = len(slam.poses)
    out: dict = {"frames": n, "keyframes": len(slam.keyframe_frames),
                 "keyframe_frames": list(slam.keyframe_frames),
                 "lost_frames": int(sum(s == "lost" for s in slam.states))}
    readable = [i for i in range(n) if i not in skip]
    gt = [seq.pose(i) for i in readable]
    if len(readable) >= 3 and all(p is not None for p in gt):
        stats = ate(np.stack(gt), np.stack([slam.poses[i] for i in readable]))
        out["ate_rmse_m"] = stats["rmse"]
        out["ate_mean_m"] = stats["mean"]
    picked = [i for i in range(0, n, every) if i not in skip]
    show = set(picked[:: max(1, len(picked) // n_renders)][:n_renders])
    # With trained exposures, also PSNR under the exposure SLAM estimated for each frame (its
    # keyframe's): the map's colour is the first keyframe's exposure, the frames' varies.
    exposures = slam.frame_exposures()
    for name, frames in (("every_%d" % every, picked), ("at_keyframes", slam.keyframe_frames)):
        scores, exposed_psnr = ViewScores(), []
        for i in frames:
            f = seq[i]
            r = slam.render(slam.poses[i], features=renders_dir is not None and i in show)
            color = np.clip(r["color"], 0, 1)
            if exposures is not None:
                gain, bias = exposures[i]
                exposed = np.clip(r["color"] * gain + bias, 0, 1)
                exposed_psnr.append(psnr(exposed, f.rgb.astype(np.float32) / 255.0, data_range=1.0))
            scores.add(color, r["depth"], f.rgb, f.depth)
            if renders_dir is not None and name.startswith("every") and i in show:
                side = np.concatenate([f.rgb, _to_u8(color)], axis=1)
                _save_png(renders_dir / f"frame{i:06d}_input_render.png", side)
                if "features" in r:
                    _save_png(renders_dir / f"frame{i:06d}_features.png", feature_rgb(r["features"]))
        out[name] = scores.means()
        if exposures is not None:
            out[name]["psnr_exposed"] = float(np.mean(exposed_psnr)) if exposed_psnr else None
        out[name]["count"] = len(frames)
    return out


def _timing_table(slam: SLAM, wall_s: float, live_s: float, viewer_ms: list[float]) -> dict:
    def summary(v):
        return {"mean_ms": float(np.mean(v)) if v else 0.0,
                "median_ms": float(np.median(v)) if v else 0.0,
                "total_s": float(np.sum(v)) / 1e3, "count": len(v)}

    table = {k: summary(v) for k, v in slam.timings.items()}
    table["feature_extraction (per keyframe, worker thread)"] = summary(slam.feature_timings["extraction"])
    table["compression (per keyframe)"] = summary(slam.feature_timings["compression"])
    stats = slam.mapping_stats
    for key in ("render_s", "loss_s", "backward_s", "step_s"):
        table[f"mapping.{key[:-2]}"] = {"total_s": float(sum(s[key] for s in stats))}
    if slam.config.mapping_thread:
        table["mapping.reference_render"] = {"total_s": slam.reference_render_s}
    if viewer_ms:
        table["viewer (per frame, and the final map)"] = summary(viewer_ms)
    table["wall_s"] = wall_s
    table["fps"] = len(slam.poses) / wall_s if wall_s > 0 else 0.0
    # While frames come in, before the final mapping iterations: the rate a live camera sees.
    table["live_s"] = live_s
    table["fps_live"] = len(slam.poses) / live_s if live_s > 0 else 0.0
    return table


def _save_trajectory_and_map(slam: SLAM, out: Path, stamps: list) -> None:
    from .eval import write_tum

    # A run stopped inside a frame has its stamp but not its pose.
    write_tum(out / "trajectory.txt", np.array(stamps[:len(slam.poses)]), np.stack(slam.poses))
    slam.gaussian_map().save(out / "map.ply")
    if slam.pca is not None:
        slam.pca.save(out / "pca.npz")


def _save_partial(slam: SLAM, out: Path, stamps: list) -> None:
    """Writes the trajectory and map of the frames done before a run stopped (no final
    iterations); says so on stderr, or why it could not."""
    try:
        if not slam.poses:
            return
        slam.finish(train=False)
        _save_trajectory_and_map(slam, out, stamps)
        print(f"stopped after {len(slam.poses)} frames: their trajectory.txt and map.ply are in "
              f"{out}/", file=sys.stderr)
    except Exception as e:  # the error that stopped the run is the one to report
        print(f"could not save the frames done so far: {e}", file=sys.stderr)


def run(seq, out_dir, config: SLAMConfig | None = None, progress: bool = True,
        evaluate_every: int = 5, encoder=None, viewer=None) -> dict:
    """Runs SLAM over a sequence (from legslam.datasets.open) and writes the outputs.

    `viewer` (e.g. legslam.viewer.RerunViewer) sees every step, `on_frame(index, frame, step,
    slam)`, and the finished map, `on_finish(slam)`; its time is part of the wall time and is
    reported as its own stage."""
    config = config or SLAMConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    first = seq[0] if len(seq) else None
    if first is not None:
        h, w = first.depth.shape
        (out / "camera.json").write_text(json.dumps(
            {"K": first.K.tolist(), "width": w, "height": h,
             "sequence": str(getattr(seq, "path", "")),
             "selection": getattr(seq, "selection", None)}, indent=2))
    if first is None:
        raise ValueError(f"{getattr(seq, 'path', 'the sequence')} has no frames")
    slam = SLAM(config, first.K, w, h, encoder=encoder)
    bar = Progress(len(seq), progress)
    t0 = time.perf_counter()
    stamps, viewer_ms = [], []
    unreadable: set[int] = set()
    no_depth = 0  # frames without any valid depth pixel
    try:
        for i, f in each_readable(seq):
            if f is None:  # lost: the motion model's pose
                unreadable.add(i)
                stamps.append(seq.timestamp(i))
                slam.skip()
                continue
            stamps.append(f.timestamp)
            if not np.any(f.depth > 0):
                if not no_depth:
                    print(f"warning: frame {i} has no valid depth, so it cannot grow the map "
                          "(frames like it are counted in metrics.json)", file=sys.stderr)
                no_depth += 1
            r = slam.step(f.rgb, f.depth)
            if viewer is not None:
                t1 = time.perf_counter()
                viewer.on_frame(i, f, r, slam)
                viewer_ms.append(1e3 * (time.perf_counter() - t1))
            bar.update(i, f"{r.state:4s}  kf {len(slam.keyframe_frames)}  "
                          f"gaussians {slam.num_gaussians}")
        live = time.perf_counter() - t0
        slam.finish(progress=bar.final_iterations)
    except BaseException:  # interrupted, or too many unreadable frames: keep the work done
        _save_partial(slam, out, stamps)
        raise
    if viewer is not None:
        t1 = time.perf_counter()
        viewer.on_finish(slam)
        viewer_ms.append(1e3 * (time.perf_counter() - t1))
    wall = time.perf_counter() - t0

    _save_trajectory_and_map(slam, out, stamps)
    timings = _timing_table(slam, wall, live, viewer_ms)
    (out / "timings.json").write_text(json.dumps(timings, indent=2))
    renders = out / "renders"
    renders.mkdir(exist_ok=True)
    metrics = evaluate(slam, seq, every=evaluate_every, renders_dir=renders, skip=unreadable)
    metrics["unreadable_frames"] = sorted(unreadable)
    metrics["frames_without_depth"] = no_depth
    metrics["gaussians"] = slam.mapper.num_gaussians
    metrics["fps"] = timings["fps"]
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return {"metrics": metrics, "timings": timings, "out": str(out), "slam": slam}
