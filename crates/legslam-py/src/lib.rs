//! PyO3 bindings only: numpy in, numpy out, engine errors -> Python exceptions. The contract
//! every binding keeps (argument conversions, the guard around engine calls) is in
//! [`convert`]; each other module registers the entries of one engine concept.

use pyo3::prelude::*;

mod camera;
mod convert;
mod graph;
mod map;
mod pool;
mod raster;
mod track;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    convert::register(m)?;
    camera::register(m)?;
    graph::register(m)?;
    map::register(m)?;
    raster::register(m)?;
    track::register(m)?;
    Ok(())
}
