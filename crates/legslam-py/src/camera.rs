//! Bindings of camera geometry: depth registered to another camera of a rig. Dtypes and shapes
//! are checked by the Python wrapper (legslam.datasets.registration).

use legslam_core::camera::{register_depth as engine_register_depth, Intrinsics};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::raster::{contiguous, engine_call};

/// The depth camera `k_to` of `width` x `height` sees; see `register_depth` in the engine.
#[pyfunction]
#[pyo3(signature = (depth, k_from, k_to, to_from, width, height))]
fn register_depth<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f32>,
    k_from: [f64; 4],
    k_to: [f64; 4],
    to_from: [[f64; 4]; 4],
    width: usize,
    height: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let (h, w) = (depth.shape()[0], depth.shape()[1]);
    let values = contiguous("depth", &depth)?;
    let from = Intrinsics::from_array(k_from, w, h);
    let to = Intrinsics::from_array(k_to, width, height);
    let out = engine_call(py, || engine_register_depth(values, from, to, &to_from))?;
    Ok(PyArray1::from_vec(py, out)
        .reshape([height, width])?
        .into_any())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(register_depth, m)?)?;
    Ok(())
}
