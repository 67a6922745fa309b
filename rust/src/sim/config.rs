//! A whole system as the Python package describes it (plant, controller, sensors, effects),
//! and how the effects map onto the plant: [`build_system`] turns a [`SystemSpec`] into the
//! [`ExtendedConfig`] a run needs. Names given as text (rounding, sides, distributions) are
//! parsed here, so every configuration error of a system comes from the core.
use super::closed_loop::{
    ControllerKind, ExtendedConfig, Interferometer, Sensors, SpreadDistribution, StochasticFriction,
};
use crate::control::{
    AntiWindup, CascadeConfig, Encoder, FxpFormat, OutputStage, Overflow, PidConfig, Rounding,
};
use crate::error::ConfigError;
use crate::integrate::IntegratorOptions;
use crate::model::{
    Amplifier, AxisParams, DriveParams, DwellStatic, Link, Modulation, Side, StaticMap,
    TableFriction, MAX_MODULATION_TERMS,
};

/// A fixed-point format with its rounding and overflow named.
#[derive(Debug, Clone, PartialEq)]
pub struct FxpSpec {
    /// Signed.
    pub signed: bool,
    /// Word length, bits.
    pub word_bits: u32,
    /// Integer bits (may be negative or exceed the word).
    pub int_bits: i32,
    /// One of `truncate`, `half_up`, `half_even`.
    pub rounding: String,
    /// One of `saturate`, `wrap`.
    pub overflow: String,
}

impl FxpSpec {
    /// The validated format; errors name `field`.
    pub fn to_core(&self, field: &str) -> Result<FxpFormat, ConfigError> {
        let rounding = match self.rounding.as_str() {
            "truncate" => Rounding::Truncate,
            "half_up" => Rounding::HalfUp,
            "half_even" => Rounding::HalfEven,
            other => {
                return Err(ConfigError::new(
                    format!("{field}.rounding"),
                    format!("{other:?}"),
                    "one of 'truncate', 'half_up', 'half_even'",
                ))
            }
        };
        let overflow = match self.overflow.as_str() {
            "saturate" => Overflow::Saturate,
            "wrap" => Overflow::Wrap,
            other => {
                return Err(ConfigError::new(
                    format!("{field}.overflow"),
                    format!("{other:?}"),
                    "one of 'saturate', 'wrap'",
                ))
            }
        };
        let f = FxpFormat {
            signed: self.signed,
            word_bits: self.word_bits,
            int_bits: self.int_bits,
            rounding,
            overflow,
        };
        f.validate(field)?;
        Ok(f)
    }
}

/// The FPGA PID with its formats and anti-windup named.
#[derive(Debug, Clone, PartialEq)]
pub struct PidSpec {
    /// Proportional gain.
    pub kp: f64,
    /// Integral gain.
    pub ki: f64,
    /// Derivative gain.
    pub kd: f64,
    /// Format of the gains.
    pub gain_format: FxpSpec,
    /// Format of the measurement.
    pub measurement_format: FxpSpec,
    /// Format of the error.
    pub error_format: FxpSpec,
    /// Format of the P, I, D terms.
    pub term_format: FxpSpec,
    /// Format of the integrator.
    pub integrator_format: FxpSpec,
    /// Format of the output.
    pub output_format: FxpSpec,
    /// Format of the DAC code.
    pub dac_format: FxpSpec,
    /// Format of the DAC scale.
    pub dac_scale_format: FxpSpec,
    /// Output lower limit.
    pub output_min: f64,
    /// Output upper limit.
    pub output_max: f64,
    /// One of `none`, `clamp`, `conditional`.
    pub anti_windup: String,
    /// Volts per output unit.
    pub output_unit_v: f64,
    /// Volts per DAC code.
    pub dac_lsb_v: f64,
    /// FPGA clock, Hz.
    pub clock_hz: f64,
    /// Clock ticks per control sample.
    pub ticks_per_sample: u64,
    /// Clock ticks from sampling to the output update.
    pub latency_ticks: u64,
}

