//! Orchestration: the control-tick loop and what it records. No physics, no pyo3.

mod campaign;
mod extended;
mod trial;

pub use campaign::{
    run_campaign, trial_seed, Campaign, CampaignOutput, TrialFailure, TrialStatus, MAX_THREADS,
    MAX_TRIALS,
};
pub use extended::{
    run_drive_open_loop, run_extended, run_extended_at, stream_seed, ControllerKind,
    DriveOpenLoopTrace, ExtendedConfig, Interferometer, KnownInputs, Measured, Sensors,
    SpreadDistribution, StochasticFriction,
};
pub use trial::{run_closed_loop, run_open_loop, ClosedLoopConfig, OpenLoopTrace, Trace};
