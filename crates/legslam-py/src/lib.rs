//! PyO3 bindings only: numpy in, numpy out, engine errors -> Python exceptions.
//! Each submodule registers the functions of one engine concept.

use pyo3::prelude::*;

mod camera;
mod map;
mod pool;
mod raster;
mod track;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    camera::register(m)?;
    map::register(m)?;
    raster::register(m)?;
    track::register(m)?;
    Ok(())
}