impl PidSpec {
    /// The controller configuration (formats validated).
    pub fn to_core(&self) -> Result<PidConfig, ConfigError> {
        let anti_windup = match self.anti_windup.as_str() {
            "none" => AntiWindup::None,
            "clamp" => AntiWindup::Clamp,
            "conditional" => AntiWindup::Conditional,
            other => {
                return Err(ConfigError::new(
                    "anti_windup",
                    format!("{other:?}"),
                    "one of 'none', 'clamp', 'conditional'",
                ))
            }
        };
        Ok(PidConfig {
            kp: self.kp,
            ki: self.ki,
            kd: self.kd,
            gain_format: self.gain_format.to_core("gain_format")?,
            measurement_format: self.measurement_format.to_core("measurement_format")?,
            error_format: self.error_format.to_core("error_format")?,
            term_format: self.term_format.to_core("term_format")?,
            integrator_format: self.integrator_format.to_core("integrator_format")?,
            output_format: self.output_format.to_core("output_format")?,
            dac_format: self.dac_format.to_core("dac_format")?,
            dac_scale_format: self.dac_scale_format.to_core("dac_scale_format")?,
            output_min: self.output_min,
            output_max: self.output_max,
            anti_windup,
            output_unit_v: self.output_unit_v,
            dac_lsb_v: self.dac_lsb_v,
            clock_hz: self.clock_hz,
            ticks_per_sample: self.ticks_per_sample,
            latency_ticks: self.latency_ticks,
        })
    }
}

/// A force drive moving a lumped mass (EMPS style).
#[derive(Debug, Clone, PartialEq)]
pub struct ForceDriveSpec {
    /// Drive gain, N/V.
    pub drive_gain_n_per_v: f64,
    /// Moving mass, kg.
    pub mass_kg: f64,
    /// Friction of the mass.
    pub friction: StaticMap,
    /// Constant external force, N.
    pub external_force_n: f64,
    /// Mass of the drive side, kg.
    pub drive_mass_kg: f64,
}

/// The plant of a system.
#[derive(Debug, Clone, PartialEq)]
pub enum PlantSpec {
    /// The rigid motor + gearhead + ball-screw axis.
    Rigid(AxisParams),
    /// A force drive.
    ForceDrive(ForceDriveSpec),
}

/// The controller of a system.
#[derive(Debug, Clone, PartialEq)]
#[allow(clippy::large_enum_variant)] // built once per call
pub enum ControllerSpec {
    /// The FPGA PID.
    Fpga(PidSpec),
    /// The floating-point cascade.
    Cascade(CascadeConfig),
}

/// The feedback encoder and where it measures.
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderSpec {
    /// Size of one count, m.
    pub count_m: f64,
    /// One of `motor`, `table`.
    pub side: String,
}

/// Modifiers of the motor-shaft friction.
#[derive(Debug, Clone, PartialEq)]
pub struct FrictionModifiersSpec {
    /// Direction asymmetry.
    pub asymmetry: f64,
    /// Dwell-time dependent static friction.
    pub dwell: Option<DwellStatic>,
    /// Frictional memory lag, s.
    pub memory_lag_s: Option<f64>,
}

/// Friction levels of one side modulated along the travel.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionFrictionSpec {
    /// One of `motor`, `table`.
    pub side: String,
    /// `(a_k, κ_k in rad/m, φ_k in rad)`.
    pub terms: Vec<(f64, f64, f64)>,
}

/// Stochastic friction with its distribution named.
#[derive(Debug, Clone, PartialEq)]
pub struct StochasticSpec {
    /// Trial-to-trial spread.
    pub level_spread: f64,
    /// One of `normal`, `lognormal`, `uniform`.
    pub distribution: String,
    /// Within-trial spread.
    pub within_spread: f64,
    /// Correlation time of the within-trial fluctuation, s.
    pub correlation_time_s: f64,
}

/// Gearhead backlash.
#[derive(Debug, Clone, PartialEq)]
pub struct BacklashSpec {
    /// Total dead-band width at the table, m.
    pub width_m: f64,
    /// Contact stiffness, N/m.
    pub contact_stiffness_n_per_m: f64,
    /// Contact damping, N·s/m.
    pub damping_n_s_per_m: f64,
    /// Where the drive side rests in the dead band at the start, in [−1, 1]: +1 against the
    /// flank that pushes the table toward +x (the last move was positive), −1 against the
    /// other, 0 the centre.
    pub initial_flank: f64,
}

