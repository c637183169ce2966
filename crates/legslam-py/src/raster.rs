//! Bindings of the rasterizer: `render` returns a `Render` holding the images and what its
//! `backward` needs. Shapes and dtypes are checked by the Python wrapper (legslam.render);
//! values (finite, unit quaternions, sizes) by the engine, whose errors become ValueError.

use legslam_core::camera::Intrinsics;
use legslam_core::map::GaussianMap;
use legslam_core::raster::{
    backward, render as engine_render, Camera, ImageGrads, RenderOptions, Rendered,
};
use numpy::{
    PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArrayDyn,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// Runs engine code without the GIL, turning errors into ValueError and a panic (a bug) into
/// RuntimeError instead of letting it cross into Python.
pub fn engine_call<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, String> + Send,
) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|_| {
            PyRuntimeError::new_err("legslam engine failed internally (a bug): please report it")
        })?
        .map_err(PyValueError::new_err)
}

pub(crate) fn contiguous<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    name: &str,
    a: &'a numpy::PyReadonlyArray<'_, T, D>,
) -> PyResult<&'a [T]> {
    a.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name} must be a C-contiguous array")))
}

#[pyclass(module = "legslam._core", name = "Render")]
pub struct PyRender {
    /// The Gaussians rendered, owned so that `backward` sees exactly what was rendered.
    gaussians: GaussianMap,
    camera: Camera,
    rendered: Rendered,
}

fn image<'py>(py: Python<'py>, v: &[f32], shape: &[usize]) -> PyResult<Option<Bound<'py, PyAny>>> {
    if v.is_empty() {
        return Ok(None);
    }
    Ok(Some(
        PyArray1::from_slice(py, v)
            .reshape(shape.to_vec())?
            .into_any(),
    ))
}

#[pymethods]
impl PyRender {
    #[getter]
    fn color<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let r = &self.rendered;
        image(py, &r.color, &[r.height, r.width, 3])
    }
    #[getter]
    fn depth<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let r = &self.rendered;
        image(py, &r.depth, &[r.height, r.width])
    }
    #[getter]
    fn alpha<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let r = &self.rendered;
        image(py, &r.alpha, &[r.height, r.width])
    }
    #[getter]
    fn features<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let r = &self.rendered;
        image(py, &r.features, &[r.height, r.width, r.num_features])
    }
    #[getter]
    fn radii<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        PyArray1::from_slice(py, &self.rendered.radii)
    }
    #[getter]
    fn num_pairs(&self) -> usize {
        self.rendered.num_pairs()
    }

    /// Gradients of a scalar loss given d(loss)/d(image) for the images that enter it.
    #[pyo3(signature = (d_color=None, d_depth=None, d_alpha=None, d_features=None))]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        d_color: Option<PyReadonlyArrayDyn<'py, f32>>,
        d_depth: Option<PyReadonlyArrayDyn<'py, f32>>,
        d_alpha: Option<PyReadonlyArrayDyn<'py, f32>>,
        d_features: Option<PyReadonlyArrayDyn<'py, f32>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let grads = ImageGrads {
            color: d_color
                .as_ref()
                .map(|a| contiguous("d_color", a))
                .transpose()?,
            depth: d_depth
                .as_ref()
                .map(|a| contiguous("d_depth", a))
                .transpose()?,
            alpha: d_alpha
                .as_ref()
                .map(|a| contiguous("d_alpha", a))
                .transpose()?,
            features: d_features
                .as_ref()
                .map(|a| contiguous("d_features", a))
                .transpose()?,
        };
        let g = engine_call(py, || {
            backward(&self.gaussians.view(), &self.camera, &self.rendered, &grads)
        })?;
        let n = self.gaussians.opacity_logits.len();
        let out = PyDict::new(py);
        let put = |name: &str, v: &[f32], shape: Vec<usize>| -> PyResult<()> {
            out.set_item(name, PyArray1::from_slice(py, v).reshape(shape)?)
        };
        put("means", &g.means, vec![n, 3])?;
        put("log_scales", &g.log_scales, vec![n, 3])?;
        put("quats", &g.quats, vec![n, 4])?;
        put("opacity_logits", &g.opacity_logits, vec![n])?;
        put("sh", &g.sh, vec![n, self.gaussians.sh_coeffs, 3])?;
        put(
            "features",
            &g.features,
            vec![n, self.gaussians.num_features],
        )?;
        put("means2d", &g.means2d, vec![n, 2])?;
        put("pose", &g.pose, vec![6])?;
        Ok(out)
    }
}

/// Renders Gaussians; see `legslam.render` for the documented, checked entry point.
#[pyfunction]
#[pyo3(signature = (means, log_scales, quats, opacity_logits, sh, features, intrinsics, world_to_camera, width, height, sh_degree, color, depth, alpha))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    means: PyReadonlyArray2<'py, f32>,
    log_scales: PyReadonlyArray2<'py, f32>,
    quats: PyReadonlyArray2<'py, f32>,
    opacity_logits: PyReadonlyArray1<'py, f32>,
    sh: PyReadonlyArrayDyn<'py, f32>,
    features: PyReadonlyArray2<'py, f32>,
    intrinsics: [f64; 4],
    world_to_camera: [[f64; 4]; 4],
    width: usize,
    height: usize,
    sh_degree: usize,
    color: bool,
    depth: bool,
    alpha: bool,
) -> PyResult<PyRender> {
    // The count from the array's shape, so that an empty map keeps its degree.
    let &[_, sh_coeffs, 3] = sh.shape() else {
        return Err(PyValueError::new_err(format!(
            "sh must have shape (N, C, 3), got {:?}",
            sh.shape()
        )));
    };
    let gaussians = GaussianMap {
        means: contiguous("means", &means)?.to_vec(),
        log_scales: contiguous("log_scales", &log_scales)?.to_vec(),
        quats: contiguous("quats", &quats)?.to_vec(),
        opacity_logits: contiguous("opacity_logits", &opacity_logits)?.to_vec(),
        sh: contiguous("sh", &sh)?.to_vec(),
        sh_coeffs,
        features: contiguous("features", &features)?.to_vec(),
        num_features: features.shape()[1],
        ..Default::default()
    };
    let intr = Intrinsics::from_array(intrinsics, width, height);
    let camera = Camera::new(intr, &world_to_camera).map_err(PyValueError::new_err)?;
    let opts = RenderOptions {
        sh_degree,
        color,
        depth,
        alpha,
        features: gaussians.num_features > 0,
        ..Default::default()
    };
    let rendered = engine_call(py, || {
        let g = gaussians.view();
        g.validate()?;
        engine_render(&g, &camera, &opts)
    })?;
    Ok(PyRender {
        gaussians,
        camera,
        rendered,
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyRender>()?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    Ok(())
}
