//! nanostage: an ultra-high-precision positioning axis with friction, in closed loop with a
//! cycle-accurate emulation of its FPGA PID.
//!
//! The core (`model`, `integrate`, `control`, `sim`) is plain Rust; only `python` (behind the
//! default `python` feature) knows about pyo3. `cargo test --no-default-features` builds and
//! tests the core without Python.
#![deny(missing_docs)]

pub mod control;
pub mod error;
pub mod integrate;
pub mod model;
pub mod sim;

#[cfg(feature = "python")]
mod python;

// The unit tests read the seed preset from its model file with the test crates' helper,
// which names this crate `nanostage`.
#[cfg(test)]
extern crate self as nanostage;
#[cfg(test)]
#[path = "../tests/support/presets.rs"]
mod presets;

pub use error::{ConfigError, SimError};
