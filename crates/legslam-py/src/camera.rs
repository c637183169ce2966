//! Bindings of camera geometry: intrinsics of a scaled image, depth registered to another
//! camera of a rig.

use legslam_core::camera::register_depth as engine_register_depth;
use numpy::{IntoPyArray, PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::convert::{array, contiguous, engine_call, intrinsics, pose, size};

/// The depth (float32 HxW, metres) seen by the camera `k_to` of `width` x `height` placed at
/// `to_from` (4x4, the depth camera's points in its frame); see `register_depth` in the engine.
#[pyfunction]
#[pyo3(signature = (depth, k_from, k_to, to_from, width, height))]
fn register_depth<'py>(
    py: Python<'py>,
    depth: &Bound<'py, PyAny>,
    k_from: &Bound<'py, PyAny>,
    k_to: &Bound<'py, PyAny>,
    to_from: &Bound<'py, PyAny>,
    width: i64,
    height: i64,
) -> PyResult<Bound<'py, PyAny>> {
    let (width, height) = size(width, height)?;
    let depth = array::<f32, numpy::Ix2>(depth, "depth", &[None, None])?;
    let (h, w) = (depth.shape()[0], depth.shape()[1]);
    let values = contiguous("depth", &depth)?;
    let from = intrinsics(k_from, w, h)?;
    let to = intrinsics(k_to, width, height)?;
    let to_from = pose(to_from, "to_from")?;
    let out = engine_call(py, || engine_register_depth(values, from, to, &to_from))?;
    Ok(PyArray1::from_vec(py, out)
        .reshape([height, width])?
        .into_any())
}

/// The intrinsics and size (K, width, height) of a `width` x `height` image scaled by `s`, pixel
/// centres aligned as `cv2.resize` samples them (`Intrinsics::scaled`).
#[pyfunction]
fn scaled_intrinsics<'py>(
    py: Python<'py>,
    k: &Bound<'py, PyAny>,
    width: i64,
    height: i64,
    s: f64,
) -> PyResult<(Bound<'py, PyAny>, usize, usize)> {
    let (width, height) = size(width, height)?;
    let intr = intrinsics(k, width, height)?;
    let out = engine_call(py, || {
        intr.validate()?;
        if !(s.is_finite() && s > 0.0) {
            return Err(format!("the scale must be positive, got {s}"));
        }
        Ok(intr.scaled(s))
    })?;
    let k = numpy::ndarray::arr2(&[
        [out.fx, 0.0, out.cx],
        [0.0, out.fy, out.cy],
        [0.0, 0.0, 1.0],
    ]);
    Ok((k.into_pyarray(py).into_any(), out.width, out.height))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(register_depth, m)?)?;
    m.add_function(wrap_pyfunction!(scaled_intrinsics, m)?)?;
    Ok(())
}
