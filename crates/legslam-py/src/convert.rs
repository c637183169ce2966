//! The bindings' contract in one place: how arguments cross from Python and results go back,
//! and the guard every engine call runs behind.
//!
//! - Bindings check shapes and dtypes, and name the argument that is wrong; the engine checks
//!   values (finite, positive, rigid, in range) and says what is wrong with them.
//! - Images are numpy arrays, row-major, channel last; intrinsics a 3x3 pinhole `K`; poses a
//!   4x4 float64 camera-to-world matrix (the engine's [`Pose`]); options a dict of a
//!   configuration's named options (see `legslam_core::options`).
//! - Every entry that runs engine code does so through [`engine_call`]: without the GIL,
//!   engine errors as `ValueError`, a panic (a bug) as `RuntimeError` that never unwinds
//!   into Python.

use std::sync::atomic::{AtomicBool, Ordering};

use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::options::{Options, Value};
use numpy::ndarray::Dimension;
use numpy::{
    Element, IntoPyArray, PyArrayDescrMethods, PyReadonlyArray, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyTuple};

/// Set by the tests (`_core._inject_panic`) to check that every entry is guarded.
static INJECT_PANIC: AtomicBool = AtomicBool::new(false);

/// Runs engine code without the GIL, turning errors into ValueError and a panic (a bug) into
/// RuntimeError instead of letting it cross into Python.
pub fn engine_call<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, String> + Send,
) -> PyResult<T> {
    py.detach(|| {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            if INJECT_PANIC.load(Ordering::Relaxed) {
                panic!("a panic injected by legslam's tests");
            }
            f()
        }))
    })
    .map_err(|_| {
        PyRuntimeError::new_err("legslam engine failed internally (a bug): please report it")
    })?
    .map_err(PyValueError::new_err)
}

/// While `on`, every engine call panics inside its guard: the tests' way to check that no
/// entry lets a panic through.
#[pyfunction]
fn _inject_panic(on: bool) {
    INJECT_PANIC.store(on, Ordering::Relaxed);
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_inject_panic, m)?)
}

/// A ValueError about argument `name`.
pub fn bad(name: &str, msg: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{name} {msg}"))
}

/// The data of a C-contiguous array.
pub fn contiguous<'a, T: Element, D: Dimension>(
    name: &str,
    a: &'a PyReadonlyArray<'_, T, D>,
) -> PyResult<&'a [T]> {
    a.as_slice()
        .map_err(|_| bad(name, "must be a C-contiguous array"))
}

/// Argument `name` as a numpy array of element type `T` whose shape matches `shape` (`None`:
/// any extent), or a ValueError naming the argument, the shape or dtype wanted and what it got.
pub fn array<'py, T: Element, D: Dimension>(
    arg: &Bound<'py, PyAny>,
    name: &str,
    shape: &[Option<usize>],
) -> PyResult<PyReadonlyArray<'py, T, D>> {
    let want = shape
        .iter()
        .map(|s| s.map_or("N".to_string(), |n| n.to_string()))
        .collect::<Vec<_>>()
        .join("x");
    let untyped = arg
        .cast::<PyUntypedArray>()
        .map_err(|_| bad(name, format!("must be a {want} numpy array")))?;
    let got = untyped.shape();
    let fits = got.len() == shape.len()
        && got
            .iter()
            .zip(shape)
            .all(|(g, s)| s.is_none_or(|s| *g == s));
    if !fits {
        return Err(bad(name, format!("must have shape {want}, got {got:?}")));
    }
    let wanted_dtype = numpy::dtype::<T>(arg.py());
    if !untyped.dtype().is_equiv_to(&wanted_dtype) {
        return Err(bad(
            name,
            format!(
                "must be a {wanted_dtype} array, got dtype {}",
                untyped.dtype()
            ),
        ));
    }
    arg.extract()
}

