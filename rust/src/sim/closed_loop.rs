//! The closed loop: sample → controller → hold → integrate to the next event in time, with
//! every effect of the library: component plant, FPGA PID or cascade controller, sensor
//! errors and delays, computation delay, sample jitter, stochastic friction and known
//! disturbances. With everything off it runs the rigid seed plant.
use super::plant::AnyPlant;
use super::trace::{check_samples, check_series, Measured, Trace};
use crate::control::{flags, Cascade, CascadeConfig, Encoder, OutputStage, Pid, PidConfig};
use crate::error::{check_range, ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Stats, POLL_EVERY_SAMPLES};
use crate::model::{AxisParams, DriveParams, Inputs, Side};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use std::collections::VecDeque;
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

/// The controller of the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ControllerKind {
    /// The bit-exact FPGA PID with its DAC and amplifier.
    Fpga {
        /// The FPGA loop.
        pid: PidConfig,
        /// DAC → amplifier.
        output: OutputStage,
    },
    /// A floating-point cascade (dSPACE, EMPS).
    Cascade(CascadeConfig),
}

/// Interferometer channel: the true table position, quantised and noisy (recorded only).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interferometer {
    /// Resolution, m, in (0, 1e-3].
    pub resolution_m: f64,
    /// Noise standard deviation, m, in [0, 1e-3].
    pub noise_std_m: f64,
}

/// The feedback sensor and the optional interferometer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensors {
    /// The encoder (count size).
    pub encoder: Encoder,
    /// Where the encoder measures.
    pub side: Side,
    /// Interpolation (cyclic) error amplitude, m, in [0, 1e-4].
    pub cyclic_amplitude_m: f64,
    /// Period of the cyclic error (signal period of the scale), m, in (0, 1].
    pub cyclic_period_m: f64,
    /// Phase of the cyclic error, rad, finite.
    pub cyclic_phase_rad: f64,
    /// Noise added before quantisation, standard deviation, m, in [0, 1e-4].
    pub noise_std_m: f64,
    /// Delay of the reading, whole samples, in [0, 1000].
    pub delay_samples: usize,
    /// Interferometer channel.
    pub interferometer: Option<Interferometer>,
}

impl Sensors {
    /// An ideal encoder on the table.
    pub fn encoder(encoder: Encoder) -> Self {
        Self {
            encoder,
            side: Side::Table,
            cyclic_amplitude_m: 0.0,
            cyclic_period_m: 2e-5,
            cyclic_phase_rad: 0.0,
            noise_std_m: 0.0,
            delay_samples: 0,
            interferometer: None,
        }
    }

    fn validate(&self) -> Result<(), ConfigError> {
        self.encoder.validate().map_err(|e| e.within("encoder"))?;
        check_range("cyclic_amplitude_m", self.cyclic_amplitude_m, 0.0, 1e-4)?;
        crate::error::check_positive("cyclic_period_m", self.cyclic_period_m, 1.0)?;
        check_range("cyclic_phase_rad", self.cyclic_phase_rad, -1e6, 1e6)?;
        check_range("noise_std_m", self.noise_std_m, 0.0, 1e-4)?;
        if self.delay_samples > 1000 {
            return Err(ConfigError::new(
                "delay_samples",
                self.delay_samples,
                "an integer in [0, 1000]",
            ));
        }
        if let Some(i) = &self.interferometer {
            crate::error::check_positive("interferometer.resolution_m", i.resolution_m, 1e-3)?;
            check_range("interferometer.noise_std_m", i.noise_std_m, 0.0, 1e-3)?;
        }
        Ok(())
    }
}

/// Distribution of the per-trial friction level factor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpreadDistribution {
    /// 1 + s·N(0, 1), truncated at 0.05.
    Normal,
    /// exp(s·N(0, 1) − s²/2) (mean 1).
    LogNormal,
    /// 1 + s·√3·U(−1, 1) (standard deviation s).
    Uniform,
}

/// Stochastic friction: a per-trial level factor and a within-trial fluctuation (an
/// Ornstein–Uhlenbeck process sampled at the control rate), both multiplying every friction
/// level. Seeded; same seed → bit-identical run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StochasticFriction {
    /// Relative spread (standard deviation) of the per-trial factor, in [0, 0.5].
    pub level_spread: f64,
    /// Distribution of the per-trial factor.
    pub distribution: SpreadDistribution,
    /// Relative standard deviation of the within-trial fluctuation, in [0, 0.5].
    pub within_spread: f64,
    /// Correlation time of the fluctuation, s, in (0, 1e3].
    pub correlation_time_s: f64,
}

