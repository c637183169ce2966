//! Bindings of the mapper: the map lives here in Rust; frames cross once, images and arrays
//! are copied out only on request.

use std::collections::HashMap;

use legslam_core::camera::Pose;
use legslam_core::map::train::{Mapper, MapperConfig, TrainReport};
use legslam_core::map::{FeatureGrid, GaussianMap};
use legslam_core::optim::{Groups, LR_NAMES};
use legslam_core::raster::Rendered;
use legslam_core::Real;
use numpy::{PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{array, contiguous, intrinsics, options_dict, options_from, pose, size};
use crate::pool;

/// The mapper's options: its defaults overridden by `options`, checked; a dict.
#[pyfunction]
#[pyo3(signature = (options=None))]
fn mapper_options<'py>(
    py: Python<'py>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    let c = options_from(py, options, "mapper", MapperConfig::validate)?;
    options_dict(py, &c)
}

/// `MapperCore.train`'s learning-rate scale: one for every group, or by group name.
#[derive(FromPyObject)]
enum LrScale {
    All(f64),
    Groups(HashMap<String, f64>),
}

impl LrScale {
    fn groups(self) -> PyResult<Groups<Real>> {
        match self {
            LrScale::All(s) => Ok(Groups::splat(s as Real)),
            LrScale::Groups(named) => {
                let mut scales = [1.0; 6];
                for (name, s) in named {
                    let i = LR_NAMES.iter().position(|n| *n == name).ok_or_else(|| {
                        PyValueError::new_err(format!(
                            "no learning-rate group {name:?} ({})",
                            LR_NAMES.join(", ")
                        ))
                    })?;
                    scales[i] = s as Real;
                }
                Ok(Groups::from_array(scales))
            }
        }
    }
}

/// What `MapperCore.train` did: iterations run, the last iteration's loss terms, the
/// Gaussians densification and pruning added and removed, and seconds per phase.
#[pyclass(module = "legslam._core", name = "TrainReport", frozen, get_all)]
pub struct PyTrainReport {
    iterations: usize,
    loss: f64,
    color_l1: f64,
    ssim: f64,
    depth_l1: f64,
    feature_loss: f64,
    cloned: usize,
    split: usize,
    pruned: usize,
    render_s: f64,
    loss_s: f64,
    backward_s: f64,
    step_s: f64,
}

impl From<TrainReport> for PyTrainReport {
    fn from(r: TrainReport) -> Self {
        PyTrainReport {
            iterations: r.iterations,
            loss: r.last.total,
            color_l1: r.last.color_l1,
            ssim: r.last.ssim,
            depth_l1: r.last.depth_l1,
            feature_loss: r.last.feature,
            cloned: r.cloned,
            split: r.split,
            pruned: r.pruned,
            render_s: r.render_s,
            loss_s: r.loss_s,
            backward_s: r.backward_s,
            step_s: r.step_s,
        }
    }
}

/// Images of the map rendered from a pose: colour HxWx3 (None when not asked for), depth and
/// alpha HxW (float32), and features HxWxK when asked for (else None).
#[pyclass(module = "legslam._core", name = "MapRender", frozen, get_all)]
pub struct PyMapRender {
    color: Option<Py<PyAny>>,
    depth: Py<PyAny>,
    alpha: Py<PyAny>,
    features: Option<Py<PyAny>>,
}

impl PyMapRender {
    fn new(py: Python<'_>, r: &Rendered) -> PyResult<Self> {
        let (w, h) = (r.width, r.height);
        let image = |v: &[f32], shape: Vec<usize>| -> PyResult<Py<PyAny>> {
            Ok(PyArray1::from_slice(py, v)
                .reshape(shape)?
                .into_any()
                .unbind())
        };
        Ok(PyMapRender {
            color: (!r.color.is_empty())
                .then(|| image(&r.color, vec![h, w, 3]))
                .transpose()?,
            depth: image(&r.depth, vec![h, w])?,
            alpha: image(&r.alpha, vec![h, w])?,
            features: (!r.features.is_empty())
                .then(|| image(&r.features, vec![h, w, r.num_features]))
                .transpose()?,
        })
    }
}

