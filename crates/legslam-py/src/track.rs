//! Bindings of the tracker (`legslam_core::track`), wrapped in Python by `legslam.tracking`.

use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::track::{
    self, Color, Frame, Odometry, Reference, TrackResult, TrackerConfig, Tsdf, TsdfConfig,
};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{
    array, bad, contiguous, engine_call, intrinsics, options_dict, options_from, pose, pose_array,
    size,
};
use crate::pool;

/// The tracker's options: its defaults overridden by `options`, checked; a dict.
#[pyfunction]
#[pyo3(signature = (options=None))]
fn tracker_options<'py>(
    py: Python<'py>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    options_dict(py, &tracker_config(py, options)?)
}

fn tracker_config(py: Python<'_>, options: Option<&Bound<'_, PyDict>>) -> PyResult<TrackerConfig> {
    options_from(py, options, "tracker", TrackerConfig::validate)
}

/// Colour (uint8 or float32 in [0, 1], HxWx3) and depth (float32 metres, HxW) of one view.
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
        k: &Bound<'py, PyAny>,
        name: &str,
    ) -> PyResult<View<'py>> {
        let depth = array::<f32, numpy::Ix2>(depth, &format!("{name} depth"), &[None, None])?;
        let (h, w) = (Some(depth.shape()[0]), Some(depth.shape()[1]));
        let shape = [h, w, Some(3)];
        let rgb_name = format!("{name} rgb");
        let (rgb8, rgbf) = match array::<u8, numpy::Ix3>(rgb, &rgb_name, &shape) {
            Ok(a) => (Some(a), None),
            Err(e8) => match array::<f32, numpy::Ix3>(rgb, &rgb_name, &shape) {
                Ok(a) => (None, Some(a)),
                // A uint8 image of the wrong shape is reported as such.
                Err(_) if e8.to_string().contains("shape") => return Err(e8),
                Err(_) => {
                    return Err(bad(
                        &rgb_name,
                        "must be uint8 (or float32 in [0, 1]), got another dtype",
                    ))
                }
            },
        };
        let k = intrinsics(k, w.unwrap_or(0), h.unwrap_or(0))?;
        Ok(View {
            rgb8,
            rgbf,
            depth,
            k,
        })
    }

    fn slices(&self) -> PyResult<(Color<'_>, &[f32])> {
        let color = match (&self.rgb8, &self.rgbf) {
            (Some(a), _) => Color::Rgb8(contiguous("rgb", a)?),
            (_, Some(a)) => Color::RgbF32(contiguous("rgb", a)?),
            _ => unreachable!("View::new sets one colour array"),
        };
        Ok((color, contiguous("depth", &self.depth)?))
    }
}

/// The outcome of one alignment; see `legslam.tracking` for the fields.
#[pyclass(module = "legslam._core", name = "TrackResult", frozen, get_all)]
pub struct PyTrackResult {
    pose: Py<PyAny>,
    residual_rms: f64,
    geometric_rms: f64,
    photometric_rms: f64,
    inlier_ratio: f64,
    inliers: usize,
    condition: f64,
    iterations: usize,
    gain: f64,
    lost: bool,
    reason: Option<String>,
}

impl PyTrackResult {
    fn new(py: Python<'_>, r: TrackResult) -> Self {
        PyTrackResult {
            pose: pose_array(py, &r.pose).unbind(),
            residual_rms: r.residual_rms,
            geometric_rms: r.geometric_rms,
            photometric_rms: r.photometric_rms,
            inlier_ratio: r.inlier_ratio,
            inliers: r.inliers,
            condition: r.condition,
            iterations: r.iterations,
            gain: r.gain,
            lost: r.lost,
            reason: r.reason,
        }
    }
}

