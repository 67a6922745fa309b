//! Typed errors: bad configuration (raised before anything runs) and numerical failures
//! (carrying the time and the state at which they happened).
use thiserror::Error;

/// A configuration value outside its valid range. Names the field, the value and the range.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("{field} = {value} is invalid: expected {expected}")]
pub struct ConfigError {
    /// Dotted path of the offending field, e.g. `plant.table.mass_kg`.
    pub field: String,
    /// The offending value, formatted.
    pub value: String,
    /// The valid range or set, in words.
    pub expected: String,
}

impl ConfigError {
    /// Build an error for `field` holding `value`, valid when `expected`.
    pub fn new(
        field: impl Into<String>,
        value: impl ToString,
        expected: impl Into<String>,
    ) -> Self {
        Self {
            field: field.into(),
            value: value.to_string(),
            expected: expected.into(),
        }
    }

    /// Prefix the field path with `prefix.` (used when a sub-struct is validated).
    #[must_use]
    pub fn within(mut self, prefix: &str) -> Self {
        self.field = format!("{prefix}.{}", self.field);
        self
    }
}

/// `value` as an error message shows it: as Rust prints it (`0.5`, `1000000`), except that
/// magnitudes below 1e-4 or from 1e16 up are in exponent form (`1e-30`, not thirty zeros).
pub fn format_value(value: f64) -> String {
    let a = value.abs();
    if value.is_finite() && a != 0.0 && !(1e-4..1e16).contains(&a) {
        format!("{value:e}")
    } else {
        value.to_string()
    }
}

/// Check that `value` is finite and inside `[lo, hi]`.
pub fn check_range(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(())
    } else {
        Err(ConfigError::new(
            field,
            format_value(value),
            format!("a finite number in [{lo:e}, {hi:e}]"),
        ))
    }
}

/// Check that `value` is finite and strictly inside `(lo, hi]`.
pub fn check_positive(field: &str, value: f64, hi: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value > 0.0 && value <= hi {
        Ok(())
    } else {
        Err(ConfigError::new(
            field,
            format_value(value),
            format!("a finite number in (0, {hi:e}]"),
        ))
    }
}

/// A numerical failure during a simulation.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SimError {
    /// The configuration is invalid (raised before any work).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The error-controlled step size fell below the minimum.
    #[error("step size {h_s:e} s fell below the minimum at t = {t_s} s; state = {state:?}")]
    StepSizeTooSmall {
        /// Time of the failure, s.
        t_s: f64,
        /// Rejected step size, s.
        h_s: f64,
        /// State vector at the failure.
        state: Vec<f64>,
    },
    /// The iteration matrix of the implicit method was singular.
    #[error("singular iteration matrix at t = {t_s} s; state = {state:?}")]
    SingularMatrix {
        /// Time of the failure, s.
        t_s: f64,
        /// State vector at the failure.
        state: Vec<f64>,
    },
    /// The state became NaN or infinite.
    #[error("non-finite state at t = {t_s} s; state = {state:?}")]
    NonFinite {
        /// Time of the failure, s.
        t_s: f64,
        /// State vector at the failure.
        state: Vec<f64>,
    },
    /// More integrator steps (accepted and rejected) than allowed in one control interval
    /// (see `IntegratorOptions::max_steps`).
    #[error(
        "more than {max_steps} steps in one control interval at t = {t_s} s; state = {state:?}"
    )]
    TooManySteps {
        /// Time of the failure, s.
        t_s: f64,
        /// The limit that was hit.
        max_steps: usize,
        /// State vector at the failure.
        state: Vec<f64>,
    },
    /// More stick/slip events than allowed in one control interval: the mode logic switches
    /// faster than the model can resolve (see `IntegratorOptions::max_events`).
    #[error(
        "more than {max_events} stick/slip events in one control interval at t = {t_s} s \
         (the friction switches faster than the model can resolve); state = {state:?}"
    )]
    TooManyEvents {
        /// Time of the failure, s.
        t_s: f64,
        /// The limit that was hit.
        max_events: usize,
        /// State vector at the failure.
        state: Vec<f64>,
    },
    /// The simulation was interrupted from outside (Ctrl-C).
    #[error("interrupted at t = {t_s} s")]
    Interrupted {
        /// Time of the interruption, s.
        t_s: f64,
    },
}

impl SimError {
    /// Simulated time of the failure (NaN for a configuration error) and the state there
    /// (empty when not known).
    pub fn time_and_state(&self) -> (f64, Vec<f64>) {
        match self {
            Self::StepSizeTooSmall { t_s, state, .. }
            | Self::SingularMatrix { t_s, state }
            | Self::NonFinite { t_s, state }
            | Self::TooManySteps { t_s, state, .. }
            | Self::TooManyEvents { t_s, state, .. } => (*t_s, state.clone()),
            Self::Interrupted { t_s } => (*t_s, Vec::new()),
            Self::Config(_) => (f64::NAN, Vec::new()),
        }
    }
}