impl StochasticFriction {
    fn validate(&self) -> Result<(), ConfigError> {
        check_range("level_spread", self.level_spread, 0.0, 0.5)?;
        check_range("within_spread", self.within_spread, 0.0, 0.5)?;
        crate::error::check_positive("correlation_time_s", self.correlation_time_s, 1e3)
    }

    /// The per-trial factor drawn from `rng`.
    pub fn draw_level(&self, rng: &mut Pcg64Mcg) -> f64 {
        let s = self.level_spread;
        match self.distribution {
            SpreadDistribution::Normal => {
                let g: f64 = StandardNormal.sample(rng);
                (1.0 + s * g).max(0.05)
            }
            SpreadDistribution::LogNormal => {
                let g: f64 = StandardNormal.sample(rng);
                (s * g - 0.5 * s * s).exp()
            }
            SpreadDistribution::Uniform => 1.0 + s * 3f64.sqrt() * rng.random_range(-1.0..1.0),
        }
    }
}

/// Everything an extended closed-loop run needs besides the reference and the known inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtendedConfig {
    /// The component plant.
    pub drive: DriveParams,
    /// The rigid seed parameters the plant was built from, if any: when `drive` equals
    /// `DriveParams::from_axis(axis)` and no force disturbance or friction fluctuation is
    /// present, the loop runs the rigid plant (analytic Jacobian, exact stuck phases).
    pub axis: Option<AxisParams>,
    /// The controller.
    pub controller: ControllerKind,
    /// Sensors.
    pub sensors: Sensors,
    /// Extra whole samples between the controller's update and the plant, in [0, 1000].
    pub computation_delay_samples: usize,
    /// Sample-instant jitter: each sampling instant is moved by U(−j, j), s, in
    /// [0, 0.45·T].
    pub jitter_s: f64,
    /// Stochastic friction (off: `None`).
    pub stochastic: Option<StochasticFriction>,
    /// Seed of every random draw of the run.
    pub seed: u64,
    /// Integrator options.
    pub integrator: IntegratorOptions,
    /// Initial position of every mass (at rest, relaxed), m, in [−10, 10].
    pub initial_position_m: f64,
    /// Where the drive side of a dead band (backlash) rests at the start, in [−1, 1]:
    /// ±1 against the flank that pushes the table toward ±x, 0 the centre (without a dead
    /// band it has no effect).
    pub initial_flank: f64,
}

impl ExtendedConfig {
    /// The seed-style closed loop with every effect off.
    pub fn from_closed_loop(cfg: &ClosedLoopConfig) -> Self {
        Self {
            drive: DriveParams::from_axis(&cfg.axis),
            axis: Some(cfg.axis),
            controller: ControllerKind::Fpga {
                pid: cfg.pid,
                output: cfg.output,
            },
            sensors: Sensors::encoder(cfg.encoder),
            computation_delay_samples: 0,
            jitter_s: 0.0,
            stochastic: None,
            seed: 0,
            integrator: cfg.integrator,
            initial_position_m: 0.0,
            initial_flank: 0.0,
        }
    }

    /// Sample period, s.
    pub fn sample_period_s(&self) -> f64 {
        match &self.controller {
            ControllerKind::Fpga { pid, .. } => pid.ticks_per_sample as f64 / pid.clock_hz,
            ControllerKind::Cascade(c) => c.sample_period_s,
        }
    }

    /// Validate every part; errors carry the dotted field path.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.drive.validate().map_err(|e| e.within("plant"))?;
        match &self.controller {
            ControllerKind::Fpga { pid, output } => {
                pid.validate().map_err(|e| e.within("controller"))?;
                output.validate().map_err(|e| e.within("output_stage"))?;
            }
            ControllerKind::Cascade(c) => c.validate().map_err(|e| e.within("controller"))?,
        }
        self.sensors.validate().map_err(|e| e.within("sensors"))?;
        if self.computation_delay_samples > 1000 {
            return Err(ConfigError::new(
                "timing.computation_delay_samples",
                self.computation_delay_samples,
                "an integer in [0, 1000]",
            ));
        }
        let t = self.sample_period_s();
        check_range("timing.jitter_s", self.jitter_s, 0.0, 0.45 * t)?;
        if let ControllerKind::Fpga { pid, .. } = &self.controller {
            let lat = pid.latency_ticks as f64 / pid.clock_hz;
            if self.jitter_s > 0.0 && lat + self.jitter_s >= t - self.jitter_s {
                return Err(ConfigError::new(
                    "timing.jitter_s",
                    self.jitter_s,
                    "small enough that the output update stays before the next sample",
                ));
            }
        }
        if let Some(s) = &self.stochastic {
            s.validate().map_err(|e| e.within("stochastic"))?;
        }
        check_range("initial_position_m", self.initial_position_m, -10.0, 10.0)?;
        check_range("initial_flank", self.initial_flank, -1.0, 1.0)?;
        self.integrator
            .validate()
            .map_err(|e| e.within("integrator"))
    }
}

