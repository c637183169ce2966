//! Bindings of the mapper: the map lives here in Rust; frames cross once, images and arrays
//! are copied out only on request.

use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::map::train::{Mapper, MapperConfig};
use legslam_core::map::{FeatureGrid, GaussianMap};
use legslam_core::Real;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::pool;

fn config_from_dict(d: Option<&Bound<'_, PyDict>>) -> PyResult<MapperConfig> {
    let mut c = MapperConfig::default();
    if let Some(d) = d {
        for (k, v) in d.iter() {
            let key: String = k.extract()?;
            let value: f64 = v.extract().map_err(|_| {
                PyValueError::new_err(format!("mapper option {key} must be a number"))
            })?;
            c.set(&key, value).map_err(PyValueError::new_err)?;
        }
    }
    Ok(c)
}

/// The mapper's default options as a dict.
#[pyfunction]
fn mapper_default_config(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    for (k, v) in MapperConfig::default().entries() {
        d.set_item(k, v)?;
    }
    Ok(d)
}

fn pose(p: &PyReadonlyArray2<'_, f64>) -> PyResult<Pose> {
    let a = p.as_array();
    if a.shape() != [4, 4] {
        return Err(PyValueError::new_err(format!(
            "pose must be a 4x4 camera-to-world matrix, got shape {:?}",
            a.shape()
        )));
    }
    let mut out = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            out[i][j] = a[[i, j]];
        }
    }
    Ok(out)
}

#[pyclass(module = "legslam._core", name = "MapperCore")]
pub struct PyMapper {
    inner: Mapper,
    /// Worker threads of its own when asked for (see `pool`), else rayon's global pool.
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyMapper {
    /// `threads`: run on a pool of this many threads of its own instead of the global one.
    #[new]
    #[pyo3(signature = (config=None, threads=None))]
    fn new(config: Option<&Bound<'_, PyDict>>, threads: Option<usize>) -> PyResult<Self> {
        let inner = Mapper::new(config_from_dict(config)?).map_err(PyValueError::new_err)?;
        let pool = pool::build(threads, "legslam-map")?;
        Ok(PyMapper { inner, pool })
    }

    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in self.inner.config.entries() {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    #[getter]
    fn num_gaussians(&self) -> usize {
        self.inner.map.len()
    }

    #[getter]
    fn num_keyframes(&self) -> usize {
        self.inner.keyframes.len()
    }

    #[getter]
    fn extent(&self) -> f64 {
        self.inner.extent() as f64
    }

    /// Adds a keyframe: rgb HxWx3 float32 in [0, 1], depth HxW float32 metres, K as
    /// (fx, fy, cx, cy), camera-to-world pose. Returns (keyframe id, Gaussians added).
    fn add_keyframe(
        &mut self,
        py: Python<'_>,
        rgb: PyReadonlyArray3<'_, f32>,
        depth: PyReadonlyArray2<'_, f32>,
        k: [f64; 4],
        pose_c2w: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<(u32, usize)> {
        let (h, w) = (depth.shape()[0], depth.shape()[1]);
        if rgb.shape() != [h, w, 3] {
            return Err(PyValueError::new_err(format!(
                "rgb must be {h}x{w}x3 like the depth, got {:?}",
                rgb.shape()
            )));
        }
        let rgb = rgb.as_array().iter().copied().collect();
        let depth = depth.as_array().iter().copied().collect();
        let p = pose(&pose_c2w)?;
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || {
            inner.add_keyframe(rgb, depth, Intrinsics::from_array(k, w, h), p)
        })
    }

    /// Sets keyframe `id`'s feature grid (h x w x K float32, compressed).
    fn set_features(
        &mut self,
        py: Python<'_>,
        id: u32,
        grid: PyReadonlyArray3<'_, f32>,
    ) -> PyResult<()> {
        let s = grid.shape().to_vec();
        let data = grid.as_array().iter().copied().collect();
        let inner = &mut self.inner;
        pool::call(&self.pool, py, || {
            let g = FeatureGrid::new(data, s[1], s[0], s[2])?;
            inner.set_features(id, g)
        })
    }

    /// Runs mapping iterations on keyframes drawn from the most recent `window` (default: the
    /// configured window); returns a dict of what happened.
    #[pyo3(signature = (iterations, window=None))]
    fn train<'py>(
        &mut self,
        py: Python<'py>,
        iterations: usize,
        window: Option<usize>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let inner = &mut self.inner;
        let window = window.unwrap_or(inner.config.window);
        let r = pool::call(&self.pool, py, || inner.train_window(iterations, window))?;
        let d = PyDict::new(py);
        d.set_item("iterations", r.iterations)?;
        d.set_item("loss", r.last.total)?;
        d.set_item("color_l1", r.last.color_l1)?;
        d.set_item("ssim", r.last.ssim)?;
        d.set_item("depth_l1", r.last.depth_l1)?;
        d.set_item("feature_loss", r.last.feature)?;
        d.set_item("cloned", r.cloned)?;
        d.set_item("split", r.split)?;
        d.set_item("pruned", r.pruned)?;
        d.set_item("render_s", r.render_s)?;
        d.set_item("loss_s", r.loss_s)?;
        d.set_item("backward_s", r.backward_s)?;
        d.set_item("step_s", r.step_s)?;
        Ok(d)
    }

    /// Renders the map from a camera-to-world pose: dict of color, depth, alpha (and
    /// features when asked and the map has them).
    #[pyo3(signature = (pose_c2w, k, width, height, features=false))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        pose_c2w: PyReadonlyArray2<'_, f64>,
        k: [f64; 4],
        width: usize,
        height: usize,
        features: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        let p = pose(&pose_c2w)?;
        let inner = &self.inner;
        let r = pool::call(&self.pool, py, || {
            inner.render(&p, Intrinsics::from_array(k, width, height), features)
        })?;
        let d = PyDict::new(py);
        d.set_item(
            "color",
            PyArray1::from_slice(py, &r.color).reshape([height, width, 3])?,
        )?;
        d.set_item(
            "depth",
            PyArray1::from_slice(py, &r.depth).reshape([height, width])?,
        )?;
        d.set_item(
            "alpha",
            PyArray1::from_slice(py, &r.alpha).reshape([height, width])?,
        )?;
        if !r.features.is_empty() {
            d.set_item(
                "features",
                PyArray1::from_slice(py, &r.features).reshape([height, width, r.num_features])?,
            )?;
        }
        Ok(d)
    }

