"""Trajectory metrics in evo's conventions: ATE (APE of the translation part after Umeyama
alignment, as `evo_ape tum gt est -a [-s]`), RPE (as `evo_rpe`), and
TUM-format trajectory files. Poses are camera-to-world 4x4 matrices; distances in metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..datasets._io import quat_to_pose, read_numbers
from ..datasets.base import DatasetError, DatasetNotFoundError


class TrajectoryError(ValueError):
    """Trajectories that cannot be compared (bad file, no common timestamps, too few poses)."""


def read_tum(path) -> tuple:
    """(timestamps (N,), c2w poses (N,4,4)) from a TUM file: `t tx ty tz qx qy qz qw` lines."""
    try:
        rows = read_numbers(path, columns=(8,))
    except DatasetNotFoundError:
        raise FileNotFoundError(f"no trajectory file {path}") from None
    except DatasetError as e:
        raise TrajectoryError(f"{e} (a TUM trajectory has lines t tx ty tz qx qy qz qw)") from None
    if not np.all(np.isfinite(rows)):
        raise TrajectoryError(f"{path} has non-finite values")
    return rows[:, 0], np.stack([quat_to_pose(r[1:4], r[4:8]) for r in rows])


def pose_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw), qw >= 0, of a rotation matrix."""
    # The eigenvector of Bar-Itzhack's symmetric matrix: stable for every rotation.
    m = R
    a, b, c = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]  # 4 w (x, y, z)
    Kq = np.array([
        [m[0, 0] - m[1, 1] - m[2, 2], m[1, 0] + m[0, 1], m[2, 0] + m[0, 2], a],
        [m[1, 0] + m[0, 1], m[1, 1] - m[0, 0] - m[2, 2], m[2, 1] + m[1, 2], b],
        [m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], m[2, 2] - m[0, 0] - m[1, 1], c],
        [a, b, c, m[0, 0] + m[1, 1] + m[2, 2]],
    ]) / 3.0
    w, v = np.linalg.eigh(Kq)
    q = v[:, np.argmax(w)]
    return q if q[3] >= 0 else -q


def write_tum(path, timestamps, poses) -> None:
    """Write c2w poses (N,4,4) with their timestamps as a TUM trajectory file."""
    stamps, poses = np.asarray(timestamps, dtype=np.float64), _as_poses(poses, "poses")
    if len(stamps) != len(poses):
        raise TrajectoryError(f"{len(stamps)} timestamps for {len(poses)} poses")
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(stamps, poses):
            vals = [*T[:3, 3], *pose_to_quat(T[:3, :3])]
            f.write(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in vals) + "\n")


def _as_poses(poses, what: str) -> np.ndarray:
    a = np.asarray(poses, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4):
        raise TrajectoryError(f"{what} must be an (N,4,4) array of poses, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TrajectoryError(f"{what} contain non-finite values")
    return a


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_diff: float = 0.01) -> tuple:
    """Index arrays (ia, ib) pairing timestamps as evo does: each stamp of the shorter list takes
    the nearest stamp of the longer one when within max_diff (seconds)."""
    swap = len(stamps_b) < len(stamps_a)
    short, long_ = (stamps_b, stamps_a) if swap else (stamps_a, stamps_b)
    order = np.argsort(long_, kind="stable")
    sl = long_[order]
    pos = np.searchsorted(sl, short, side="right")
    lower, upper = np.clip(pos - 1, 0, len(sl) - 1), np.clip(pos, 0, len(sl) - 1)
    # Ties go to the earlier stamp, as in evo.
    pick = np.where(np.abs(sl[upper] - short) < np.abs(short - sl[lower]), upper, lower)
    ok = np.abs(sl[pick] - short) <= max_diff
    i_short, i_long = np.nonzero(ok)[0], order[pick[ok]]
    return (i_long, i_short) if swap else (i_short, i_long)


