"""A pose graph of keyframes for loop closure, optimised by the engine (its `graph` module).

Nodes are keyframe poses, 4x4 camera-to-world; the fixed ones anchor the graph (the first
keyframe, usually). An edge from node i to node j measures T_ij, the pose of j in i's frame
(`relative(T_i, T_j)` when consistent), with a 6x6 information matrix over the residual twist
log(inv(T_ij) inv(T_i) T_j): translation first (metres), then rotation (radians); see
`information`. Odometry edges (consecutive keyframes) are trusted; every other edge (a loop,
or a covisibility edge between keyframes that see the same surfaces) gets a robust (Cauchy)
kernel, and one still inconsistent after optimisation (chi2 above the `outlier_chi2` option)
is dropped, logged, and the graph solved again.

    >>> graph = PoseGraph()
    >>> a = graph.add_node(T0, fixed=True)
    >>> b = graph.add_node(T1)
    >>> graph.add_edge(a, b, relative(T0, T1), information(0.01, np.radians(0.5)))
    >>> result = graph.optimize()   # graph.poses are now the optimised ones
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from legslam import _core

__all__ = ["DEFAULT_OPTIONS", "PoseGraph", "PoseGraphResult", "Edge", "information", "relative"]

log = logging.getLogger("legslam")

#: The engine's default pose-graph options (`PoseGraph(**overrides)` changes any of them):
#: max_iterations, tolerance (relative cost decrease that ends a solve), robust_scale (Cauchy
#: scale on the Mahalanobis norm of loop edges; 0: plain least squares), reject_outliers and
#: outlier_chi2 (loop edges above it are dropped).
DEFAULT_OPTIONS: dict[str, Any] = dict(_core.pose_graph_options())

#: Outcome of an optimisation (the engine's): poses (N x 4 x 4, optimised camera-to-world; fixed
#: ones as given); chi2 and weights (per edge, in the order given: the squared Mahalanobis norm
#: of its residual at the optimised poses, and its final robust weight, 1 for odometry, 0 for a
#: rejected edge); rejected (indices of the loop edges dropped); iterations (Levenberg-Marquardt
#: steps over all solves); initial_cost and final_cost (the robust cost at the given poses over
#: every edge, and at the result over the edges kept); converged; seconds.
PoseGraphResult = _core.PoseGraphResult


def information(sigma_translation: float, sigma_rotation: float) -> np.ndarray:
    """The 6x6 information of independent errors with these standard deviations (metres per
    axis, radians per axis), translation first."""
    if not (sigma_translation > 0 and sigma_rotation > 0):
        raise ValueError(f"standard deviations must be positive, got {sigma_translation} and "
                         f"{sigma_rotation}")
    return np.diag([sigma_translation ** -2.0] * 3 + [sigma_rotation ** -2.0] * 3)


def relative(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """T_ij = inv(T_i) @ T_j: the pose of j in i's frame, for camera-to-world rigid poses."""
    r, t = pose_i[:3, :3], pose_i[:3, 3]
    inv = np.eye(4)
    inv[:3, :3] = r.T
    inv[:3, 3] = -r.T @ t
    return inv @ pose_j


@dataclass
class Edge:
    """A relative-pose measurement: `measurement` is T_ij, the pose of node j in node i's frame;
    `kind` is "odometry", "loop" or "covisibility" (the engine treats all but odometry alike)."""
    i: int
    j: int
    measurement: np.ndarray
    information: np.ndarray
    kind: str = "odometry"


class PoseGraph:
    """Keyframe poses, the fixed ones among them, and the edges between them. Options by name
    (see `DEFAULT_OPTIONS`) are checked when the graph is made."""

    def __init__(self, **options: Any):
        self.options = dict(_core.pose_graph_options(options))
        self.poses: list[np.ndarray] = []
        self.fixed: list[int] = []
        self.edges: list[Edge] = []
        #: Loop edges dropped by past optimisations, as they were.
        self.rejected: list[Edge] = []

    def add_node(self, pose: np.ndarray, fixed: bool = False) -> int:
        """Adds a keyframe at camera-to-world `pose` (4x4); returns its index."""
        self.poses.append(np.array(pose, dtype=np.float64))
        if fixed:
            self.fixed.append(len(self.poses) - 1)
        return len(self.poses) - 1

    def add_edge(self, i: int, j: int, measurement: np.ndarray, information: np.ndarray,
                 kind: str = "odometry") -> int:
        """Adds the measurement T_ij of node j's pose in node i's frame, with its 6x6
        information; returns the edge's index."""
        self.edges.append(Edge(i, j, np.array(measurement, dtype=np.float64),
                               np.array(information, dtype=np.float64), kind))
        return len(self.edges) - 1

    def optimize(self) -> PoseGraphResult:
        """Optimises the free poses in place. Loop edges rejected as outliers are logged and
        removed from `edges` (kept in `rejected`); the result's per-edge values and indices
        refer to `edges` as they were before the call."""
        poses = np.stack(self.poses) if self.poses else np.zeros((0, 4, 4))
        edges = [(e.i, e.j, e.measurement, e.information, "odometry" if e.kind == "odometry" else "loop")
                 for e in self.edges]
        result = _core.optimize_pose_graph(poses, edges, self.fixed, self.options)
        self.poses = list(result.poses)
        for k in result.rejected:
            e = self.edges[k]
            log.warning("pose graph: %s edge %d (keyframes %d-%d) rejected as an outlier, "
                        "chi2 %.1f", e.kind, k, e.i, e.j, result.chi2[k])
        dropped = set(result.rejected)
        self.rejected += [self.edges[k] for k in result.rejected]
        self.edges = [e for k, e in enumerate(self.edges) if k not in dropped]
        return result
