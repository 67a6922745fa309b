//! Monte Carlo campaigns: many trials of one whole test cycle on the extended closed loop, in
//! parallel, keeping only the positions at the measurement instants.
//!
//! Determinism rule: trial `i` runs with seed `stream_seed(base_seed, i)` and nothing else
//! about it depends on the other trials, the thread count or how the trial range is split,
//! so a campaign run as `0..n` on one thread, on eight threads, or as `0..k` and `k..n` on two
//! machines gives bit-identical positions and statuses.
//!
//! A numerical failure in one trial is that trial's status (with the time and the state of the
//! failure); the other trials complete. A stop flag (Ctrl-C) is polled before each trial and,
//! inside a trial, every [`POLL_EVERY_SAMPLES`](super::POLL_EVERY_SAMPLES) control samples by [`run_extended`]; trials
//! cut short or never started are reported as such. Every trial's work is bounded (the
//! integrator's `max_steps` and `max_events` per control interval), so every trial gets a
//! status. Invalid input is a [`ConfigError`] before any trial runs.
use super::closed_loop::{run_extended_at, stream_seed, ExtendedConfig, KnownInputs};
use crate::error::{ConfigError, SimError};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Most trials one call accepts (`trial_stop − trial_start`).
pub const MAX_TRIALS: u64 = 1 << 32;
/// Most threads of the local pool.
pub const MAX_THREADS: usize = 1024;

/// Outcome of one trial (mirrored by `nanostage.campaign.TrialStatus`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(i8)]
pub enum TrialStatus {
    /// The trial ran to the end of the cycle.
    Ok = 0,
    /// The error-controlled step size fell below the minimum.
    StepSizeTooSmall = 1,
    /// The iteration matrix of the implicit method was singular.
    SingularMatrix = 2,
    /// The state became NaN or infinite.
    NonFinite = 3,
    /// More integrator steps than allowed in one control interval.
    TooManySteps = 4,
    /// Stopped from outside while running.
    Interrupted = 5,
    /// Not started: the stop flag was already set.
    NotStarted = 6,
    /// A configuration error raised inside the trial (cannot happen after the up-front
    /// validation; kept so that no error is ever lost).
    Config = 7,
    /// More stick/slip events than allowed in one control interval.
    TooManyEvents = 8,
}

impl TrialStatus {
    /// The status of a failed trial.
    pub fn of_error(e: &SimError) -> Self {
        match e {
            SimError::StepSizeTooSmall { .. } => Self::StepSizeTooSmall,
            SimError::SingularMatrix { .. } => Self::SingularMatrix,
            SimError::NonFinite { .. } => Self::NonFinite,
            SimError::TooManySteps { .. } => Self::TooManySteps,
            SimError::TooManyEvents { .. } => Self::TooManyEvents,
            SimError::Interrupted { .. } => Self::Interrupted,
            SimError::Config(_) => Self::Config,
        }
    }
}

/// A failed (or stopped) trial: when and where.
#[derive(Debug, Clone, PartialEq)]
pub struct TrialFailure {
    /// Trial index (absolute, in `trial_start..trial_stop`).
    pub trial: u64,
    /// Simulated time of the failure, s (NaN when the trial never started).
    pub t_s: f64,
    /// State vector at the failure (empty when not available).
    pub state: Vec<f64>,
    /// The error in words.
    pub message: String,
}

/// What a campaign keeps: per trial, the positions at the measurement instants and a status.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CampaignOutput {
    /// First trial index of this range.
    pub trial_start: u64,
    /// Number of measurement instants per trial.
    pub n_measure: usize,
    /// True table position at each measurement instant, m; row-major
    /// `[n_trials][n_measure]`; NaN for a trial that did not complete.
    pub position_m: Vec<f64>,
    /// Encoder reading (counts · count size) at each measurement instant, m; same layout.
    pub encoder_m: Vec<f64>,
    /// Status of each trial.
    pub status: Vec<TrialStatus>,
    /// The trials that did not complete, in trial order.
    pub failures: Vec<TrialFailure>,
}

impl CampaignOutput {
    /// Number of trials.
    pub fn n_trials(&self) -> usize {
        self.status.len()
    }
}

/// One campaign: the loop (its `seed` is ignored; each trial gets its own), the reference of
/// the whole cycle and the sample indices at which the position is measured.
#[derive(Debug, Clone, Copy)]
pub struct Campaign<'a> {
    /// The closed loop.
    pub config: &'a ExtendedConfig,
    /// Reference position per control sample, m.
    pub reference_m: &'a [f64],
    /// Measurement sample indices, strictly increasing, each `< reference_m.len()`.
    pub measure_index: &'a [usize],
}

