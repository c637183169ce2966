//! Bindings of the tracker (`legslam_core::track`). Python wraps these in
//! `legslam.tracking`; engine errors become `ValueError`, the GIL is released while the
//! engine works.

use legslam_core::camera::Intrinsics;
use legslam_core::track::{
    self, Color, Frame, Matrix4, Odometry, Reference, TrackResult, TrackerConfig,
};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::pool;
use pyo3::types::{PyDict, PyList};

fn err(msg: String) -> PyErr {
    PyValueError::new_err(msg)
}

/// The default tracker options as a dict (the single source of the defaults).
fn config_to_dict<'py>(py: Python<'py>, c: &TrackerConfig) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("levels", c.levels)?;
    d.set_item("finest_level", c.finest_level)?;
    d.set_item("iterations", PyList::new(py, &c.iterations)?)?;
    d.set_item("min_depth", c.min_depth)?;
    d.set_item("max_depth", c.max_depth)?;
    d.set_item("max_depth_diff", c.max_depth_diff)?;
    d.set_item("geometric_huber", c.geometric_huber)?;
    d.set_item("photometric_huber", c.photometric_huber)?;
    d.set_item("photometric_weight", c.photometric_weight)?;
    d.set_item("estimate_gain", c.estimate_gain)?;
    d.set_item("min_gradient", c.min_gradient)?;
    d.set_item("convergence_eps", c.convergence_eps)?;
    d.set_item("inlier_threshold", c.inlier_threshold)?;
    d.set_item("min_inlier_ratio", c.min_inlier_ratio)?;
    d.set_item("min_inliers", c.min_inliers)?;
    d.set_item("max_condition", c.max_condition)?;
    d.set_item("max_translation", c.max_translation)?;
    d.set_item("max_rotation_deg", c.max_rotation_deg)?;
    Ok(d)
}

fn config_from_dict(d: &Bound<'_, PyDict>) -> PyResult<TrackerConfig> {
    let mut c = TrackerConfig::default();
    for (k, v) in d.iter() {
        let key: String = k.extract()?;
        let bad = |e: PyErr| err(format!("tracker option {key}: {e}"));
        match key.as_str() {
            "levels" => c.levels = v.extract().map_err(bad)?,
            "finest_level" => c.finest_level = v.extract().map_err(bad)?,
            "iterations" => c.iterations = v.extract().map_err(bad)?,
            "min_depth" => c.min_depth = v.extract().map_err(bad)?,
            "max_depth" => c.max_depth = v.extract().map_err(bad)?,
            "max_depth_diff" => c.max_depth_diff = v.extract().map_err(bad)?,
            "geometric_huber" => c.geometric_huber = v.extract().map_err(bad)?,
            "photometric_huber" => c.photometric_huber = v.extract().map_err(bad)?,
            "photometric_weight" => c.photometric_weight = v.extract().map_err(bad)?,
            "estimate_gain" => c.estimate_gain = v.extract().map_err(bad)?,
            "min_gradient" => c.min_gradient = v.extract().map_err(bad)?,
            "convergence_eps" => c.convergence_eps = v.extract().map_err(bad)?,
            "inlier_threshold" => c.inlier_threshold = v.extract().map_err(bad)?,
            "min_inlier_ratio" => c.min_inlier_ratio = v.extract().map_err(bad)?,
            "min_inliers" => c.min_inliers = v.extract().map_err(bad)?,
            "max_condition" => c.max_condition = v.extract().map_err(bad)?,
            "max_translation" => c.max_translation = v.extract().map_err(bad)?,
            "max_rotation_deg" => c.max_rotation_deg = v.extract().map_err(bad)?,
            _ => return Err(err(format!("unknown tracker option '{key}'"))),
        }
    }
    c.validate().map_err(err)?;
    Ok(c)
}

