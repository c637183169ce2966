//! Bindings of the rasterizer: `render` returns a `Render` holding the images and what its
//! `backward` needs (legslam.render documents the entry).

use legslam_core::camera::se3;
use legslam_core::map::GaussianMap;
use legslam_core::raster::{
    backward, render as engine_render, Camera, ImageGrads, RenderOptions, Rendered,
};
use numpy::{IxDyn, PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{array, contiguous, engine_call, intrinsics, pose, size};

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

    /// Gradients of a scalar loss given d(loss)/d(image) for the images that enter it, each
    /// shaped like its image.
    #[pyo3(signature = (d_color=None, d_depth=None, d_alpha=None, d_features=None))]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        d_color: Option<&Bound<'py, PyAny>>,
        d_depth: Option<&Bound<'py, PyAny>>,
        d_alpha: Option<&Bound<'py, PyAny>>,
        d_features: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let r = &self.rendered;
        let (h, w) = (Some(r.height), Some(r.width));
        let grad = |a: Option<&Bound<'py, PyAny>>, name: &str, shape: &[Option<usize>]| {
            a.map(|a| array::<f32, IxDyn>(a, name, shape)).transpose()
        };
        let d_color = grad(d_color, "d_color", &[h, w, Some(3)])?;
        let d_depth = grad(d_depth, "d_depth", &[h, w])?;
        let d_alpha = grad(d_alpha, "d_alpha", &[h, w])?;
        // Without rendered features any width: the engine then says they were not rendered.
        let k = Some(r.num_features).filter(|k| *k > 0);
        let d_features = grad(d_features, "d_features", &[h, w, k])?;
        fn slice<'a>(
            a: &'a Option<PyReadonlyArrayDyn<'_, f32>>,
            name: &str,
        ) -> PyResult<Option<&'a [f32]>> {
            a.as_ref().map(|a| contiguous(name, a)).transpose()
        }
        let grads = ImageGrads {
            color: slice(&d_color, "d_color")?,
            depth: slice(&d_depth, "d_depth")?,
            alpha: slice(&d_alpha, "d_alpha")?,
            features: slice(&d_features, "d_features")?,
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

/// Renders Gaussians; see `legslam.render` for the documented entry point.
#[pyfunction]
#[pyo3(signature = (means, log_scales, quats, opacity_logits, sh, features, k, pose_c2w, width, height, sh_degree, color, depth, alpha))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    means: &Bound<'py, PyAny>,
    log_scales: &Bound<'py, PyAny>,
    quats: &Bound<'py, PyAny>,
    opacity_logits: &Bound<'py, PyAny>,
    sh: &Bound<'py, PyAny>,
    features: &Bound<'py, PyAny>,
    k: &Bound<'py, PyAny>,
    pose_c2w: &Bound<'py, PyAny>,
    width: i64,
    height: i64,
    sh_degree: usize,
    color: bool,
    depth: bool,
    alpha: bool,
) -> PyResult<PyRender> {
    let means = array::<f32, numpy::Ix2>(means, "means", &[None, Some(3)])?;
    let n = Some(means.shape()[0]);
    let log_scales = array::<f32, numpy::Ix2>(log_scales, "log_scales", &[n, Some(3)])?;
    let quats = array::<f32, numpy::Ix2>(quats, "quats", &[n, Some(4)])?;
    let opacity = array::<f32, numpy::Ix1>(opacity_logits, "opacity_logits", &[n])?;
    // The coefficient count from the array's shape, so that an empty map keeps its degree.
    let sh = array::<f32, numpy::Ix3>(sh, "sh", &[n, None, Some(3)])?;
    let features = array::<f32, numpy::Ix2>(features, "features", &[n, None])?;
    let (width, height) = size(width, height)?;
    let intr = intrinsics(k, width, height)?;
    let c2w = pose(pose_c2w, "pose")?;
    let gaussians = GaussianMap {
        means: contiguous("means", &means)?.to_vec(),
        log_scales: contiguous("log_scales", &log_scales)?.to_vec(),
        quats: contiguous("quats", &quats)?.to_vec(),
        opacity_logits: contiguous("opacity_logits", &opacity)?.to_vec(),
        sh: contiguous("sh", &sh)?.to_vec(),
        sh_coeffs: sh.shape()[1],
        features: contiguous("features", &features)?.to_vec(),
        num_features: features.shape()[1],
        ..Default::default()
    };
    let opts = RenderOptions {
        sh_degree,
        color,
        depth,
        alpha,
        features: gaussians.num_features > 0,
        ..Default::default()
    };
    let (camera, rendered) = engine_call(py, || {
        se3::validate_pose(&c2w, "pose")?;
        let camera = Camera::new(intr, &se3::inverse(&c2w))?;
        let g = gaussians.view();
        g.validate()?;
        Ok((camera, engine_render(&g, &camera, &opts)?))
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