/// Drive-train compliance.
#[derive(Debug, Clone, PartialEq)]
pub struct ComplianceSpec {
    /// Coupling stiffness, N/m.
    pub stiffness_n_per_m: f64,
    /// Coupling damping, N·s/m.
    pub damping_n_s_per_m: f64,
    /// Screw/nut axial stiffness, N/m (three masses).
    pub axial_stiffness_n_per_m: Option<f64>,
    /// Screw/nut axial damping, N·s/m.
    pub axial_damping_n_s_per_m: f64,
}

/// Encoder interpolation error and noise.
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderErrorsSpec {
    /// Cyclic error amplitude, m.
    pub cyclic_amplitude_m: f64,
    /// Cyclic error period, m.
    pub cyclic_period_m: f64,
    /// Cyclic error phase, rad.
    pub cyclic_phase_rad: f64,
    /// Noise standard deviation, m.
    pub noise_std_m: f64,
}

/// The effects switched on.
#[derive(Debug, Clone, PartialEq)]
pub struct EffectsSpec {
    /// Replaces the plant's table friction.
    pub table_friction: Option<TableFriction>,
    /// Modifiers of the motor-shaft friction.
    pub motor_friction: FrictionModifiersSpec,
    /// Position-dependent friction.
    pub position_friction: Vec<PositionFrictionSpec>,
    /// Stochastic friction.
    pub stochastic: Option<StochasticSpec>,
    /// Backlash.
    pub backlash: Option<BacklashSpec>,
    /// Compliance.
    pub compliance: Option<ComplianceSpec>,
    /// Amplifier dynamics.
    pub amplifier: Option<Amplifier>,
    /// Encoder errors.
    pub encoder_errors: Option<EncoderErrorsSpec>,
    /// Interferometer channel.
    pub interferometer: Option<Interferometer>,
    /// Sensor delay, samples.
    pub sensor_delay_samples: usize,
    /// Computation delay, samples.
    pub computation_delay_samples: usize,
    /// Sample jitter, s.
    pub jitter_s: f64,
}

/// A whole system.
#[derive(Debug, Clone, PartialEq)]
pub struct SystemSpec {
    /// The plant.
    pub plant: PlantSpec,
    /// The controller.
    pub controller: ControllerSpec,
    /// The encoder.
    pub encoder: EncoderSpec,
    /// DAC → amplifier.
    pub output_stage: OutputStage,
    /// Integrator options.
    pub integrator: IntegratorOptions,
    /// Effects.
    pub effects: EffectsSpec,
}

/// The side named `s`; errors name `field`.
pub fn side(field: &str, s: &str) -> Result<Side, ConfigError> {
    match s {
        "motor" => Ok(Side::Motor),
        "table" => Ok(Side::Table),
        other => Err(ConfigError::new(
            field,
            format!("{other:?}"),
            "one of 'motor', 'table'",
        )),
    }
}

/// Append the position-friction `terms` to `into`.
pub fn modulation(terms: &[(f64, f64, f64)], into: &mut Modulation) -> Result<(), ConfigError> {
    let start = into.n_terms;
    if start + terms.len() > MAX_MODULATION_TERMS {
        return Err(ConfigError::new(
            "effects.position_friction (terms per side)",
            start + terms.len(),
            format!("at most {MAX_MODULATION_TERMS}"),
        ));
    }
    for (k, &(a, kappa, phi)) in terms.iter().enumerate() {
        into.amplitude[start + k] = a;
        into.wavenumber_rad_per_m[start + k] = kappa;
        into.phase_rad[start + k] = phi;
    }
    into.n_terms += terms.len();
    Ok(())
}

