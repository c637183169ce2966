//! Bindings of the pose-graph optimiser (`legslam_core::graph`), wrapped in Python by
//! `legslam.slam.pose_graph`.

use legslam_core::camera::Pose;
use legslam_core::graph::{
    self, Edge, EdgeKind, Information, PoseGraph, PoseGraphConfig, PoseGraphResult,
};
use numpy::ndarray::Array3;
use numpy::IntoPyArray;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{array, bad, engine_call, options_dict, options_from, pose};

/// The pose graph's options: its defaults overridden by `options`, checked; a dict.
#[pyfunction]
#[pyo3(signature = (options=None))]
fn pose_graph_options<'py>(
    py: Python<'py>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    options_dict(py, &config(py, options)?)
}

fn config(py: Python<'_>, options: Option<&Bound<'_, PyDict>>) -> PyResult<PoseGraphConfig> {
    options_from(py, options, "pose_graph", PoseGraphConfig::validate)
}

/// The outcome of `optimize_pose_graph`; see `legslam.slam.pose_graph` for the fields.
#[pyclass(module = "legslam._core", name = "PoseGraphResult", frozen, get_all)]
pub struct PyPoseGraphResult {
    poses: Py<PyAny>,
    chi2: Py<PyAny>,
    weights: Py<PyAny>,
    rejected: Vec<usize>,
    iterations: usize,
    initial_cost: f64,
    final_cost: f64,
    converged: bool,
    seconds: f64,
}

impl PyPoseGraphResult {
    fn new(py: Python<'_>, r: PoseGraphResult) -> Self {
        let poses = Array3::from_shape_fn((r.poses.len(), 4, 4), |(k, i, j)| r.poses[k][(i, j)]);
        PyPoseGraphResult {
            poses: poses.into_pyarray(py).into_any().unbind(),
            chi2: r.chi2.into_pyarray(py).into_any().unbind(),
            weights: r.weights.into_pyarray(py).into_any().unbind(),
            rejected: r.rejected,
            iterations: r.iterations,
            initial_cost: r.initial_cost,
            final_cost: r.final_cost,
            converged: r.converged,
            seconds: r.seconds,
        }
    }
}

#[pymethods]
impl PyPoseGraphResult {
    fn __repr__(&self) -> String {
        format!(
            "PoseGraphResult(rejected={:?}, iterations={}, initial_cost={:.4}, final_cost={:.4}, converged={})",
            self.rejected, self.iterations, self.initial_cost, self.final_cost, self.converged
        )
    }
}

/// Edge `k` from a sequence `(i, j, T_ij, information, kind)`.
fn edge(k: usize, item: &Bound<'_, PyAny>) -> PyResult<Edge> {
    let name = format!("edges[{k}]");
    let parts: Vec<Bound<'_, PyAny>> = item
        .extract()
        .ok()
        .filter(|p: &Vec<_>| p.len() == 5)
        .ok_or_else(|| bad(&name, "must be a tuple (i, j, T_ij, information, kind)"))?;
    let node = |p: &Bound<'_, PyAny>, which: &str| {
        p.extract::<usize>().map_err(|_| {
            bad(
                &format!("{name} {which}"),
                "must be a node index (a whole number >= 0)",
            )
        })
    };
    let info = array::<f64, numpy::Ix2>(
        &parts[3],
        &format!("{name} information"),
        &[Some(6), Some(6)],
    )?;
    let v = info.as_array();
    let kind = match parts[4].extract::<String>().as_deref() {
        Ok("odometry") => EdgeKind::Odometry,
        Ok("loop") => EdgeKind::Loop,
        _ => {
            let got = parts[4].repr().map_or("?".into(), |r| r.to_string());
            return Err(bad(
                &format!("{name} kind"),
                format!("must be 'odometry' or 'loop', got {got}"),
            ));
        }
    };
    Ok(Edge {
        from: node(&parts[0], "i")?,
        to: node(&parts[1], "j")?,
        measurement: pose(&parts[2], &format!("{name} T_ij"))?,
        information: Information::from_fn(|i, j| v[[i, j]]),
        kind,
    })
}

/// Optimises keyframe poses (N x 4 x 4 float64, camera-to-world) under relative-pose `edges`,
/// each `(i, j, T_ij, information, kind)`: T_ij the pose of node j in node i's frame (4x4
/// float64), its 6x6 float64 information (translation first), kind 'odometry' or 'loop'. The
/// nodes in `fixed` stay where they are; `options` are the pose graph's options by name.
#[pyfunction]
#[pyo3(signature = (poses, edges, fixed=None, options=None))]
fn optimize_pose_graph(
    py: Python<'_>,
    poses: &Bound<'_, PyAny>,
    edges: &Bound<'_, PyAny>,
    fixed: Option<&Bound<'_, PyAny>>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<PyPoseGraphResult> {
    let a = array::<f64, numpy::Ix3>(poses, "poses", &[None, Some(4), Some(4)])?;
    let v = a.as_array();
    let poses: Vec<Pose> = (0..v.shape()[0])
        .map(|k| Pose::from_fn(|i, j| v[[k, i, j]]))
        .collect();
    let items: Vec<Bound<'_, PyAny>> = edges
        .extract()
        .map_err(|_| bad("edges", "must be a list of (i, j, T_ij, information, kind)"))?;
    let edges = items
        .iter()
        .enumerate()
        .map(|(k, item)| edge(k, item))
        .collect::<PyResult<Vec<Edge>>>()?;
    let fixed = match fixed {
        None => vec![0],
        Some(f) => f.extract().map_err(|_| {
            bad(
                "fixed",
                "must be a list of node indices (whole numbers >= 0)",
            )
        })?,
    };
    let config = config(py, options)?;
    let graph = PoseGraph {
        poses,
        fixed,
        edges,
    };
    let result = engine_call(py, || graph::optimize(&graph, &config))?;
    Ok(PyPoseGraphResult::new(py, result))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyPoseGraphResult>()?;
    m.add_function(wrap_pyfunction!(pose_graph_options, m)?)?;
    m.add_function(wrap_pyfunction!(optimize_pose_graph, m)?)?;
    Ok(())
}