#[pymethods]
impl PyTrackResult {
    fn __repr__(&self) -> String {
        format!(
            "TrackResult(lost={}, reason={:?}, residual_rms={:.4}, inlier_ratio={:.3}, iterations={})",
            self.lost, self.reason, self.residual_rms, self.inlier_ratio, self.iterations
        )
    }
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
    /// `options`: tracker options by name (see `tracker_options`); `threads`: run on a pool of
    /// this many threads of its own instead of the global one.
    #[new]
    #[pyo3(signature = (options=None, threads=None))]
    fn new(
        py: Python<'_>,
        options: Option<&Bound<'_, PyDict>>,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        Ok(PyTracker {
            config: tracker_config(py, options)?,
            pool: pool::build(threads, "legslam-track", false)?,
        })
    }

    /// The effective configuration as a dict.
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        options_dict(py, &self.config)
    }

    /// Prepares a reference view with camera-to-world `pose` (reusable for many frames).
    fn prepare_reference<'py>(
        &self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
        pose_c2w: &Bound<'py, PyAny>,
    ) -> PyResult<PyTrackReference> {
        let view = View::new(rgb, depth, k, "reference")?;
        let pose = pose(pose_c2w, "ref_pose")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let cfg = &self.config;
        let inner = pool::call(&self.pool, py, || Reference::new(color, d, &kk, &pose, cfg))?;
        Ok(PyTrackReference {
            inner,
            config: self.config.clone(),
        })
    }

    /// Aligns the frame to the reference from `init_pose`.
    fn track<'py>(
        &self,
        py: Python<'py>,
        reference: &Bound<'py, PyTrackReference>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
        init_pose: &Bound<'py, PyAny>,
    ) -> PyResult<PyTrackResult> {
        let reference = reference.get();
        if reference.config != self.config {
            return Err(PyValueError::new_err(
                "the reference was prepared by a tracker with a different configuration",
            ));
        }
        let view = View::new(rgb, depth, k, "frame")?;
        let init: Pose = pose(init_pose, "init_pose")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let cfg = &self.config;
        let rf = &reference.inner;
        let res = pool::call(&self.pool, py, || {
            let frame = Frame::new(color, d, &kk, cfg)?;
            track::track(rf, &frame, &init, cfg)
        })?;
        Ok(PyTrackResult::new(py, res))
    }
}

/// One frame of odometry: the pose assigned to it (tracked, or the constant-velocity
/// prediction when lost), the prediction, and the alignment (None for the first frame).
#[pyclass(module = "legslam._core", name = "OdometryStep", frozen, get_all)]
pub struct PyOdometryStep {
    pose: Py<PyAny>,
    predicted: Py<PyAny>,
    result: Option<Py<PyTrackResult>>,
}

