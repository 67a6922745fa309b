//! One closed-loop trial: sample → controller → hold → integrate to the next event in time.
use super::extended::{run_extended, ExtendedConfig, KnownInputs, POLL_EVERY_SAMPLES};
use crate::control::{Encoder, OutputStage, PidConfig};
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Rodas4, Stats};
use crate::model::{Axis, AxisParams, Mode, Plant};
use std::sync::atomic::AtomicBool;

/// Everything a closed-loop run needs besides the reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClosedLoopConfig {
    /// The plant.
    pub axis: AxisParams,
    /// The FPGA loop.
    pub pid: PidConfig,
    /// The encoder.
    pub encoder: Encoder,
    /// DAC → amplifier → motor.
    pub output: OutputStage,
    /// Integrator options.
    pub integrator: IntegratorOptions,
}

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

impl ClosedLoopConfig {
    /// Validate every part; errors carry the dotted field path.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.axis.validate().map_err(|e| e.within("plant"))?;
        self.pid.validate().map_err(|e| e.within("controller"))?;
        self.encoder.validate().map_err(|e| e.within("encoder"))?;
        self.output
            .validate()
            .map_err(|e| e.within("output_stage"))?;
        self.integrator
            .validate()
            .map_err(|e| e.within("integrator"))
    }
}

pub(crate) fn check_samples(n: usize) -> Result<(), ConfigError> {
    if n == 0 || n > MAX_SAMPLES {
        return Err(ConfigError::new(
            "reference_m (number of samples)",
            n,
            format!("between 1 and {MAX_SAMPLES} samples"),
        ));
    }
    Ok(())
}

/// Run the closed loop over `reference_m` (one value per control sample). `stop` is polled
/// every [`POLL_EVERY_SAMPLES`] samples; when set the run ends with
/// [`SimError::Interrupted`]. This is
/// [`run_extended`] with every effect off.
pub fn run_closed_loop(
    cfg: &ClosedLoopConfig,
    reference_m: &[f64],
    stop: Option<&AtomicBool>,
) -> Result<Trace, SimError> {
    cfg.validate()?;
    let ext = ExtendedConfig::from_closed_loop(cfg);
    run_extended(&ext, reference_m, KnownInputs::default(), stop)
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

/// Drive the plant alone with `voltage_v[k]` held on [k·T, (k+1)·T).
pub fn run_open_loop(
    axis: &AxisParams,
    integrator: &IntegratorOptions,
    voltage_v: &[f64],
    sample_period_s: f64,
) -> Result<OpenLoopTrace, SimError> {
    run_open_loop_polled(axis, integrator, voltage_v, sample_period_s, &mut || false)
}

/// [`run_open_loop`] asking `poll` every [`POLL_EVERY_SAMPLES`] samples whether to stop
/// (true: [`SimError::Interrupted`]).
pub fn run_open_loop_polled(
    axis: &AxisParams,
    integrator: &IntegratorOptions,
    voltage_v: &[f64],
    sample_period_s: f64,
    poll: &mut dyn FnMut() -> bool,
) -> Result<OpenLoopTrace, SimError> {
    crate::error::check_positive("sample_period_s", sample_period_s, 10.0)?;
    check_samples(voltage_v.len())?;
    if let Some((k, v)) = voltage_v.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(ConfigError::new(format!("voltage_v[{k}]"), v, "a finite voltage").into());
    }
    let axis = Axis::new(*axis).map_err(|e| e.within("plant"))?;
    let integ = Rodas4::new(*integrator).map_err(|e| e.within("integrator"))?;
    let mut plant = Plant::new(axis, integ);
    let n = voltage_v.len();
    let mut tr = OpenLoopTrace::default();
    let record = |plant: &Plant, t: f64, u: f64, tr: &mut OpenLoopTrace| {
        let current = plant.current(u);
        if !current.is_finite() {
            return Err(SimError::NonFinite {
                t_s: t,
                state: plant.y.iter().copied().collect(),
            });
        }
        tr.time_s.push(t);
        tr.position_m.push(plant.y[0]);
        tr.velocity_m_per_s.push(plant.y[1]);
        tr.dahl_force_n.push(plant.y[2]);
        tr.current_a.push(current);
        tr.stuck.push(plant.mode == Mode::Stuck);
        Ok(())
    };
    for (k, &u) in voltage_v.iter().enumerate() {
        let t0 = k as f64 * sample_period_s;
        if k % POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: t0 });
        }
        record(&plant, t0, u, &mut tr)?;
        plant.advance_polled(u, t0, (k + 1) as f64 * sample_period_s, poll)?;
    }
    record(
        &plant,
        n as f64 * sample_period_s,
        voltage_v[n - 1],
        &mut tr,
    )?;
    tr.stats = plant.integrator.stats;
    Ok(tr)
}