/// Known inputs per control sample (empty slices: none).
#[derive(Debug, Clone, Copy, Default)]
pub struct KnownInputs<'a> {
    /// Force on the table held over sample interval n, N (+x).
    pub force_n: &'a [f64],
    /// Voltage added to the controller's (saturated) output of sample n, V.
    pub command_v: &'a [f64],
}

/// Derive the stream seed of one purpose from the run seed (SplitMix64 finaliser).
pub fn stream_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The stop request of a run: `flag` set from outside (`None`: never).
fn flag_poll(flag: Option<&AtomicBool>) -> impl FnMut() -> bool + '_ {
    move || flag.is_some_and(|f| f.load(Ordering::Relaxed))
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

/// Run the extended closed loop over `reference_m` (one value per control sample). `stop`
/// is polled every [`POLL_EVERY_SAMPLES`] samples; when set the run ends with
/// [`SimError::Interrupted`].
pub fn run_extended(
    cfg: &ExtendedConfig,
    reference_m: &[f64],
    known: KnownInputs<'_>,
    stop: Option<&AtomicBool>,
) -> Result<Trace, SimError> {
    run_extended_polled(cfg, reference_m, known, &mut flag_poll(stop))
}

/// [`run_extended`] asking `poll` every [`POLL_EVERY_SAMPLES`] control samples whether to
/// stop (true: the run ends with [`SimError::Interrupted`]); the bindings poll for Ctrl-C.
/// The poll does not change the run.
pub fn run_extended_polled(
    cfg: &ExtendedConfig,
    reference_m: &[f64],
    known: KnownInputs<'_>,
    poll: &mut dyn FnMut() -> bool,
) -> Result<Trace, SimError> {
    let mut tr = Trace::default();
    let stats = run_loop(cfg, reference_m, known, poll, &mut Sink::Trace(&mut tr))?;
    tr.stats = stats;
    Ok(tr)
}

/// [`run_extended`] keeping only the table position and the encoder reading at the samples
/// `measure_index` (strictly increasing; indices past the reference are ignored): the same
/// run, bit for bit (`position_m[j]` equals the trace's `position_m[measure_index[j]]`), without
/// the per-sample trace (channels, friction forces, controller terms) that a Monte Carlo
/// campaign does not keep.
pub fn run_extended_at(
    cfg: &ExtendedConfig,
    reference_m: &[f64],
    known: KnownInputs<'_>,
    stop: Option<&AtomicBool>,
    measure_index: &[usize],
) -> Result<Measured, SimError> {
    let mut out = Measured {
        position_m: Vec::with_capacity(measure_index.len()),
        encoder_counts: Vec::with_capacity(measure_index.len()),
        stats: Stats::default(),
    };
    let mut sink = Sink::At {
        index: measure_index,
        next: 0,
        out: &mut out,
    };
    let stats = run_loop(cfg, reference_m, known, &mut flag_poll(stop), &mut sink)?;
    out.stats = stats;
    Ok(out)
}

/// Where the loop's samples go.
enum Sink<'a> {
    /// Every channel of every sample.
    Trace(&'a mut Trace),
    /// Position and encoder reading at the samples `index` (`next`: the first not yet reached).
    At {
        index: &'a [usize],
        next: usize,
        out: &'a mut Measured,
    },
}