fn matrix4(a: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Matrix4<f64>> {
    let v = a.as_array();
    if v.shape() != [4, 4] {
        return Err(err(format!("{name} must be 4x4, got {:?}", v.shape())));
    }
    Ok(Matrix4::from_fn(|i, j| v[[i, j]]))
}

fn intrinsics(k: &PyReadonlyArray2<'_, f64>, width: usize, height: usize) -> PyResult<Intrinsics> {
    let v = k.as_array();
    if v.shape() != [3, 3] {
        return Err(err(format!("K must be 3x3, got {:?}", v.shape())));
    }
    if v[[1, 0]] != 0.0 || v[[2, 0]] != 0.0 || v[[2, 1]] != 0.0 || v[[2, 2]] != 1.0 {
        return Err(err(format!(
            "K must be a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {v}"
        )));
    }
    if v[[0, 1]] != 0.0 {
        return Err(err("K with skew is not supported".into()));
    }
    let k = Intrinsics {
        fx: v[[0, 0]],
        fy: v[[1, 1]],
        cx: v[[0, 2]],
        cy: v[[1, 2]],
        width,
        height,
    };
    k.validate().map_err(err)?;
    Ok(k)
}

/// Colour (uint8 or float32 HxWx3, C-contiguous) and depth (float32 HxW) of one view.
struct View<'py> {
    rgb8: Option<PyReadonlyArray3<'py, u8>>,
    rgbf: Option<PyReadonlyArray3<'py, f32>>,
    depth: PyReadonlyArray2<'py, f32>,
    k: Intrinsics,
}

impl<'py> View<'py> {
    fn new(
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: &PyReadonlyArray2<'py, f64>,
        name: &str,
    ) -> PyResult<View<'py>> {
        let depth: PyReadonlyArray2<'py, f32> = depth.extract().map_err(|_| {
            err(format!(
                "{name} depth must be a 2-D float32 numpy array (HxW, metres)"
            ))
        })?;
        let (h, w) = (depth.shape()[0], depth.shape()[1]);
        let (rgb8, rgbf) = if let Ok(a) = rgb.extract::<PyReadonlyArray3<'py, u8>>() {
            (Some(a), None)
        } else if let Ok(a) = rgb.extract::<PyReadonlyArray3<'py, f32>>() {
            (None, Some(a))
        } else {
            return Err(err(format!(
                "{name} rgb must be an HxWx3 uint8 (or float32 in [0, 1]) numpy array"
            )));
        };
        let shape = rgb8
            .as_ref()
            .map(|a| a.shape().to_vec())
            .or_else(|| rgbf.as_ref().map(|a| a.shape().to_vec()))
            .unwrap_or_default();
        if shape != [h, w, 3] {
            return Err(err(format!(
                "{name} rgb has shape {shape:?} but depth is {h}x{w}: expected ({h}, {w}, 3)"
            )));
        }
        let k = intrinsics(k, w, h)?;
        Ok(View {
            rgb8,
            rgbf,
            depth,
            k,
        })
    }

    fn slices(&self) -> PyResult<(Color<'_>, &[f32])> {
        let nc = |_| err("arrays must be C-contiguous".to_string());
        let color = match (&self.rgb8, &self.rgbf) {
            (Some(a), _) => Color::Rgb8(a.as_slice().map_err(nc)?),
            (_, Some(a)) => Color::RgbF32(a.as_slice().map_err(nc)?),
            _ => unreachable!("View::new sets one colour array"),
        };
        Ok((color, self.depth.as_slice().map_err(nc)?))
    }
}

fn pose_array<'py>(py: Python<'py>, m: &Matrix4<f64>) -> Bound<'py, PyAny> {
    Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)])
        .into_pyarray(py)
        .into_any()
}

fn result_dict<'py>(py: Python<'py>, r: &TrackResult) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("pose", pose_array(py, &r.pose))?;
    d.set_item("residual_rms", r.residual_rms)?;
    d.set_item("geometric_rms", r.geometric_rms)?;
    d.set_item("photometric_rms", r.photometric_rms)?;
    d.set_item("inlier_ratio", r.inlier_ratio)?;
    d.set_item("inliers", r.inliers)?;
    d.set_item("condition", r.condition)?;
    d.set_item("iterations", r.iterations)?;
    d.set_item("gain", r.gain)?;
    d.set_item("lost", r.lost)?;
    d.set_item("reason", r.reason.clone())?;
    Ok(d)
}

/// A prepared reference view (pyramids, gradients, normals) with its pose.
#[pyclass(module = "legslam._core", name = "TrackReference", frozen)]
struct PyTrackReference {
    inner: Reference,
    config: TrackerConfig,
}

