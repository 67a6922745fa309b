//! The closed loop with every effect of the library: component plant, FPGA PID or cascade
//! controller, sensor errors and delays, computation delay, sample jitter, stochastic
//! friction and known disturbances. With everything off it runs the rigid seed plant.
use super::trial::{check_samples, ClosedLoopConfig, Trace};
use crate::control::{flags, Cascade, CascadeConfig, Encoder, OutputStage, Pid, PidConfig};
use crate::error::{check_range, ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Rodas4, Stats};
use crate::model::{
    AnyDrivePlant, Axis, AxisParams, DriveParams, Inputs, MassMode, Mode, Plant, Side,
};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};

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

enum AnyPlant {
    Rigid(Box<Plant>),
    Drive(AnyDrivePlant),
}

impl AnyPlant {
    fn advance(
        &mut self,
        inp: &Inputs,
        t0: f64,
        t1: f64,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<(), SimError> {
        if t1 <= t0 {
            return Ok(());
        }
        match self {
            Self::Rigid(p) => p.advance_polled(inp.u_v, t0, t1, poll),
            Self::Drive(p) => p.advance_polled(inp, t0, t1, poll),
        }
    }

    /// (table position, motor-side position): what the sensors need (equal to the first two
    /// entries of [`Self::observe`]).
    #[inline]
    fn positions(&self) -> (f64, f64) {
        match self {
            Self::Rigid(p) => (p.y[0], p.y[0]),
            Self::Drive(p) => {
                let y = p.state();
                (y[2 * p.drive().table()], y[0])
            }
        }
    }

    /// (table position, motor-side position, table velocity, current, motor friction,
    /// table friction, stuck)
    fn observe(&self, inp: &Inputs) -> (f64, f64, f64, f64, f64, f64, bool) {
        match self {
            Self::Rigid(p) => (
                p.y[0],
                p.y[0],
                p.y[1],
                p.current(inp.u_v),
                p.axis.motor_friction_force(&p.y, p.mode, inp.u_v),
                p.y[2],
                p.mode == Mode::Stuck,
            ),
            Self::Drive(p) => {
                let d = p.drive();
                let y = p.state();
                let modes = p.modes();
                let t = d.table();
                let (fm, ft) = d.friction_forces(y, inp, &modes);
                (
                    y[2 * t],
                    y[0],
                    y[2 * t + 1],
                    d.current_a(y, inp),
                    fm,
                    ft,
                    modes[0] == MassMode::Stuck || modes[t] == MassMode::Stuck,
                )
            }
        }
    }

    fn stats(&self) -> Stats {
        match self {
            Self::Rigid(p) => p.integrator.stats,
            Self::Drive(p) => p.stats(),
        }
    }

    /// [`SimError::NonFinite`] at `t_s` (with the plant's state) unless every value of
    /// `observed` is finite: a recorded channel that is not finite is an error, never output.
    fn check_finite(&self, t_s: f64, observed: &[f64]) -> Result<(), SimError> {
        if observed.iter().all(|v| v.is_finite()) {
            return Ok(());
        }
        Err(SimError::NonFinite {
            t_s,
            state: match self {
                Self::Rigid(p) => p.y.iter().copied().collect(),
                Self::Drive(p) => p.state().to_vec(),
            },
        })
    }
}

/// Derive the stream seed of one purpose from the run seed (SplitMix64 finaliser).
pub fn stream_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn check_series(name: &str, v: &[f64], n: usize) -> Result<(), ConfigError> {
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

/// Control samples between two polls of a run's stop request.
pub const POLL_EVERY_SAMPLES: usize = 16;

/// The stop request of a run: `flag` set from outside (`None`: never).
pub(crate) fn flag_poll(flag: Option<&AtomicBool>) -> impl FnMut() -> bool + '_ {
    move || flag.is_some_and(|f| f.load(Ordering::Relaxed))
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
    let mut plant = match (&cfg.axis, rigid_ok) {
        (Some(axis), true) if DriveParams::from_axis(axis) == cfg.drive => {
            let a = Axis::new(axis.with_friction_scale(level)).map_err(|e| e.within("plant"))?;
            let integ = Rodas4::new(cfg.integrator).map_err(|e| e.within("integrator"))?;
            AnyPlant::Rigid(Box::new(Plant::new(a, integ)))
        }
        _ => AnyPlant::Drive(
            AnyDrivePlant::new(cfg.drive, cfg.integrator).map_err(|e| e.within("plant"))?,
        ),
    };
    match &mut plant {
        AnyPlant::Rigid(p) => p.y[0] = cfg.initial_position_m,
        AnyPlant::Drive(p) => p.set_position(cfg.initial_position_m),
    }
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
        if inp_new == inp && matches!(plant, AnyPlant::Rigid(_)) {
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

/// Drive the component plant of `cfg` alone: `voltage_v[k]` (actuator command) and
/// `force_n[k]` (empty: none) held on `[k·T, (k+1)·T)`. Starts at rest.
pub fn run_drive_open_loop(
    cfg: &ExtendedConfig,
    voltage_v: &[f64],
    force_n: &[f64],
    sample_period_s: f64,
) -> Result<DriveOpenLoopTrace, SimError> {
    run_drive_open_loop_polled(cfg, voltage_v, force_n, sample_period_s, &mut || false)
}

/// [`run_drive_open_loop`] asking `poll` every [`POLL_EVERY_SAMPLES`] samples whether to
/// stop (true: [`SimError::Interrupted`]).
pub fn run_drive_open_loop_polled(
    cfg: &ExtendedConfig,
    voltage_v: &[f64],
    force_n: &[f64],
    sample_period_s: f64,
    poll: &mut dyn FnMut() -> bool,
) -> Result<DriveOpenLoopTrace, SimError> {
    crate::error::check_positive("sample_period_s", sample_period_s, 10.0)?;
    let n = voltage_v.len();
    check_samples(n)?;
    check_series("voltage_v", voltage_v, n)?;
    check_series("force_n", force_n, n)?;
    let mut plant = AnyPlant::Drive(
        AnyDrivePlant::new(cfg.drive, cfg.integrator).map_err(|e| e.within("plant"))?,
    );
    let mut tr = DriveOpenLoopTrace::default();
    let record = |plant: &AnyPlant, t: f64, inp: &Inputs, tr: &mut DriveOpenLoopTrace| {
        let (x_t, x_m, v_t, _, f_m, f_t, stuck) = plant.observe(inp);
        plant.check_finite(t, &[x_t, x_m, v_t, f_m, f_t])?;
        tr.time_s.push(t);
        tr.position_m.push(x_t);
        tr.motor_position_m.push(x_m);
        tr.velocity_m_per_s.push(v_t);
        tr.motor_friction_force_n.push(f_m);
        tr.table_friction_force_n.push(f_t);
        tr.stuck.push(stuck);
        Ok::<(), SimError>(())
    };
    let mut inp = Inputs::voltage(0.0);
    for (k, &u_v) in voltage_v.iter().enumerate() {
        inp = Inputs {
            u_v,
            force_n: force_n.get(k).copied().unwrap_or(0.0),
            friction_scale: 1.0,
        };
        let t0 = k as f64 * sample_period_s;
        if k % POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: t0 });
        }
        record(&plant, t0, &inp, &mut tr)?;
        plant.advance(&inp, t0, (k + 1) as f64 * sample_period_s, poll)?;
    }
    record(&plant, n as f64 * sample_period_s, &inp, &mut tr)?;
    tr.stats = plant.stats();
    Ok(tr)
}
