//! Bindings only: extract the Python dataclasses into core structs, release the GIL while
//! computing, hand the results back as numpy arrays. No physics and no effect mapping here
//! (that is `sim::build_system`).
//!
//! - `errors`: the exception classes and the conversion of core errors;
//! - `extract`: the mirror of the configuration dataclasses (in, and the seed values out);
//! - `arrays`: results into numpy arrays and dicts;
//! - `api`: the entry points of single runs and batches, and their `StopFlag`;
//! - `campaign`: `campaign_run` and its `CampaignControl`.
#![allow(missing_docs)]

mod api;
mod arrays;
mod campaign;
mod errors;
mod extract;

use errors::{config_type_error_class, ConfigError, SimulationError};
use pyo3::prelude::*;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("ConfigError", py.get_type::<ConfigError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add("ConfigTypeError", config_type_error_class(py)?)?;
    api::register(m)?;
    campaign::register(m)?;
    Ok(())
}