/// The loop of [`run_extended`]; returns the integrator's work counters.
fn run_loop(
    cfg: &ExtendedConfig,
    reference_m: &[f64],
    known: KnownInputs<'_>,
    poll: &mut dyn FnMut() -> bool,
    sink: &mut Sink<'_>,
) -> Result<Stats, SimError> {
    cfg.validate()?;
    let n = reference_m.len();
    check_samples(n)?;
    check_series("reference_m", reference_m, n)?;
    check_series("force_disturbance_n", known.force_n, n)?;
    check_series("command_disturbance_v", known.command_v, n)?;
    let fluctuating = cfg.stochastic.is_some_and(|s| s.within_spread > 0.0);
    let mut rng_friction = Pcg64Mcg::seed_from_u64(stream_seed(cfg.seed, 1));
    let level = cfg
        .stochastic
        .map_or(1.0, |s| s.draw_level(&mut rng_friction));
    // The rigid plant serves whenever the component plant would be the seed axis itself; a
    // per-trial level factor only scales its friction levels (the same levels the component
    // plant's `friction_scale` multiplies), so Monte Carlo trials keep the fast path.
    let rigid_ok = known.force_n.is_empty() && !fluctuating;
    let mut plant = AnyPlant::new(
        &cfg.drive,
        cfg.axis.as_ref().filter(|_| rigid_ok),
        level,
        cfg.integrator,
    )?;
    plant.set_position(cfg.initial_position_m, cfg.initial_flank);
    let t_s = cfg.sample_period_s();
    let latency_s = match &cfg.controller {
        ControllerKind::Fpga { pid, .. } => pid.latency_ticks as f64 / pid.clock_hz,
        ControllerKind::Cascade(_) => 0.0,
    };
    let sample_time = |k: usize| match &cfg.controller {
        ControllerKind::Fpga { pid, .. } => (k as u64 * pid.ticks_per_sample) as f64 / pid.clock_hz,
        ControllerKind::Cascade(c) => k as f64 * c.sample_period_s,
    };
    // Jittered sampling instants (the first sample at t = 0).
    let mut rng_jitter = Pcg64Mcg::seed_from_u64(stream_seed(cfg.seed, 2));
    let mut rng_noise = Pcg64Mcg::seed_from_u64(stream_seed(cfg.seed, 3));
    let mut rng_interf = Pcg64Mcg::seed_from_u64(stream_seed(cfg.seed, 4));
    let mut times: Vec<f64> = (0..=n).map(sample_time).collect();
    if cfg.jitter_s > 0.0 {
        for t in times.iter_mut().take(n).skip(1) {
            *t += rng_jitter.random_range(-cfg.jitter_s..=cfg.jitter_s);
        }
    }
    // Friction level per sample interval.
    let mut scale = vec![level; if fluctuating { n } else { 0 }];
    if let (Some(s), true) = (&cfg.stochastic, fluctuating) {
        let a = (-t_s / s.correlation_time_s).exp();
        let b = s.within_spread * (1.0 - a * a).sqrt();
        let g0: f64 = StandardNormal.sample(&mut rng_friction);
        let mut w = s.within_spread * g0;
        for v in scale.iter_mut() {
            *v = (level * (1.0 + w)).max(0.05 * level);
            let g: f64 = StandardNormal.sample(&mut rng_friction);
            w = a * w + b * g;
        }
    }
    if let Sink::Trace(tr) = sink {
        **tr = Trace::with_capacity(n);
    }
    let mut pid = match &cfg.controller {
        ControllerKind::Fpga { pid, .. } => {
            Some(Pid::new(*pid).map_err(|e| e.within("controller"))?)
        }
        ControllerKind::Cascade(_) => None,
    };
    let mut cascade = match &cfg.controller {
        ControllerKind::Cascade(c) => Some(Cascade::new(*c).map_err(|e| e.within("controller"))?),
        ControllerKind::Fpga { .. } => None,
    };
    let enc = &cfg.sensors;
    let mut reading_buf: VecDeque<i64> = VecDeque::with_capacity(enc.delay_samples + 1);
    let mut output_buf: VecDeque<f64> = VecDeque::with_capacity(cfg.computation_delay_samples + 1);
    let mut u_held = 0.0_f64;
    for (k, &r_m) in reference_m.iter().enumerate() {
        if k % POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: times[k] });
        }
        let inp = Inputs {
            u_v: u_held,
            force_n: known.force_n.get(k).copied().unwrap_or(0.0),
            friction_scale: if fluctuating { scale[k] } else { level },
        };
        let t_n = times[k];
        let (x_t, x_m) = plant.positions();
        // Sensor: cyclic error and noise before the floor quantisation, then the delay.
        let x_sensed = match enc.side {
            Side::Table => x_t,
            Side::Motor => x_m,
        };
        let mut x_read = x_sensed;
        if enc.cyclic_amplitude_m > 0.0 {
            x_read += enc.cyclic_amplitude_m
                * (2.0 * std::f64::consts::PI * x_sensed / enc.cyclic_period_m
                    + enc.cyclic_phase_rad)
                    .sin();
        }
        if enc.noise_std_m > 0.0 {
            let g: f64 = StandardNormal.sample(&mut rng_noise);
            x_read += enc.noise_std_m * g;
        }
        let counts_now = enc.encoder.read(x_read);
        // Without a reading delay the buffer would hand back the reading just pushed.
        let counts_seen = if enc.delay_samples == 0 {
            counts_now
        } else {
            reading_buf.push_back(counts_now);
            if reading_buf.len() > enc.delay_samples {
                reading_buf.pop_front().unwrap_or(counts_now)
            } else {
                *reading_buf.front().unwrap_or(&counts_now)
            }
        };
        let r_counts = enc.encoder.reference_counts(r_m);
        // The controller.
        // The controller (its recorded terms are converted only when a trace is kept).
        let (u_ctrl, fl, pid_out) = match (&cfg.controller, pid.as_mut(), cascade.as_mut()) {
            (ControllerKind::Fpga { pid: c, output }, Some(p), _) => {
                let out = p.step(r_counts, counts_seen);
                let (u, amp_sat) = output.motor_voltage(out.code, c.dac_lsb_v);
                let fl = out.flags
                    | if amp_sat {
                        flags::AMPLIFIER_SATURATED
                    } else {
                        0
                    };
                (u, fl, Some(out))
            }
            (ControllerKind::Cascade(_), _, Some(c)) => {
                let y_m = counts_seen as f64 * enc.encoder.count_m;
                let (u, sat) = c.step(r_m, y_m);
                let fl = if sat { flags::AMPLIFIER_SATURATED } else { 0 };
                (u, fl, None)
            }
            _ => unreachable!("controller state matches its kind"),
        };
        let u_dist = u_ctrl + known.command_v.get(k).copied().unwrap_or(0.0);
        // Without a computation delay the buffer would hand back the output just pushed.
        let u_new = if cfg.computation_delay_samples == 0 {
            u_dist
        } else {
            output_buf.push_back(u_dist);
            if output_buf.len() > cfg.computation_delay_samples {
                output_buf.pop_front().unwrap_or(u_dist)
            } else {
                0.0
            }
        };
        match sink {
            Sink::Trace(tr) => {
                let (_, _, v_t, cur, f_motor, f_table, stuck) = plant.observe(&inp);
                plant.check_finite(t_n, &[v_t, cur, f_motor, f_table])?;
                let (command, terms) = match (&cfg.controller, pid_out) {
                    (ControllerKind::Fpga { pid: c, .. }, Some(out)) => (
                        c.output_format.to_f64(out.u),
                        (
                            out.code,
                            c.error_format.to_f64(out.e),
                            c.term_format.to_f64(out.p),
                            c.integrator_format.to_f64(out.i),
                            c.term_format.to_f64(out.d),
                        ),
                    ),
                    _ => (u_ctrl, (0, 0.0, 0.0, 0.0, 0.0)),
                };
                tr.time_s.push(t_n);
                tr.reference_m.push(r_m);
                tr.reference_counts.push(r_counts);
                tr.position_m.push(x_t);
                tr.motor_position_m.push(x_m);
                tr.velocity_m_per_s.push(v_t);
                tr.encoder_counts.push(counts_now);
                tr.current_a.push(cur);
                tr.motor_voltage_v.push(u_new);
                tr.command.push(command);
                tr.dac_code.push(terms.0);
                tr.error.push(terms.1);
                tr.p_term.push(terms.2);
                tr.i_term.push(terms.3);
                tr.d_term.push(terms.4);
                tr.flags.push(fl);
                tr.motor_friction_force_n.push(f_motor);
                tr.table_friction_force_n.push(f_table);
                tr.stuck.push(stuck);
                if let Some(i) = &enc.interferometer {
                    let g: f64 = if i.noise_std_m > 0.0 {
                        StandardNormal.sample(&mut rng_interf)
                    } else {
                        0.0
                    };
                    tr.interferometer_m
                        .push((x_t / i.resolution_m).round() * i.resolution_m + i.noise_std_m * g);
                }
            }
            Sink::At { index, next, out } => {
                if index.get(*next) == Some(&k) {
                    out.position_m.push(x_t);
                    out.encoder_counts.push(counts_now);
                    *next += 1;
                }
            }
        }
        let t_update = t_n + latency_s;
        let inp_new = Inputs { u_v: u_new, ..inp };
        if inp_new == inp && plant.is_rigid() {
            // The update leaves the held input as it is (e.g. at the voltage limit): the
            // plant's ODE is the same on both sides of the update instant, so one segment.
            plant.advance(&inp, t_n, times[k + 1], poll)?;
        } else {
            plant.advance(&inp, t_n, t_update, poll)?;
            plant.advance(&inp_new, t_update, times[k + 1], poll)?;
        }
        u_held = u_new;
    }
    Ok(plant.stats())
}