#[pymethods]
impl PyTrackReference {
    /// The reference pose (4x4 camera-to-world).
    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        pose_array(py, self.inner.pose())
    }
}

/// Tracker with a fixed configuration.
#[pyclass(module = "legslam._core", name = "TrackerCore", frozen)]
struct PyTracker {
    config: TrackerConfig,
    /// Worker threads of its own when asked for (see `pool`), else rayon's global pool.
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyTracker {
    /// `threads`: run on a pool of this many threads of its own instead of the global one.
    #[new]
    #[pyo3(signature = (config, threads=None))]
    fn new(config: &Bound<'_, PyDict>, threads: Option<usize>) -> PyResult<Self> {
        Ok(PyTracker {
            config: config_from_dict(config)?,
            pool: pool::build(threads, "legslam-track")?,
        })
    }

    /// The effective configuration as a dict.
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        config_to_dict(py, &self.config)
    }

    /// Prepares a reference view for tracking (reusable for many frames).
    fn prepare_reference<'py>(
        &self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: PyReadonlyArray2<'py, f64>,
        pose: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<PyTrackReference> {
        let view = View::new(rgb, depth, &k, "reference")?;
        let pose = matrix4(&pose, "reference pose")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let cfg = &self.config;
        let inner = pool::call(&self.pool, py, || Reference::new(color, d, &kk, &pose, cfg))?;
        Ok(PyTrackReference {
            inner,
            config: self.config.clone(),
        })
    }

    /// Aligns the frame to the reference from `init_pose`; returns a dict of the result.
    fn track<'py>(
        &self,
        py: Python<'py>,
        reference: &Bound<'py, PyTrackReference>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: PyReadonlyArray2<'py, f64>,
        init_pose: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let reference = reference.get();
        if reference.config != self.config {
            return Err(err(
                "the reference was prepared by a tracker with a different configuration".into(),
            ));
        }
        let view = View::new(rgb, depth, &k, "frame")?;
        let init = matrix4(&init_pose, "init_pose")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let cfg = &self.config;
        let rf = &reference.inner;
        let res = pool::call(&self.pool, py, || {
            let frame = Frame::new(color, d, &kk, cfg)?;
            track::track(rf, &frame, &init, cfg)
        })?;
        result_dict(py, &res)
    }
}

/// Frame-to-frame odometry with a constant-velocity prior.
#[pyclass(module = "legslam._core", name = "OdometryCore")]
struct PyOdometry {
    inner: Odometry,
}

#[pymethods]
impl PyOdometry {
    #[new]
    fn new(
        config: &Bound<'_, PyDict>,
        initial_pose: PyReadonlyArray2<'_, f64>,
        motion_prior: bool,
    ) -> PyResult<Self> {
        let config = config_from_dict(config)?;
        let pose = matrix4(&initial_pose, "initial_pose")?;
        Ok(PyOdometry {
            inner: Odometry::new(config, &pose, motion_prior).map_err(err)?,
        })
    }

    /// Tracks the next frame; returns `{pose, predicted, result}` (result None for the
    /// first frame).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let view = View::new(rgb, depth, &k, "frame")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let odo = &mut self.inner;
        let step = py
            .detach(|| {
                let frame = Frame::new(color, d, &kk, odo.config())?;
                odo.step(frame)
            })
            .map_err(err)?;
        let out = PyDict::new(py);
        out.set_item("pose", pose_array(py, &step.pose))?;
        out.set_item("predicted", pose_array(py, &step.predicted))?;
        match &step.result {
            Some(r) => out.set_item("result", result_dict(py, r)?)?,
            None => out.set_item("result", py.None())?,
        }
        Ok(out)
    }

    #[getter]
    fn frames(&self) -> usize {
        self.inner.frames()
    }

    #[getter]
    fn lost_frames(&self) -> usize {
        self.inner.lost_frames()
    }
}

/// The default tracker configuration as a dict.
#[pyfunction]
fn tracker_default_config(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    config_to_dict(py, &TrackerConfig::default())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyTracker>()?;
    m.add_class::<PyTrackReference>()?;
    m.add_class::<PyOdometry>()?;
    m.add_function(wrap_pyfunction!(tracker_default_config, m)?)?;
    Ok(())
}
