//! What a run records (every channel of a closed loop, chosen samples of a campaign trial,
//! the open loop of either plant) and the checks of the series a run is given.
use crate::error::ConfigError;
use crate::integrate::Stats;

/// Largest trace the core accepts, in samples (about 1.7 GB of channels at 2^24 samples).
pub const MAX_SAMPLES: usize = 1 << 24;

/// What a closed-loop run recorded, one entry per control sample n at t_n = n·T.
/// Plant channels are sampled at t_n; controller channels are the update computed from the
/// sample at t_n (effective at the plant from t_n + latency).
#[derive(Debug, Clone, Default)]
pub struct Trace {
    /// Sample instants, s.
    pub time_s: Vec<f64>,
    /// Reference, m (as given).
    pub reference_m: Vec<f64>,
    /// Reference as the FPGA sees it, counts.
    pub reference_counts: Vec<i64>,
    /// True table position, m.
    pub position_m: Vec<f64>,
    /// Table velocity, m/s.
    pub velocity_m_per_s: Vec<f64>,
    /// Encoder reading, counts.
    pub encoder_counts: Vec<i64>,
    /// Motor current at t_n, A.
    pub current_a: Vec<f64>,
    /// Motor voltage applied from t_n + latency, V.
    pub motor_voltage_v: Vec<f64>,
    /// Controller output after the range clamp, output units.
    pub command: Vec<f64>,
    /// DAC code.
    pub dac_code: Vec<i64>,
    /// Error, counts (value of the error register).
    pub error: Vec<f64>,
    /// P term, output units.
    pub p_term: Vec<f64>,
    /// Integrator, output units.
    pub i_term: Vec<f64>,
    /// D term, output units.
    pub d_term: Vec<f64>,
    /// Flag bits (`control::flags`).
    pub flags: Vec<u32>,
    /// Motor-shaft friction reflected to the table, N.
    pub motor_friction_force_n: Vec<f64>,
    /// Table-side friction force (the Dahl force in the seed model), N.
    pub table_friction_force_n: Vec<f64>,
    /// Whether the drive train (motor side or table) was stuck at t_n.
    pub stuck: Vec<bool>,
    /// Motor-side position at the table (equals `position_m` for a rigid chain), m.
    pub motor_position_m: Vec<f64>,
    /// Interferometer reading, m (empty without an interferometer).
    pub interferometer_m: Vec<f64>,
    /// Integrator work counters.
    pub stats: Stats,
}

impl Trace {
    pub(crate) fn with_capacity(n: usize) -> Self {
        Self {
            time_s: Vec::with_capacity(n),
            reference_m: Vec::with_capacity(n),
            reference_counts: Vec::with_capacity(n),
            position_m: Vec::with_capacity(n),
            velocity_m_per_s: Vec::with_capacity(n),
            encoder_counts: Vec::with_capacity(n),
            current_a: Vec::with_capacity(n),
            motor_voltage_v: Vec::with_capacity(n),
            command: Vec::with_capacity(n),
            dac_code: Vec::with_capacity(n),
            error: Vec::with_capacity(n),
            p_term: Vec::with_capacity(n),
            i_term: Vec::with_capacity(n),
            d_term: Vec::with_capacity(n),
            flags: Vec::with_capacity(n),
            motor_friction_force_n: Vec::with_capacity(n),
            table_friction_force_n: Vec::with_capacity(n),
            stuck: Vec::with_capacity(n),
            motor_position_m: Vec::with_capacity(n),
            interferometer_m: Vec::new(),
            stats: Stats::default(),
        }
    }
}

/// What a run measured at chosen samples only (see [`run_extended_at`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Measured {
    /// True table position at each chosen sample, m.
    pub position_m: Vec<f64>,
    /// Encoder reading (before any reading delay) at each chosen sample, counts.
    pub encoder_counts: Vec<i64>,
    /// Integrator work counters.
    pub stats: Stats,
}

/// What an open-loop run recorded, at t_k = k·T for k = 0..=n.
#[derive(Debug, Clone, Default)]
pub struct OpenLoopTrace {
    /// Sample instants, s.
    pub time_s: Vec<f64>,
    /// Table position, m.
    pub position_m: Vec<f64>,
    /// Table velocity, m/s.
    pub velocity_m_per_s: Vec<f64>,
    /// Dahl force, N.
    pub dahl_force_n: Vec<f64>,
    /// Motor current, A.
    pub current_a: Vec<f64>,
    /// Stuck at t_k.
    pub stuck: Vec<bool>,
    /// Integrator work counters.
    pub stats: Stats,
}

/// What an open-loop run of the component plant recorded, at t_k = k·T for k = 0..=n.
#[derive(Debug, Clone, Default)]
pub struct DriveOpenLoopTrace {
    /// Sample instants, s.
    pub time_s: Vec<f64>,
    /// Table position, m.
    pub position_m: Vec<f64>,
    /// Motor-side position at the table, m.
    pub motor_position_m: Vec<f64>,
    /// Table velocity, m/s.
    pub velocity_m_per_s: Vec<f64>,
    /// Motor-side friction force, N.
    pub motor_friction_force_n: Vec<f64>,
    /// Table friction force, N.
    pub table_friction_force_n: Vec<f64>,
    /// Motor side or table stuck.
    pub stuck: Vec<bool>,
    /// Integrator work counters.
    pub stats: Stats,
}

/// The sample count of a run: between 1 and [`MAX_SAMPLES`].
pub(super) fn check_samples(n: usize) -> Result<(), ConfigError> {
    if n == 0 || n > MAX_SAMPLES {
        return Err(ConfigError::new(
            "reference_m (number of samples)",
            n,
            format!("between 1 and {MAX_SAMPLES} samples"),
        ));
    }
    Ok(())
}

/// An input series: empty (none) or of the reference's length `n`, every value finite.
pub(super) fn check_series(name: &str, v: &[f64], n: usize) -> Result<(), ConfigError> {
    if !v.is_empty() && v.len() != n {
        return Err(ConfigError::new(
            format!("{name} (length)"),
            v.len(),
            format!("0 (none) or the reference length {n}"),
        ));
    }
    if let Some((k, x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
        return Err(ConfigError::new(
            format!("{name}[{k}]"),
            x,
            "a finite number",
        ));
    }
    Ok(())
}