impl Campaign<'_> {
    /// Check everything that does not depend on a trial's seed.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.config.validate()?;
        let n = self.reference_m.len();
        if n == 0 {
            return Err(ConfigError::new(
                "reference_m (length)",
                0,
                "at least 1 sample",
            ));
        }
        if let Some((k, x)) = self
            .reference_m
            .iter()
            .enumerate()
            .find(|(_, x)| !x.is_finite())
        {
            return Err(ConfigError::new(
                format!("reference_m[{k}]"),
                x,
                "a finite number",
            ));
        }
        if self.measure_index.is_empty() {
            return Err(ConfigError::new(
                "measure_index (length)",
                0,
                "at least one measurement",
            ));
        }
        for (k, &i) in self.measure_index.iter().enumerate() {
            if i >= n {
                return Err(ConfigError::new(
                    format!("measure_index[{k}]"),
                    i,
                    format!("an index in [0, {}]", n - 1),
                ));
            }
            if k > 0 && i <= self.measure_index[k - 1] {
                return Err(ConfigError::new(
                    format!("measure_index[{k}]"),
                    i,
                    format!(
                        "greater than measure_index[{}] = {} (strictly increasing)",
                        k - 1,
                        self.measure_index[k - 1]
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// The seed of trial `trial` of a campaign with seed `base_seed`.
pub fn trial_seed(base_seed: u64, trial: u64) -> u64 {
    stream_seed(base_seed, trial)
}

struct TrialResult {
    position_m: Vec<f64>,
    encoder_m: Vec<f64>,
    status: TrialStatus,
    failure: Option<TrialFailure>,
}

fn failure(trial: u64, e: &SimError) -> TrialFailure {
    let (t_s, state) = e.time_and_state();
    TrialFailure {
        trial,
        t_s,
        state,
        message: e.to_string(),
    }
}

/// Run one trial of `campaign` (already validated) with its own seed.
fn run_trial(
    campaign: &Campaign<'_>,
    base_seed: u64,
    trial: u64,
    stop: Option<&AtomicBool>,
) -> TrialResult {
    let m = campaign.measure_index.len();
    let nan = || vec![f64::NAN; m];
    if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
        return TrialResult {
            position_m: nan(),
            encoder_m: nan(),
            status: TrialStatus::NotStarted,
            failure: Some(TrialFailure {
                trial,
                t_s: f64::NAN,
                state: Vec::new(),
                message: "not started: the campaign was stopped".into(),
            }),
        };
    }
    let mut cfg = *campaign.config;
    cfg.seed = trial_seed(base_seed, trial);
    match run_extended_at(
        &cfg,
        campaign.reference_m,
        KnownInputs::default(),
        stop,
        campaign.measure_index,
    ) {
        Ok(meas) => {
            let count_m = cfg.sensors.encoder.count_m;
            let pad = |mut v: Vec<f64>| {
                v.resize(m, f64::NAN);
                v
            };
            let encoder_m = meas
                .encoder_counts
                .iter()
                .map(|&c| c as f64 * count_m)
                .collect();
            TrialResult {
                position_m: pad(meas.position_m),
                encoder_m: pad(encoder_m),
                status: TrialStatus::Ok,
                failure: None,
            }
        }
        Err(e) => TrialResult {
            position_m: nan(),
            encoder_m: nan(),
            status: TrialStatus::of_error(&e),
            failure: Some(failure(trial, &e)),
        },
    }
}

/// Run trials `trial_start..trial_stop` of `campaign` on a local pool of `threads` threads.
///
/// `progress` (if given) is incremented once per finished trial (completed, failed or not
/// started); `stop` (if given) stops the campaign within [`POLL_EVERY_SAMPLES`](super::POLL_EVERY_SAMPLES) control
/// samples of every running trial. The result is the same, bit for bit, for any `threads` and any split of
/// the trial range.
///
/// # Errors
/// A [`ConfigError`] before any trial runs: invalid configuration, reference or measurement
/// indices, an empty or too long trial range, `threads` outside `[1, MAX_THREADS]`, or a
/// thread pool that cannot be started.
pub fn run_campaign(
    campaign: &Campaign<'_>,
    base_seed: u64,
    trial_start: u64,
    trial_stop: u64,
    threads: usize,
    stop: Option<&AtomicBool>,
    progress: Option<&AtomicUsize>,
) -> Result<CampaignOutput, ConfigError> {
    campaign.validate()?;
    if trial_stop <= trial_start || trial_stop - trial_start > MAX_TRIALS {
        return Err(ConfigError::new(
            "trial_stop",
            trial_stop,
            format!("in (trial_start = {trial_start}, trial_start + {MAX_TRIALS}]"),
        ));
    }
    if threads == 0 || threads > MAX_THREADS {
        return Err(ConfigError::new(
            "threads",
            threads,
            format!("an integer in [1, {MAX_THREADS}]"),
        ));
    }
    let n_trials = usize::try_from(trial_stop - trial_start).map_err(|_| {
        ConfigError::new(
            "trial_stop",
            trial_stop,
            "a trial count that fits in memory on this platform",
        )
    })?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| {
            ConfigError::new(
                "threads",
                threads,
                format!("a pool size the system can start ({e})"),
            )
        })?;
    let results: Vec<TrialResult> = pool.install(|| {
        (0..n_trials)
            .into_par_iter()
            .map(|k| {
                let trial = trial_start + k as u64;
                let r = run_trial(campaign, base_seed, trial, stop);
                if let Some(p) = progress {
                    p.fetch_add(1, Ordering::Relaxed);
                }
                r
            })
            .collect()
    });
    let m = campaign.measure_index.len();
    let mut out = CampaignOutput {
        trial_start,
        n_measure: m,
        position_m: Vec::with_capacity(n_trials * m),
        encoder_m: Vec::with_capacity(n_trials * m),
        status: Vec::with_capacity(n_trials),
        failures: Vec::new(),
    };
    for r in results {
        out.position_m.extend_from_slice(&r.position_m);
        out.encoder_m.extend_from_slice(&r.encoder_m);
        out.status.push(r.status);
        out.failures.extend(r.failure);
    }
    Ok(out)
}