/// Intrinsics from a 3x3 pinhole matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` for a
/// `width` x `height` image. Its values are the engine's to check.
pub fn intrinsics(k: &Bound<'_, PyAny>, width: usize, height: usize) -> PyResult<Intrinsics> {
    let k = array::<f64, numpy::Ix2>(k, "K", &[Some(3), Some(3)])?;
    let v = k.as_array();
    let pinhole = v[[1, 0]] == 0.0 && v[[2, 0]] == 0.0 && v[[2, 1]] == 0.0 && v[[2, 2]] == 1.0;
    if !pinhole {
        return Err(bad(
            "K",
            format!("must be a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {v}"),
        ));
    }
    if v[[0, 1]] != 0.0 {
        return Err(bad("K", "with skew is not supported"));
    }
    Ok(Intrinsics::from_array(
        [v[[0, 0]], v[[1, 1]], v[[0, 2]], v[[1, 2]]],
        width,
        height,
    ))
}

/// An image size from Python integers: both must be positive.
pub fn size(width: i64, height: i64) -> PyResult<(usize, usize)> {
    if width <= 0 || height <= 0 {
        return Err(PyValueError::new_err(format!(
            "width and height must be positive, got {width}x{height}"
        )));
    }
    Ok((width as usize, height as usize))
}

/// A 4x4 float64 pose. Whether it is rigid is the engine's to check.
pub fn pose(p: &Bound<'_, PyAny>, name: &str) -> PyResult<Pose> {
    let a = array::<f64, numpy::Ix2>(p, name, &[Some(4), Some(4)])?;
    let v = a.as_array();
    Ok(Pose::from_fn(|i, j| v[[i, j]]))
}

/// A pose as a 4x4 float64 numpy array.
pub fn pose_array<'py>(py: Python<'py>, m: &Pose) -> Bound<'py, PyAny> {
    numpy::ndarray::Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)])
        .into_pyarray(py)
        .into_any()
}

/// A configuration from its defaults and a dict of named options, checked by `validate`; each
/// value must be of its option's kind (a flag a bool, a count an int, a number an int or
/// float, a list of ints).
pub fn options_from<C: Options + Send>(
    py: Python<'_>,
    d: Option<&Bound<'_, PyDict>>,
    section: &str,
    validate: fn(&C) -> Result<(), String>,
) -> PyResult<C> {
    let defaults = engine_call(py, || Ok(C::default().entries()))?;
    let mut values = Vec::new();
    for (k, v) in d.into_iter().flat_map(|d| d.iter()) {
        let name: String = k
            .extract()
            .map_err(|_| bad(section, format!("option names must be strings, got {k}")))?;
        let value = match defaults.iter().find(|(n, _)| *n == name) {
            Some((_, kind)) => value_of_kind(&v, kind).ok_or_else(|| {
                let got = v.repr().map_or("?".into(), |r| r.to_string());
                bad(
                    &format!("{section} option {name}"),
                    format!("must be {}, got {got}", kind.kind()),
                )
            })?,
            // An unknown name: the engine's message lists the known ones.
            None => Value::Bool(false),
        };
        values.push((name, value));
    }
    engine_call(py, || {
        let mut c = C::default();
        for (name, value) in values {
            c.set(&name, value)?;
        }
        validate(&c)?;
        Ok(c)
    })
}

/// `v` converted to the kind of `like`, or None when it is not of that kind.
fn value_of_kind(v: &Bound<'_, PyAny>, like: &Value) -> Option<Value> {
    let is_int = v.is_instance_of::<PyInt>() && !v.is_instance_of::<PyBool>();
    match like {
        Value::Bool(_) => v.cast::<PyBool>().ok().map(|b| Value::Bool(b.is_true())),
        Value::Int(_) if is_int => v.extract::<u64>().ok().map(Value::Int),
        Value::Real(_) if is_int || v.is_instance_of::<PyFloat>() => {
            v.extract::<f64>().ok().map(Value::Real)
        }
        Value::Ints(_) if v.is_instance_of::<PyList>() || v.is_instance_of::<PyTuple>() => {
            v.extract::<Vec<usize>>().ok().map(Value::Ints)
        }
        _ => None,
    }
}

/// Every option of a configuration as a dict.
pub fn options_dict<'py, C: Options + Sync>(
    py: Python<'py>,
    c: &C,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (name, v) in engine_call(py, || Ok(c.entries()))? {
        match v {
            Value::Bool(b) => d.set_item(name, b)?,
            Value::Int(i) => d.set_item(name, i)?,
            Value::Real(x) => d.set_item(name, x)?,
            Value::Ints(v) => d.set_item(name, PyList::new(py, v)?)?,
        }
    }
    Ok(d)
}
