"""Geometric agreement of two RGB-D frames under their poses: the check that a dataset's
intrinsics, depth scale and pose convention were read right (SOURCE.md files state the
numbers it gives for the shared sequences)."""

from __future__ import annotations

import numpy as np


def depth_reprojection(frame_a, frame_b, tolerance: float = 0.05) -> dict:
    """Back-project frame_a's valid depth with its K and pose, project it into frame_b and
    compare the predicted z with frame_b's depth at the nearest pixel.

    Returns {"median_cm": median |dz| in cm, "within": fraction of compared points with
    |dz| <= tolerance (metres), "overlap": compared points / valid points of frame_a, "n",
    "colour_l1": mean |rgb_a - rgb_b| of the compared points in 8-bit levels, None without
    colour (colour that sits on the wrong depth, e.g. unregistered depth, raises it)}.
    Frames need poses (camera-to-world)."""
    if frame_a.pose is None or frame_b.pose is None:
        raise ValueError("both frames need a pose")
    Ka, Kb = frame_a.K, frame_b.K
    v, u = np.nonzero(frame_a.depth > 0)
    z = frame_a.depth[v, u].astype(np.float64)
    pts = np.stack([(u - Ka[0, 2]) / Ka[0, 0] * z, (v - Ka[1, 2]) / Ka[1, 1] * z, z, np.ones_like(z)])
    pb = (np.linalg.inv(frame_b.pose) @ frame_a.pose @ pts)[:3]
    front = pb[2] > 1e-6
    pb, v, u = pb[:, front], v[front], u[front]
    ub = np.round(Kb[0, 0] * pb[0] / pb[2] + Kb[0, 2]).astype(np.int64)
    vb = np.round(Kb[1, 1] * pb[1] / pb[2] + Kb[1, 2]).astype(np.int64)
    h, w = frame_b.depth.shape
    inside = (ub >= 0) & (ub < w) & (vb >= 0) & (vb < h)
    pb, v, u, ub, vb = pb[:, inside], v[inside], u[inside], ub[inside], vb[inside]
    zb = frame_b.depth[vb, ub]
    ok = zb > 0
    dz = np.abs(zb[ok] - pb[2, ok])
    if dz.size == 0:
        return {"median_cm": float("nan"), "within": 0.0, "overlap": 0.0, "n": 0, "colour_l1": None}
    colour_l1 = None
    if frame_a.rgb is not None and frame_b.rgb is not None:
        colour_l1 = float(np.abs(frame_a.rgb[v[ok], u[ok]].astype(np.float64)
                                 - frame_b.rgb[vb[ok], ub[ok]]).mean())
    return {"median_cm": float(np.median(dz) * 100), "within": float((dz <= tolerance).mean()),
            "overlap": float(dz.size / max(len(z), 1)), "n": int(dz.size), "colour_l1": colour_l1}


def view_agreement(seq, trajectories: dict, every: int = 9, pairs: int = 400,
                   frames: range | None = None) -> dict:
    """How well each trajectory (name: (N,4,4) camera-to-world poses, one per frame of `seq`)
    makes the frames agree with each other, needing no ground truth: pairs of frames (every
    `every`-th of `frames`, all of them by default, from the 3rd on; a seeded sample of at most
    `pairs` whose views overlap on at least 30% under the first trajectory), each frame's depth
    moved into the other by the poses. Per trajectory, (pairs compared, the median over pairs
    of the median depth disagreement in cm, the median colour difference where they meet in
    8-bit levels). A ground truth of its own, measured like this, says how far it can be
    trusted. The figures do not depend on where a trajectory is anchored (only relative poses
    enter), so trajectories need no alignment."""
    from types import SimpleNamespace

    frames = range(len(seq)) if frames is None else frames
    picked = list(frames)[3::every]
    candidates = [(a, b) for n, a in enumerate(picked) for b in picked[n + 1:]]
    order = np.random.default_rng(0).permutation(len(candidates))
    first = next(iter(trajectories))
    scores = {name: [] for name in trajectories}
    for k in order[:pairs]:
        a, b = (seq[i] for i in candidates[k])
        views = {name: [SimpleNamespace(pose=poses[i], K=f.K, depth=f.depth, rgb=f.rgb)
                        for i, f in zip(candidates[k], (a, b))] for name, poses in trajectories.items()}
        if depth_reprojection(*views[first], 0.02)["overlap"] < 0.3:
            continue
        for name, (va, vb) in views.items():
            r = depth_reprojection(va, vb, 0.02)
            scores[name].append((r["median_cm"], r["colour_l1"]))
    return {name: (len(v), float(np.nanmedian([d for d, _ in v])),
                   float(np.median([c for _, c in v])) if v[0][1] is not None else float("nan"))
            for name, v in scores.items() if v}
