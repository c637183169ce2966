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
