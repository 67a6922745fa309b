//! Orchestration: the control-tick loop and what it records. No physics, no pyo3.

mod campaign;
mod config;
mod extended;
mod trial;

pub use campaign::{
    run_campaign, trial_seed, Campaign, CampaignOutput, TrialFailure, TrialStatus, MAX_THREADS,
    MAX_TRIALS,
};
pub use config::{
    build_system, modulation, side, BacklashSpec, ComplianceSpec, ControllerSpec, EffectsSpec,
    EncoderErrorsSpec, EncoderSpec, ForceDriveSpec, FrictionModifiersSpec, FxpSpec, PidSpec,
    PlantSpec, PositionFrictionSpec, StochasticSpec, SystemSpec,
};
pub use extended::{
    run_drive_open_loop, run_drive_open_loop_polled, run_extended, run_extended_at,
    run_extended_polled, stream_seed, ControllerKind, DriveOpenLoopTrace, ExtendedConfig,
    Interferometer, KnownInputs, Measured, Sensors, SpreadDistribution, StochasticFriction,
    POLL_EVERY_SAMPLES,
};
pub use trial::{
    run_closed_loop, run_open_loop, run_open_loop_polled, ClosedLoopConfig, OpenLoopTrace, Trace,
};
