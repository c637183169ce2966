//! Engine objects that run on thread pools of their own: with mapping in a Python thread beside
//! the tracker, neither's parallel work queues behind the other's in rayon's global pool.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::convert::engine_call;

/// `None` (rayon's global pool) or a pool of `threads` threads named `{name}-{i}`.
pub fn build(threads: Option<usize>, name: &'static str) -> PyResult<Option<rayon::ThreadPool>> {
    match threads {
        None => Ok(None),
        Some(0) => Err(PyValueError::new_err("threads must be at least 1")),
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .thread_name(move |i| format!("{name}-{i}"))
            .build()
            .map(Some)
            .map_err(|e| PyValueError::new_err(format!("{name} thread pool: {e}"))),
    }
}

/// `engine_call` inside `pool`, if there is one.
pub fn call<T: Send>(
    pool: &Option<rayon::ThreadPool>,
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, String> + Send,
) -> PyResult<T> {
    engine_call(py, || match pool {
        Some(p) => p.install(f),
        None => f(),
    })
}
