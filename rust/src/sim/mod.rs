//! Orchestration: the control-tick loop and what it records. No physics, no pyo3.

mod trial;

pub use trial::{run_closed_loop, run_open_loop, ClosedLoopConfig, OpenLoopTrace, Trace};