    /// Every keyframe's camera-to-world pose (refined by mapping when pose learning rates are
    /// set), in keyframe order: n x 4 x 4.
    fn keyframe_poses<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let flat: Vec<f64> = self
            .inner
            .keyframes
            .iter()
            .flat_map(|k| k.pose.into_iter().flatten())
            .collect();
        let n = self.inner.keyframes.len();
        Ok(PyArray1::from_vec(py, flat).reshape([n, 4, 4])?.into_any())
    }

    /// Every keyframe's exposure as n x 2 x 3: per channel the gain and the bias that take
    /// the map's colour to what the camera recorded (1 and 0 when exposures are not trained).
    fn keyframe_exposures<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let flat: Vec<Real> = self
            .inner
            .keyframes
            .iter()
            .flat_map(|k| {
                k.exposure
                    .log_gain
                    .map(Real::exp)
                    .into_iter()
                    .chain(k.exposure.bias)
            })
            .collect();
        let n = self.inner.keyframes.len();
        Ok(PyArray1::from_vec(py, flat).reshape([n, 2, 3])?.into_any())
    }

    /// The map's arrays (copies).
    fn export<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m: &GaussianMap = &self.inner.map;
        let n = m.len();
        let d = PyDict::new(py);
        d.set_item("means", PyArray1::from_slice(py, &m.means).reshape([n, 3])?)?;
        d.set_item(
            "log_scales",
            PyArray1::from_slice(py, &m.log_scales).reshape([n, 3])?,
        )?;
        d.set_item("quats", PyArray1::from_slice(py, &m.quats).reshape([n, 4])?)?;
        d.set_item(
            "opacity_logits",
            PyArray1::from_slice(py, &m.opacity_logits),
        )?;
        d.set_item(
            "sh",
            PyArray1::from_slice(py, &m.sh).reshape([n, m.sh_coeffs, 3])?,
        )?;
        d.set_item(
            "features",
            PyArray1::from_slice(py, &m.features).reshape([n, m.num_features])?,
        )?;
        Ok(d)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyMapper>()?;
    m.add_function(wrap_pyfunction!(mapper_default_config, m)?)?;
    Ok(())
}