/// The run configuration of `sys` with the random draws seeded by `seed` and every mass
/// starting at rest at `initial_position_m` (validated).
pub fn build_system(
    sys: &SystemSpec,
    seed: u64,
    initial_position_m: f64,
) -> Result<ExtendedConfig, ConfigError> {
    let fx = &sys.effects;
    let (mut drive, axis) = match &sys.plant {
        PlantSpec::Rigid(axis) => (DriveParams::from_axis(axis), Some(*axis)),
        PlantSpec::ForceDrive(f) => (
            DriveParams::force_drive(
                f.drive_gain_n_per_v,
                f.drive_mass_kg,
                f.friction,
                f.mass_kg,
                f.external_force_n,
            ),
            None,
        ),
    };
    if let Some(tf) = &fx.table_friction {
        drive.table_friction = *tf;
    }
    if let Some(m) = drive.motor_friction.as_mut() {
        m.asymmetry = fx.motor_friction.asymmetry;
        m.dwell = fx.motor_friction.dwell;
        m.memory_lag_s = fx.motor_friction.memory_lag_s;
    } else if fx.motor_friction.asymmetry != 0.0
        || fx.motor_friction.dwell.is_some()
        || fx.motor_friction.memory_lag_s.is_some()
    {
        return Err(ConfigError::new(
            "effects.motor_friction",
            "modifiers",
            "none: this plant has no motor-shaft friction (use the table friction map)",
        ));
    }
    for (k, pf) in fx.position_friction.iter().enumerate() {
        let target = match side(&format!("effects.position_friction[{k}].side"), &pf.side)? {
            Side::Motor => &mut drive.motor_modulation,
            Side::Table => &mut drive.table_modulation,
        };
        modulation(&pf.terms, target)?;
    }
    match (&fx.backlash, &fx.compliance) {
        (None, None) => {}
        (b, c) => {
            let (k, damping) = match (b, c) {
                (_, Some(c)) => (c.stiffness_n_per_m, c.damping_n_s_per_m),
                (Some(b), None) => (b.contact_stiffness_n_per_m, b.damping_n_s_per_m),
                (None, None) => (1.0, 0.0),
            };
            drive.n_links = 1;
            drive.links[0] = Link {
                stiffness_n_per_m: k,
                damping_n_s_per_m: damping,
                backlash_m: b.as_ref().map_or(0.0, |b| b.width_m),
            };
            if let Some(ka) = c.as_ref().and_then(|c| c.axial_stiffness_n_per_m) {
                drive.n_links = 2;
                drive.links[1] = Link {
                    stiffness_n_per_m: ka,
                    damping_n_s_per_m: c.as_ref().map_or(0.0, |c| c.axial_damping_n_s_per_m),
                    backlash_m: 0.0,
                };
            }
        }
    }
    drive.amplifier = fx.amplifier;
    let controller = match &sys.controller {
        ControllerSpec::Fpga(p) => ControllerKind::Fpga {
            pid: p.to_core().map_err(|e| e.within("controller"))?,
            output: sys.output_stage,
        },
        ControllerSpec::Cascade(c) => ControllerKind::Cascade(*c),
    };
    let e = fx.encoder_errors.as_ref();
    let sensors = Sensors {
        encoder: Encoder {
            count_m: sys.encoder.count_m,
        },
        side: side("encoder.side", &sys.encoder.side)?,
        cyclic_amplitude_m: e.map_or(0.0, |e| e.cyclic_amplitude_m),
        cyclic_period_m: e.map_or(2e-5, |e| e.cyclic_period_m),
        cyclic_phase_rad: e.map_or(0.0, |e| e.cyclic_phase_rad),
        noise_std_m: e.map_or(0.0, |e| e.noise_std_m),
        delay_samples: fx.sensor_delay_samples,
        interferometer: fx.interferometer,
    };
    let stochastic = match &fx.stochastic {
        None => None,
        Some(st) => Some(StochasticFriction {
            level_spread: st.level_spread,
            distribution: match st.distribution.as_str() {
                "normal" => SpreadDistribution::Normal,
                "lognormal" => SpreadDistribution::LogNormal,
                "uniform" => SpreadDistribution::Uniform,
                other => {
                    return Err(ConfigError::new(
                        "effects.stochastic.distribution",
                        format!("{other:?}"),
                        "one of 'normal', 'lognormal', 'uniform'",
                    ))
                }
            },
            within_spread: st.within_spread,
            correlation_time_s: st.correlation_time_s,
        }),
    };
    let cfg = ExtendedConfig {
        drive,
        axis,
        controller,
        sensors,
        computation_delay_samples: fx.computation_delay_samples,
        jitter_s: fx.jitter_s,
        stochastic,
        seed,
        integrator: sys.integrator,
        initial_position_m,
        initial_flank: fx.backlash.as_ref().map_or(0.0, |b| b.initial_flank),
    };
    cfg.validate()?;
    Ok(cfg)
}
