"""The pose-graph optimiser from Python: `_core.optimize_pose_graph` (shapes and dtypes named
by the binding, values by the engine) and the `legslam.slam.pose_graph.PoseGraph` wrapper
(loop closure on a drifted loop, a false loop rejected, logged and dropped)."""

import logging

import numpy as np
import pytest

from legslam import _core
from legslam.slam.pose_graph import DEFAULT_OPTIONS, PoseGraph, information, relative


def rotation(axis_angle) -> np.ndarray:
    """Rodrigues' formula."""
    w = np.asarray(axis_angle, float)
    theta = np.linalg.norm(w)
    if theta == 0:
        return np.eye(3)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / theta
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def pose(axis_angle=(0, 0, 0), t=(0, 0, 0)) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = rotation(axis_angle)
    p[:3, 3] = t
    return p


def circle(n: int) -> list:
    """Camera-to-world poses on a circle of radius 2 m, looking at its centre (y down)."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        look = pose((-np.pi / 2, 0, 0)) @ pose((0, a + np.pi / 2, 0))
        out.append(pose(t=(2 * np.cos(a), 2 * np.sin(a), 1.5)) @ np.block(
            [[look[:3, :3], np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    return out


INFO = information(0.01, np.radians(0.5))


def test_a_consistent_graph_comes_back_as_it_went_in():
    truth = circle(8)
    edges = [(k, k + 1, relative(truth[k], truth[k + 1]), INFO, "odometry") for k in range(7)]
    edges.append((7, 0, relative(truth[7], truth[0]), INFO, "loop"))
    r = _core.optimize_pose_graph(np.stack(truth), edges)
    assert r.poses.shape == (8, 4, 4) and r.poses.dtype == np.float64
    assert r.chi2.shape == (8,) and r.weights.shape == (8,)
    np.testing.assert_allclose(r.poses, np.stack(truth), atol=1e-12)
    assert r.rejected == [] and r.converged and r.final_cost < 1e-20
    assert "PoseGraphResult(rejected=[]" in repr(r)


def test_two_measurements_are_averaged_by_their_information():
    # Node 1 measured twice from the fixed node 0 (rotated, elsewhere): at translations ta and
    # tb with isotropic information 100 and 300, so the optimum is (ta + 3 tb) / 4.
    t0 = pose((0.3, -0.5, 1.0), (1.0, 2.0, -0.5))
    ta, tb = np.array([1.0, 0.2, -0.4]), np.array([1.4, -0.2, 0.0])
    wa, wb = np.diag([100.0] * 3 + [1e4] * 3), np.diag([300.0] * 3 + [1e4] * 3)
    edges = [(0, 1, pose(t=ta), wa, "odometry"), (0, 1, pose(t=tb), wb, "loop")]
    r = _core.optimize_pose_graph(np.stack([t0, t0 @ pose((0.1, 0, 0), (0.5, 0, 0))]), edges,
                                  fixed=[0], options={"robust_scale": 0.0, "tolerance": 1e-12})
    np.testing.assert_allclose(relative(t0, r.poses[1]), pose(t=(ta + 3 * tb) / 4), atol=1e-9)
    assert np.array_equal(r.poses[0], t0)


def _drifted(n=40):
    """True poses on a circle, odometry with a heading bias of 0.25 degrees a keyframe, one
    exact loop edge from the last keyframe to the first, and a false loop: keyframes 10 and 30
    (opposite sides of the room) claimed to be 30 cm apart."""
    truth = circle(n)
    bias = pose((0, 0.0045, 0), (0.001, 0, 0))
    graph = PoseGraph()
    graph.add_node(truth[0], fixed=True)
    for k in range(1, n):
        z = relative(truth[k - 1], truth[k]) @ bias
        graph.add_node(graph.poses[-1] @ z)
        graph.add_edge(k - 1, k, z, INFO)
    graph.add_edge(n - 1, 0, relative(truth[n - 1], truth[0]), INFO, kind="loop")
    graph.add_edge(10, 30, pose(t=(0.3, 0, 0)), INFO, kind="loop")
    return truth, graph


def _error(poses, truth) -> float:
    return max(np.linalg.norm(p[:3, 3] - t[:3, 3]) for p, t in zip(poses, truth))


def test_a_loop_removes_drift_and_a_false_loop_is_logged_and_dropped(caplog):
    truth, graph = _drifted()
    before = _error(graph.poses, truth)
    with caplog.at_level(logging.WARNING, logger="legslam"):
        r = graph.optimize()
    after = _error(graph.poses, truth)
    assert before > 0.2 and after < before / 10, (before, after)
    assert r.rejected == [40] and r.weights[40] == 0 and r.weights[39] > 0.9
    assert "loop edge 40 (keyframes 10-30) rejected" in caplog.text
    assert len(graph.edges) == 40 and graph.rejected[0].i == 10 and graph.rejected[0].j == 30
    # Optimised again, the graph without the false loop stays where it is (to micrometres: the
    # first solve stopped at the default tolerance).
    again = graph.optimize()
    assert again.rejected == [] and _error(graph.poses, truth) == pytest.approx(after, abs=1e-5)


def test_without_the_kernel_the_false_loop_bends_the_trajectory():
    truth, graph = _drifted()
    plain = PoseGraph(robust_scale=0.0, reject_outliers=False)
    plain.poses, plain.fixed, plain.edges = list(graph.poses), list(graph.fixed), list(graph.edges)
    plain.optimize()
    graph.optimize()
    assert _error(plain.poses, truth) > 3 * _error(graph.poses, truth)


def test_the_binding_names_the_argument_with_the_wrong_shape_or_dtype():
    poses = np.stack([np.eye(4), np.eye(4)])
    good = (0, 1, np.eye(4), np.eye(6), "odometry")

    def refused(message, poses=poses, edges=[good], **kw):
        with pytest.raises(ValueError, match=message):
            _core.optimize_pose_graph(poses, edges, **kw)

    refused(r"poses must have shape Nx4x4, got \[2, 4, 3\]", poses=poses[:, :, :3])
    refused("poses must be a float64 array, got dtype float32", poses=poses.astype(np.float32))
    refused("poses must be a Nx4x4 numpy array", poses=[np.eye(4)] * 2)
    refused("edges must be a list", edges=None)
    refused(r"edges\[0\] must be a tuple \(i, j, T_ij, information, kind\)", edges=[good[:4]])
    refused(r"edges\[1\] T_ij must have shape 4x4",
            edges=[good, (1, 0, np.eye(3), np.eye(6), "loop")])
    refused(r"edges\[0\] information must have shape 6x6, got \[6, 5\]",
            edges=[(0, 1, np.eye(4), np.eye(6)[:, :5], "loop")])
    refused(r"edges\[0\] information must be a float64 array",
            edges=[(0, 1, np.eye(4), np.eye(6, dtype=np.float32), "loop")])
    refused(r"edges\[0\] kind must be 'odometry' or 'loop', got 'odo'",
            edges=[(0, 1, np.eye(4), np.eye(6), "odo")])
    refused(r"edges\[0\] i must be a node index", edges=[(-1, 1, np.eye(4), np.eye(6), "loop")])
    refused("fixed must be a list of node indices", fixed="first")
    refused('unknown pose_graph option "scale"', options={"scale": 1.0})
    refused("pose_graph option robust_scale must be a number, got 'big'",
            options={"robust_scale": "big"})


def test_the_engine_names_what_is_wrong_with_the_values():
    poses = np.stack([np.eye(4), np.eye(4)])
    good = (0, 1, np.eye(4), np.eye(6), "odometry")
    nan = poses.copy()
    nan[1, 0, 3] = np.nan
    for message, args in (
            ("pose 1 must be finite", (nan, [good])),
            ("the pose graph has no edges", (poses, [])),
            ("edge 0 joins nodes 0 and 9, but the graph has 2 nodes",
             (poses, [(0, 9, np.eye(4), np.eye(6), "loop")])),
            ("edge 0 information must be positive definite",
             (poses, [(0, 1, np.eye(4), -np.eye(6), "loop")])),
            ("edge 0 measurement rotation must be orthonormal",
             (poses, [(0, 1, np.diag([2.0, 1, 1, 1]), np.eye(6), "loop")]))):
        with pytest.raises(ValueError, match=message):
            _core.optimize_pose_graph(*args)
    with pytest.raises(ValueError, match="fixed node 4 does not exist"):
        _core.optimize_pose_graph(poses, [good], fixed=[4])
    with pytest.raises(ValueError, match="pose_graph option robust_scale must be >= 0"):
        PoseGraph(robust_scale=-1.0)


def test_options_and_helpers():
    assert set(DEFAULT_OPTIONS) == {"max_iterations", "tolerance", "robust_scale",
                                    "reject_outliers", "outlier_chi2"}
    assert PoseGraph(max_iterations=5).options["max_iterations"] == 5
    np.testing.assert_allclose(np.diag(information(0.1, 0.01)), [100] * 3 + [1e4] * 3)
    a, b = pose((0.2, 0.1, -0.3), (1, 2, 3)), pose((-0.5, 0.3, 0.1), (0, 1, -1))
    np.testing.assert_allclose(a @ relative(a, b), b, atol=1e-12)
    with pytest.raises(ValueError, match="standard deviations must be positive"):
        information(0.0, 0.1)