#[pymethods]
impl PyOdometryStep {
    /// Whether the alignment failed (the pose is then the prediction).
    #[getter]
    fn lost(&self, py: Python<'_>) -> bool {
        self.result.as_ref().is_some_and(|r| r.borrow(py).lost)
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
    #[pyo3(signature = (options, initial_pose, motion_prior))]
    fn new(
        py: Python<'_>,
        options: Option<&Bound<'_, PyDict>>,
        initial_pose: &Bound<'_, PyAny>,
        motion_prior: bool,
    ) -> PyResult<Self> {
        let config = tracker_config(py, options)?;
        let pose = pose(initial_pose, "initial_pose")?;
        let inner = engine_call(py, || Odometry::new(config, &pose, motion_prior))?;
        Ok(PyOdometry { inner })
    }

    /// Tracks the next frame.
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
    ) -> PyResult<PyOdometryStep> {
        let view = View::new(rgb, depth, k, "frame")?;
        let (color, d) = view.slices()?;
        let kk = view.k;
        let odo = &mut self.inner;
        let step = engine_call(py, || {
            let frame = Frame::new(color, d, &kk, odo.config())?;
            odo.step(frame)
        })?;
        Ok(PyOdometryStep {
            pose: pose_array(py, &step.pose).unbind(),
            predicted: pose_array(py, &step.predicted).unbind(),
            result: step
                .result
                .map(|r| Py::new(py, PyTrackResult::new(py, r)))
                .transpose()?,
        })
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

/// The fused surface volume (`legslam_core::track::Tsdf`); see `legslam.slam.surface`.
#[pyclass(module = "legslam._core", name = "TsdfCore")]
struct PyTsdf {
    inner: Tsdf,
    /// Worker threads of its own when asked for (see `pool`), else rayon's global pool.
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyTsdf {
    /// `threads`: a pool of its own, as `MapperCore`'s (a fusion beside the tracker in real
    /// time), at the tracker's priority: the tracker waits for its ray-casts.
    #[new]
    #[pyo3(signature = (voxel, truncation, max_weight, min_depth, max_depth, threads=None))]
    fn new(
        py: Python<'_>,
        voxel: f64,
        truncation: f64,
        max_weight: f32,
        min_depth: f64,
        max_depth: f64,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        let cfg = TsdfConfig {
            voxel,
            truncation,
            max_weight,
            min_depth,
            max_depth,
        };
        let inner = engine_call(py, || Tsdf::new(cfg))?;
        let pool = pool::build(threads, "legslam-surface", false)?;
        Ok(PyTsdf { inner, pool })
    }

    /// Fuses `depth` (float32 HxW metres, 0 = none) seen through `k` from `pose` (c2w).
    fn integrate<'py>(
        &mut self,
        py: Python<'py>,
        depth: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
        pose_c2w: &Bound<'py, PyAny>,
    ) -> PyResult<()> {
        let depth = array::<f32, numpy::Ix2>(depth, "depth", &[None, None])?;
        let kk = intrinsics(k, depth.shape()[1], depth.shape()[0])?;
        let p = pose(pose_c2w, "pose")?;
        let d = contiguous("depth", &depth)?;
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || inner.integrate(d, &kk, &p))
    }

    /// The fused surface's depth (float32 height x width, 0 where none) through `k` from
    /// `pose` (c2w); with `near` (float32 height x width), each ray where it has depth d starts
    /// at d - 2 truncation and those through its holes cover only the depths it measured,
    /// one ray through the centre of each `hole_cell` x `hole_cell` cell of pixels giving its
    /// holes' depth.
    #[pyo3(signature = (k, width, height, pose_c2w, near=None, hole_cell=1))]
    #[allow(clippy::too_many_arguments)] // Python's keyword arguments
    fn raycast<'py>(
        &self,
        py: Python<'py>,
        k: &Bound<'py, PyAny>,
        width: i64,
        height: i64,
        pose_c2w: &Bound<'py, PyAny>,
        near: Option<&Bound<'py, PyAny>>,
        hole_cell: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (w, h) = size(width, height)?;
        let kk = intrinsics(k, w, h)?;
        let p = pose(pose_c2w, "pose")?;
        let near = near
            .map(|a| array::<f32, numpy::Ix2>(a, "near", &[Some(h), Some(w)]))
            .transpose()?;
        let near = near.as_ref().map(|a| contiguous("near", a)).transpose()?;
        let inner = &self.inner;
        let out = pool::call(&self.pool, py, || {
            let mut out = vec![0.0f32; w * h];
            match near {
                Some(d) => inner.raycast_near(&kk, &p, d, hole_cell, &mut out),
                None => inner.raycast(&kk, &p, &mut out),
            }
            .map(|_| out)
        })?;
        Ok(PyArray1::from_vec(py, out).reshape([h, w])?.into_any())
    }

    /// Allocated voxel blocks.
    #[getter]
    fn blocks(&self) -> usize {
        self.inner.blocks()
    }

    /// Bytes held by the voxels.
    #[getter]
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyTracker>()?;
    m.add_class::<PyTsdf>()?;
    m.add_class::<PyTrackReference>()?;
    m.add_class::<PyTrackResult>()?;
    m.add_class::<PyOdometry>()?;
    m.add_class::<PyOdometryStep>()?;
    m.add_function(wrap_pyfunction!(tracker_options, m)?)?;
    Ok(())
}