#[pyclass(module = "legslam._core", name = "MapperCore")]
pub struct PyMapper {
    inner: Mapper,
    /// Worker threads of its own when asked for (see `pool`), else rayon's global pool.
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyMapper {
    /// `options`: mapper options by name (see `mapper_options`); `threads`: run on a pool of
    /// this many threads of its own instead of the global one; `background`: that pool's
    /// threads give way to the process's others (a tracker beside them; Linux).
    #[new]
    #[pyo3(signature = (options=None, threads=None, background=false))]
    fn new(
        py: Python<'_>,
        options: Option<&Bound<'_, PyDict>>,
        threads: Option<usize>,
        background: bool,
    ) -> PyResult<Self> {
        // Mapper::new checks the options.
        let config = options_from(py, options, "mapper", |_: &MapperConfig| Ok(()))?;
        let pool = pool::build(threads, "legslam-map", background)?;
        let inner = pool::call(&pool, py, || Mapper::new(config))?;
        Ok(PyMapper { inner, pool })
    }

    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        options_dict(py, &self.inner.config)
    }

    #[getter]
    fn num_gaussians(&self) -> usize {
        self.inner.map.len()
    }

    #[getter]
    fn num_keyframes(&self) -> usize {
        self.inner.keyframes.len()
    }

    /// Adds a keyframe: rgb HxWx3 float32 in [0, 1], depth HxW float32 metres, K 3x3,
    /// camera-to-world pose 4x4. Returns (keyframe id, Gaussians added).
    fn add_keyframe<'py>(
        &mut self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
        pose_c2w: &Bound<'py, PyAny>,
    ) -> PyResult<(u32, usize)> {
        let depth = array::<f32, numpy::Ix2>(depth, "depth", &[None, None])?;
        let (h, w) = (depth.shape()[0], depth.shape()[1]);
        let rgb = array::<f32, numpy::Ix3>(rgb, "rgb", &[Some(h), Some(w), Some(3)])?;
        let intr = intrinsics(k, w, h)?;
        let p = pose(pose_c2w, "pose")?;
        let rgb = contiguous("rgb", &rgb)?.to_vec();
        let depth = contiguous("depth", &depth)?.to_vec();
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || inner.add_keyframe(rgb, depth, intr, p))
    }

    /// Sets keyframe `id`'s feature grid (h x w x K float32, compressed).
    fn set_features<'py>(
        &mut self,
        py: Python<'py>,
        id: u32,
        grid: &Bound<'py, PyAny>,
    ) -> PyResult<()> {
        let grid = array::<f32, numpy::Ix3>(grid, "grid", &[None, None, None])?;
        let s = grid.shape().to_vec();
        let data = contiguous("grid", &grid)?.to_vec();
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || {
            let g = FeatureGrid::new(data, s[1], s[0], s[2])?;
            inner.set_features(id, g)
        })
    }

    /// Runs mapping iterations on keyframes drawn from the most recent `window` (default: the
    /// configured window), with the Gaussians' learning rates `lr_scale` times the configured:
    /// one number for every group, or a dict of group (the mapper options' `lr_` names:
    /// means, log_scales, quats, opacity, sh, features) to its scale, 1 for those left out.
    #[pyo3(signature = (iterations, window=None, lr_scale=LrScale::All(1.0)))]
    fn train(
        &mut self,
        py: Python<'_>,
        iterations: usize,
        window: Option<usize>,
        lr_scale: LrScale,
    ) -> PyResult<PyTrainReport> {
        let scales = lr_scale.groups()?;
        let inner = &mut self.inner;
        let window = window.unwrap_or(inner.config.window);
        let r = pool::call(&self.pool, py, || {
            inner.set_lr_scales(scales)?;
            inner.train_window(iterations, window)
        })?;
        Ok(r.into())
    }

    /// Renders the map from a camera-to-world pose (features when asked and the map has them;
    /// without `color`, depth and alpha alone, the same values, at less cost).
    #[pyo3(signature = (pose_c2w, k, width, height, features=false, color=true))]
    #[allow(clippy::too_many_arguments)] // Python's keyword arguments
    fn render<'py>(
        &self,
        py: Python<'py>,
        pose_c2w: &Bound<'py, PyAny>,
        k: &Bound<'py, PyAny>,
        width: i64,
        height: i64,
        features: bool,
        color: bool,
    ) -> PyResult<PyMapRender> {
        let (width, height) = size(width, height)?;
        let p = pose(pose_c2w, "pose")?;
        let intr = intrinsics(k, width, height)?;
        let inner = &self.inner;
        let r = pool::call(&self.pool, py, || inner.render(&p, intr, color, features))?;
        PyMapRender::new(py, &r)
    }

    /// Every keyframe's camera-to-world pose (refined by mapping when pose learning rates are
    /// set), in keyframe order: n x 4 x 4.
    fn keyframe_poses<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let kfs = &self.inner.keyframes;
        let flat = pool::call(&self.pool, py, || {
            Ok(kfs
                .iter()
                .flat_map(|k| k.pose.transpose().iter().copied().collect::<Vec<_>>())
                .collect::<Vec<f64>>())
        })?;
        Ok(PyArray1::from_vec(py, flat)
            .reshape([kfs.len(), 4, 4])?
            .into_any())
    }

    /// Moves keyframe k by `corrections[k]` (n x 4 x 4 float64, rigid world-to-world
    /// transforms, n at most the keyframes) and every Gaussian it made with it; returns the
    /// Gaussians moved.
    fn correct_keyframes(
        &mut self,
        py: Python<'_>,
        corrections: &Bound<'_, PyAny>,
    ) -> PyResult<usize> {
        let a = array::<f64, numpy::Ix3>(corrections, "corrections", &[None, Some(4), Some(4)])?;
        let v = a.as_array();
        let c: Vec<Pose> = (0..v.shape()[0])
            .map(|k| Pose::from_fn(|i, j| v[[k, i, j]]))
            .collect();
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || inner.correct_keyframes(&c))
    }

    /// Every keyframe's exposure as n x 2 x 3: per channel the gain and the bias that take
    /// the map's colour to what the camera recorded (1 and 0 when exposures are not trained).
    fn keyframe_exposures<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let kfs = &self.inner.keyframes;
        let flat = pool::call(&self.pool, py, || {
            Ok(kfs
                .iter()
                .flat_map(|k| {
                    k.exposure
                        .log_gain
                        .map(Real::exp)
                        .into_iter()
                        .chain(k.exposure.bias)
                })
                .collect::<Vec<Real>>())
        })?;
        Ok(PyArray1::from_vec(py, flat)
            .reshape([kfs.len(), 2, 3])?
            .into_any())
    }

    /// The map's arrays (copies), named as `GaussianMap`'s fields.
    fn export<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m: &GaussianMap = &self.inner.map;
        let copy = pool::call(&self.pool, py, || Ok(m.clone()))?;
        let n = copy.len();
        let d = PyDict::new(py);
        let put = |name: &str, v: Vec<Real>, shape: Vec<usize>| -> PyResult<()> {
            d.set_item(name, PyArray1::from_vec(py, v).reshape(shape)?)
        };
        put("means", copy.means, vec![n, 3])?;
        put("log_scales", copy.log_scales, vec![n, 3])?;
        put("quats", copy.quats, vec![n, 4])?;
        put("opacity_logits", copy.opacity_logits, vec![n])?;
        put("sh", copy.sh, vec![n, copy.sh_coeffs, 3])?;
        put("features", copy.features, vec![n, copy.num_features])?;
        Ok(d)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyMapper>()?;
    m.add_class::<PyTrainReport>()?;
    m.add_class::<PyMapRender>()?;
    m.add_function(wrap_pyfunction!(mapper_options, m)?)?;
    Ok(())
}
