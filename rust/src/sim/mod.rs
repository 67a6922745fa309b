//! Orchestration: the control-tick loop and what it records. No physics, no pyo3.
//!
//! - `config.rs`: a whole system as the Python package describes it, and how its effects map
//!   onto the plant ([`build_system`]).
//! - `plant.rs`: the plant a run drives (rigid or component), behind one dispatch.
//! - `trace.rs`: what a run records, and the checks of the series it is given.
//! - `closed_loop.rs`: the closed loop with every effect ([`run_extended`]) and its
//!   configuration; `open_loop.rs`: either plant driven by a held voltage series.
//! - `campaign.rs`: Monte Carlo campaigns over the closed loop, on `threads` threads.

mod campaign;
mod closed_loop;
mod config;
mod open_loop;
mod plant;
mod trace;

pub use crate::integrate::POLL_EVERY_SAMPLES;
pub use campaign::{
    run_campaign, trial_seed, Campaign, CampaignOutput, TrialFailure, TrialStatus, MAX_THREADS,
    MAX_TRIALS,
};
pub use closed_loop::{
    run_closed_loop, run_extended, run_extended_at, run_extended_polled, stream_seed,
    ClosedLoopConfig, ControllerKind, ExtendedConfig, Interferometer, KnownInputs, Sensors,
    SpreadDistribution, StochasticFriction,
};
pub use config::{
    build_system, modulation, side, BacklashSpec, ComplianceSpec, ControllerSpec, EffectsSpec,
    EncoderErrorsSpec, EncoderSpec, ForceDriveSpec, FrictionModifiersSpec, FxpSpec, PidSpec,
    PlantSpec, PositionFrictionSpec, StochasticSpec, SystemSpec,
};
pub use open_loop::{
    run_drive_open_loop, run_drive_open_loop_polled, run_open_loop, run_open_loop_polled,
};
pub use trace::{DriveOpenLoopTrace, Measured, OpenLoopTrace, Trace};