def _load_pair(gt, est, max_diff: float) -> tuple:
    """(gt poses, est poses) of equal length: TUM files are associated by timestamp, arrays
    are taken as already corresponding frame by frame."""
    if isinstance(gt, (str, Path)) != isinstance(est, (str, Path)):
        raise TrajectoryError("give both trajectories as TUM files or both as (N,4,4) arrays")
    if isinstance(gt, (str, Path)):
        (tg, pg), (te, pe) = read_tum(gt), read_tum(est)
        ig, ie = associate(tg, te, max_diff)
        if len(ig) == 0:
            raise TrajectoryError(f"no timestamps of {gt} and {est} are within {max_diff} s of each other")
        return pg[ig], pe[ie]
    pg, pe = _as_poses(gt, "ground-truth poses"), _as_poses(est, "estimated poses")
    if len(pg) != len(pe):
        raise TrajectoryError(f"{len(pg)} ground-truth poses but {len(pe)} estimated ones")
    return pg, pe


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple:
    """(R, t, s) minimising sum |dst - (s R src + t)|^2 over (N,3) point sets (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    return R, mu_d - s * R @ mu_s, s


def _stats(err: np.ndarray) -> dict:
    return {"rmse": float(np.sqrt(np.mean(err ** 2))), "mean": float(err.mean()),
            "median": float(np.median(err)), "std": float(err.std()), "min": float(err.min()),
            "max": float(err.max()), "sse": float((err ** 2).sum()), "n": int(len(err))}


def ate(gt, est, align: str = "se3", max_diff: float = 0.01) -> dict:
    """Absolute trajectory error of the translations, after aligning est to gt.

    gt, est: TUM file paths (associated by timestamp within max_diff seconds) or (N,4,4) c2w
    arrays of corresponding poses. align: "se3" (rotation + translation, `evo_ape -a`), "sim3"
    (also scale, `-as`) or "none". Returns the error statistics in metres (rmse, mean, median,
    std, min, max, sse, n) plus "aligned": est after alignment (N,4,4), "scale", "errors" (N,).
    """
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"align must be 'se3', 'sim3' or 'none', not {align!r}")
    pg, pe = _load_pair(gt, est, max_diff)
    if align != "none" and len(pg) < 3:
        raise TrajectoryError(f"alignment needs at least 3 poses, got {len(pg)}")
    R, t, s = (np.eye(3), np.zeros(3), 1.0) if align == "none" else umeyama(pe[:, :3, 3], pg[:, :3, 3], align == "sim3")
    aligned = pe.copy()
    aligned[:, :3, :3] = R @ pe[:, :3, :3]
    aligned[:, :3, 3] = s * pe[:, :3, 3] @ R.T + t
    errors = np.linalg.norm(aligned[:, :3, 3] - pg[:, :3, 3], axis=1)
    return {**_stats(errors), "aligned": aligned, "scale": s, "errors": errors}


def ate_rmse(gt, est, align: str = "se3", max_diff: float = 0.01) -> float:
    """ATE RMSE in metres (the number `evo_ape tum gt est -a` reports as rmse)."""
    return ate(gt, est, align, max_diff)["rmse"]


def rpe(gt, est, delta: int = 1, all_pairs: bool = False, max_diff: float = 0.01) -> dict:
    """Relative pose error over pose pairs delta frames apart, as `evo_rpe tum gt est --delta
    delta --delta_unit f [--all_pairs]`: pairs (0, d), (d, 2d), ... by default, every (i, i + d)
    with all_pairs. Returns {"trans": stats in metres, "rot": stats in degrees}."""
    pg, pe = _load_pair(gt, est, max_diff)
    if not (isinstance(delta, (int, np.integer)) and 1 <= delta < len(pg)):
        raise TrajectoryError(f"delta must be an integer in [1, {len(pg) - 1}], got {delta!r}")
    i = np.arange(len(pg) - delta) if all_pairs else np.arange(0, len(pg) - delta, delta)
    rel_g = np.linalg.inv(pg[i]) @ pg[i + delta]
    rel_e = np.linalg.inv(pe[i]) @ pe[i + delta]
    E = np.linalg.inv(rel_g) @ rel_e
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    cos = np.clip((np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return {"trans": _stats(trans), "rot": _stats(np.degrees(np.arccos(cos)))}
