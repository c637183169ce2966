//! Engine objects that run on thread pools of their own: with mapping in a Python thread beside
//! the tracker, neither's parallel work queues behind the other's in rayon's global pool.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::convert::engine_call;

/// How much lower a background pool's threads run (the nice value they add, Linux).
const BACKGROUND_NICE: i32 = 10;

/// `None` (rayon's global pool) or a pool of `threads` threads named `{name}-{i}`; with
/// `background`, its threads yield the CPU to the process's other threads (Linux: nice raised
/// by [`BACKGROUND_NICE`]; elsewhere no change), so that a tracker waiting for the cores gets
/// them first.
pub fn build(
    threads: Option<usize>,
    name: &'static str,
    background: bool,
) -> PyResult<Option<rayon::ThreadPool>> {
    match threads {
        None => Ok(None),
        Some(0) => Err(PyValueError::new_err("threads must be at least 1")),
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .thread_name(move |i| format!("{name}-{i}"))
            .start_handler(move |_| {
                if background {
                    lower_this_threads_priority(BACKGROUND_NICE);
                }
            })
            .build()
            .map(Some)
            .map_err(|e| PyValueError::new_err(format!("{name} thread pool: {e}"))),
    }
}

/// Raises the calling thread's nice value by `by` (on Linux the nice value is per thread).
/// Failing is harmless (the thread keeps its priority), so the result is not checked.
fn lower_this_threads_priority(by: i32) {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid takes no arguments; getpriority / setpriority only read their arguments.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        let now = libc::getpriority(libc::PRIO_PROCESS, tid);
        libc::setpriority(libc::PRIO_PROCESS, tid, now + by);
    }
    #[cfg(not(target_os = "linux"))]
    let _ = by;
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
