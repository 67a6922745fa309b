//! One closed-loop trial: sample → controller → hold → integrate to the next event in time.
use crate::control::{flags, Encoder, OutputStage, Pid, PidConfig};
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Rodas4, Stats};
use crate::model::{Axis, AxisParams, Mode, Plant};
use std::sync::atomic::{AtomicBool, Ordering};

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
    /// Dahl friction force, N.
    pub dahl_force_n: Vec<f64>,
    /// Whether the drive train was stuck at t_n.
    pub stuck: Vec<bool>,
    /// Integrator work counters.
    pub stats: Stats,
}

impl Trace {
    fn with_capacity(n: usize) -> Self {
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
            dahl_force_n: Vec::with_capacity(n),
            stuck: Vec::with_capacity(n),
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

fn check_samples(n: usize) -> Result<(), ConfigError> {
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
/// every 1024 samples; when set the run ends with [`SimError::Interrupted`].
pub fn run_closed_loop(
    cfg: &ClosedLoopConfig,
    reference_m: &[f64],
    stop: Option<&AtomicBool>,
) -> Result<Trace, SimError> {
    cfg.validate()?;
    check_samples(reference_m.len())?;
    if let Some((k, v)) = reference_m.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(
            ConfigError::new(format!("reference_m[{k}]"), v, "a finite position in m").into(),
        );
    }
    let axis = Axis::new(cfg.axis).map_err(|e| e.within("plant"))?;
    let integrator = Rodas4::new(cfg.integrator).map_err(|e| e.within("integrator"))?;
    let mut pid = Pid::new(cfg.pid).map_err(|e| e.within("controller"))?;
    let mut plant = Plant::new(axis, integrator);
    let n = reference_m.len();
    let mut tr = Trace::with_capacity(n);
    let c = &cfg.pid;
    let clock = c.clock_hz;
    let tick_t = |ticks: u64| ticks as f64 / clock;
    let mut u_held = 0.0_f64;
    for (k, &r_m) in reference_m.iter().enumerate() {
        if k % 1024 == 0 {
            if let Some(flag) = stop {
                if flag.load(Ordering::Relaxed) {
                    return Err(SimError::Interrupted {
                        t_s: tick_t(k as u64 * c.ticks_per_sample),
                    });
                }
            }
        }
        let t_sample_ticks = k as u64 * c.ticks_per_sample;
        let t_n = tick_t(t_sample_ticks);
        let t_update = tick_t(t_sample_ticks + c.latency_ticks);
        let t_next = tick_t(t_sample_ticks + c.ticks_per_sample);
        let y_counts = cfg.encoder.read(plant.y[0]);
        let r_counts = cfg.encoder.reference_counts(r_m);
        let out = pid.step(r_counts, y_counts);
        let (u_new, amp_sat) = cfg.output.motor_voltage(out.code, c.dac_lsb_v);
        let fl = out.flags
            | if amp_sat {
                flags::AMPLIFIER_SATURATED
            } else {
                0
            };
        // Record the plant at t_n (with the voltage held before the update) and the update.
        tr.time_s.push(t_n);
        tr.reference_m.push(r_m);
        tr.reference_counts.push(r_counts);
        tr.position_m.push(plant.y[0]);
        tr.velocity_m_per_s.push(plant.y[1]);
        tr.encoder_counts.push(y_counts);
        tr.current_a.push(plant.current(u_held));
        tr.motor_voltage_v.push(u_new);
        tr.command.push(c.output_format.to_f64(out.u));
        tr.dac_code.push(out.code);
        tr.error.push(c.error_format.to_f64(out.e));
        tr.p_term.push(c.term_format.to_f64(out.p));
        tr.i_term.push(c.integrator_format.to_f64(out.i));
        tr.d_term.push(c.term_format.to_f64(out.d));
        tr.flags.push(fl);
        tr.motor_friction_force_n.push(
            plant
                .axis
                .motor_friction_force(&plant.y, plant.mode, u_held),
        );
        tr.dahl_force_n.push(plant.y[2]);
        tr.stuck.push(plant.mode == Mode::Stuck);
        if c.latency_ticks > 0 {
            plant.advance(u_held, t_n, t_update)?;
        }
        u_held = u_new;
        plant.advance(u_held, t_update, t_next)?;
    }
    tr.stats = plant.integrator.stats;
    Ok(tr)
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
        tr.time_s.push(t);
        tr.position_m.push(plant.y[0]);
        tr.velocity_m_per_s.push(plant.y[1]);
        tr.dahl_force_n.push(plant.y[2]);
        tr.current_a.push(plant.current(u));
        tr.stuck.push(plant.mode == Mode::Stuck);
    };
    for (k, &u) in voltage_v.iter().enumerate() {
        let t0 = k as f64 * sample_period_s;
        record(&plant, t0, u, &mut tr);
        plant.advance(u, t0, (k + 1) as f64 * sample_period_s)?;
    }
    record(
        &plant,
        n as f64 * sample_period_s,
        voltage_v[n - 1],
        &mut tr,
    );
    tr.stats = plant.integrator.stats;
    Ok(tr)
}
