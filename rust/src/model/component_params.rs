//! Parameters of the component plant: the drive train as a chain of masses with friction
//! components on each side, drive electronics, and the effect modifiers. SI units, units in
//! the names; each field's doc gives its valid range and `validate()` enforces exactly that.
use super::params::{
    AxisParams, BallScrew, DahlFriction, Gearhead, Motor, MIN_COULOMB_FORCE_N, MIN_MASS_KG,
    MIN_PRESLIDING_STIFFNESS_N_PER_M, MIN_ROTOR_INERTIA_KG_M2,
};
use crate::error::{check_positive, check_range, ConfigError};

/// Most Maxwell-slip elements of a GMS model.
pub const MAX_GMS_ELEMENTS: usize = 8;
/// Most position-modulation terms per side.
pub const MAX_MODULATION_TERMS: usize = 32;

/// Which side of the drive train a component acts on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The motor shaft (reflected to the table: forces in N, velocities in m/s at the table).
    Motor,
    /// The table (the last mass of the chain).
    Table,
}

/// Rising static friction with dwell time: `Fs(θ) = Fs + ΔFs·θ/(θ + γ)` (Armstrong's form,
/// written so that `ΔFs = 0` is the nominal map). Two laws of the dwell clock θ:
///
/// - breakaway only (`slip_distance_m = None`): θ is the time the side has been stuck (reset
///   when it sticks, frozen while it slides) and raises only the breakaway capacity;
/// - contact ageing (`slip_distance_m = Some(D_c)`): θ is the contact age of Ruina's ageing
///   law, `θ̇ = 1 − |v|·θ/D_c` (the dwell time at rest, relaxing to `D_c/|v|` over a slip of
///   about `D_c`, never reset), and `Fs(θ)` is also the static level of the Stribeck term
///   while sliding: a slow creep keeps the level raised, a fast slide forgets it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DwellStatic {
    /// Rise of the static force for an infinite dwell ΔFs, N, in [0, 1e4].
    pub rise_n: f64,
    /// Dwell time constant γ, s, in (0, 1e3].
    pub time_constant_s: f64,
    /// Characteristic slip distance `D_c` of the contact-ageing law, m, in [1e-9, 1e-2]
    /// (`None`: breakaway only).
    pub slip_distance_m: Option<f64>,
}

/// A static friction map with true stiction, at the table in force units:
/// `F(v) = (1 ± a)·[Fc + (Fs − Fc)·exp(−|v_m/vs|^δ)]·sgn v + (1 ± a_v)·Fv·v` (upper signs for
/// v > 0; asymmetries `a` of the levels and `a_v` of the viscous term). `v_m` is the velocity itself or, with
/// frictional memory, the velocity lagged by a first-order filter of time constant τ_L.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticMap {
    /// Static (breakaway) force Fs, N, in [Fc, 1e5].
    pub static_force_n: f64,
    /// Coulomb force Fc, N, in [0, 1e5].
    pub coulomb_force_n: f64,
    /// Viscous coefficient Fv, N·s/m, in [0, 1e7].
    pub viscous_n_s_per_m: f64,
    /// Stribeck velocity vs, m/s, in (0, 10].
    pub stribeck_velocity_m_per_s: f64,
    /// Stribeck exponent δ, in [0.5, 4].
    pub stribeck_exponent: f64,
    /// Direction asymmetry a of the levels Fs, Fc, in [−0.9, 0.9] (0: symmetric).
    pub asymmetry: f64,
    /// Direction asymmetry of the viscous coefficient, in [−0.9, 0.9]: `Fv·(1 ± a_v)`.
    pub viscous_asymmetry: f64,
    /// Rising static friction with dwell time (off: `None`).
    pub dwell: Option<DwellStatic>,
    /// Frictional memory: time constant τ_L of the lag of the Stribeck term behind the
    /// velocity, s, in (0, 1] (off: `None`).
    pub memory_lag_s: Option<f64>,
}

/// Dahl friction on the table, with a direction asymmetry of its Coulomb level:
/// `dF/dt = σ·v·|1 − F·d/Fc_d|^n·sgn(1 − F·d/Fc_d)` with `Fc_d = (1 + a·d)·Fc` and `d` the
/// direction of sliding (`sgn v`; the slip segment's direction in the plant).
///
/// The direction is the sign of the velocity, not of the force or the deflection: the
/// level only sets where the force saturates in the direction the table moves, so steady
/// sliding gives exactly `Fc·(1 + a)` in + and `−Fc·(1 − a)` in −. The force is a state and
/// stays continuous, and the rate `σ·v·(…)` vanishes at v = 0 where `d` switches, so the
/// rate is continuous in v too. The law stays passive for every `a` in the range: with the
/// spring energy `V = F²/(2σ)` as storage, the power dissipated is
/// `F·v − V̇ = |v|·Fc_d·(1 − q)·(1 − |q|^n·sgn q) ≥ 0` (q = 1 − F·d/Fc_d; both factors have
/// the sign of 1 − q, and `Fc_d ≥ 0.1·Fc > 0`), so over a closed displacement cycle that
/// returns to the same force the friction absorbs energy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableDahl {
    /// The law: Coulomb level Fc, rest stiffness σ, shape exponent n.
    pub law: DahlFriction,
    /// Direction asymmetry a of the Coulomb level, in [−0.9, 0.9] (0: the symmetric law,
    /// bit for bit).
    pub asymmetry: f64,
}

/// Maxwell-slip / GMS friction: `N` parallel elasto-slide elements, element `i` with stiffness
/// `k_i` and slip force `ν_i·s(v)` where `s(v) = (1 + a·d)·[Fc + (Fs − Fc)·exp(−(v/vs)²)]`,
/// `d` the direction of sliding (as [`TableDahl`]) and `Σ ν_i = 1`. Each element's deflection
/// follows the motion exactly (`ż_i = v`) while `sgn v · k_i z_i ≤ β·ν_i s(v)` (β = 0.9),
/// then yields smoothly and saturates at its slip force (an elasto-plastic element, Dupont et
/// al. 2002, per Maxwell-slip branch). Steady sliding gives `s(v)·d + σ2·v`; each element
/// stays passive for any positive slip force (storage `k_i·z_i²/2`, dissipation
/// `k_i·|v|·(z_i·sgn v)·α ≥ 0` where α > 0 only while `z_i·sgn v > 0`), so the asymmetry
/// keeps the law passive, and the rate `v·(1 − α)` vanishes at v = 0 where `d` switches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gms {
    /// Number of elements, in [1, 8].
    pub n_elements: usize,
    /// Element stiffnesses k_i, N/m, each in [1e-3, 1e12] (the lower bound as for
    /// [`DahlFriction::stiffness_n_per_m`]).
    pub stiffness_n_per_m: [f64; MAX_GMS_ELEMENTS],
    /// Element weights ν_i, each in (0, 1], summing to 1 (± 1e-9).
    pub weights: [f64; MAX_GMS_ELEMENTS],
    /// Sliding (Coulomb) force Fc, N, in [1e-6, 1e5] (the lower bound as for
    /// [`DahlFriction::coulomb_force_n`]).
    pub coulomb_force_n: f64,
    /// Static force Fs, N, in [Fc, 1e5].
    pub static_force_n: f64,
    /// Stribeck velocity vs, m/s, in (0, 10].
    pub stribeck_velocity_m_per_s: f64,
    /// Viscous coefficient σ2, N·s/m, in [0, 1e7].
    pub viscous_n_s_per_m: f64,
    /// Direction asymmetry a of the levels Fc, Fs, in [−0.9, 0.9] (0: symmetric).
    pub asymmetry: f64,
}

/// LuGre friction: `ż = v − σ0·|v|·z/g(v)`,
/// `g(v) = (1 + a·d)·[Fc + (Fs − Fc)·exp(−(v/vs)²)]` with `d` the direction of sliding (as
/// [`TableDahl`]), `F = σ0·z + σ1·ż + σ2·v`. Steady sliding gives `g(v)·d + σ2·v`. The
/// asymmetry only changes the positive function g, so the bristle map v → σ0·z stays passive
/// (storage `σ0·z²/2`, `σ0·z·v − V̇ = σ0²·|v|·z²/g ≥ 0`), and g enters ż only through
/// `|v|/g`, which vanishes at v = 0 where `d` switches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LuGre {
    /// Bristle stiffness σ0, N/m, in [1e-3, 1e12] (the lower bound as for
    /// [`DahlFriction::stiffness_n_per_m`]).
    pub stiffness_n_per_m: f64,
    /// Bristle damping σ1, N·s/m, in [0, 1e7].
    pub damping_n_s_per_m: f64,
    /// Viscous coefficient σ2, N·s/m, in [0, 1e7].
    pub viscous_n_s_per_m: f64,
    /// Coulomb force Fc, N, in [1e-6, 1e5] (the lower bound as for
    /// [`DahlFriction::coulomb_force_n`]).
    pub coulomb_force_n: f64,
    /// Static force Fs, N, in [Fc, 1e5].
    pub static_force_n: f64,
    /// Stribeck velocity vs, m/s, in (0, 10].
    pub stribeck_velocity_m_per_s: f64,
    /// Direction asymmetry a of the levels Fc, Fs, in [−0.9, 0.9] (0: symmetric).
    pub asymmetry: f64,
}

/// The friction model acting on the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TableFriction {
    /// No table friction.
    None,
    /// A static map with true stiction (Coulomb + viscous, Stribeck).
    Static(StaticMap),
    /// Dahl (presliding spring with rate-independent hysteresis).
    Dahl(TableDahl),
    /// LuGre.
    LuGre(LuGre),
    /// Generalized Maxwell-slip.
    Gms(Gms),
}

/// A spatial modulation of a side's friction levels,
/// `1 + Σ_k a_k·cos(κ_k·x + φ_k)` (amplitudes relative to the nominal level).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Modulation {
    /// Number of terms in use, in [0, 32].
    pub n_terms: usize,
    /// Relative amplitudes a_k, each in [0, 0.9]; Σ a_k ≤ 0.9 (the factor stays positive).
    pub amplitude: [f64; MAX_MODULATION_TERMS],
    /// Wavenumbers κ_k = 2π/λ_k, rad/m, each in (0, 1e9].
    pub wavenumber_rad_per_m: [f64; MAX_MODULATION_TERMS],
    /// Phases φ_k, rad, finite.
    pub phase_rad: [f64; MAX_MODULATION_TERMS],
}

impl Default for Modulation {
    fn default() -> Self {
        Self {
            n_terms: 0,
            amplitude: [0.0; MAX_MODULATION_TERMS],
            wavenumber_rad_per_m: [1.0; MAX_MODULATION_TERMS],
            phase_rad: [0.0; MAX_MODULATION_TERMS],
        }
    }
}

/// A connection between two neighbouring masses of the chain: a spring and damper, with an
/// optional dead band (backlash) of total width `backlash_m` inside which no force passes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Link {
    /// Stiffness (contact stiffness with backlash), N/m at the table, in (0, 1e12].
    pub stiffness_n_per_m: f64,
    /// Damping, N·s/m at the table, in [0, 1e8].
    pub damping_n_s_per_m: f64,
    /// Total dead-band width, m at the table, in [0, 1e-2].
    pub backlash_m: f64,
}

/// The actuator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Actuator {
    /// A DC motor through gearhead and ball screw (the seed axis). Masses: motor rotor
    /// (`η·J_m/r²`), screw (`η_s·J_s·(2π/P)²`), table.
    DcMotor {
        /// Motor.
        motor: Motor,
        /// Gearhead.
        gearhead: Gearhead,
        /// Ball screw.
        screw: BallScrew,
    },
    /// A force-controlled drive: force = gain · command (EMPS). Masses: drive side
    /// `drive_mass_kg`, table.
    ForceDrive {
        /// Drive gain, N/V, in (0, 1e5].
        gain_n_per_v: f64,
        /// Mass on the drive side of the first link, kg, in [0, 1e4] (lumped with the table
        /// when the chain is rigid; at least 1e-6 with a link, as [`Table::mass_kg`]).
        ///
        /// [`Table::mass_kg`]: crate::model::Table::mass_kg
        drive_mass_kg: f64,
    },
}

/// The power amplifier between the DAC and the motor: first-order bandwidth and slew limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Amplifier {
    /// −3 dB bandwidth, Hz, in (0, 1e7].
    pub bandwidth_hz: f64,
    /// Slew-rate limit, V/s, in (0, 1e12] (`f64::INFINITY` is not allowed; use 1e12).
    pub slew_v_per_s: f64,
}

/// The whole component plant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriveParams {
    /// The actuator.
    pub actuator: Actuator,
    /// Static friction map on the motor shaft (DC motor only), reflected to the table.
    pub motor_friction: Option<StaticMap>,
    /// Friction on the table.
    pub table_friction: TableFriction,
    /// Table (moving) mass, kg, in [1e-6, 1e4] (the lower bound as for
    /// [`Table::mass_kg`](crate::model::Table::mass_kg)).
    pub table_mass_kg: f64,
    /// Constant external force opposing +x, N, in [−1e4, 1e4].
    pub external_force_n: f64,
    /// Links of the chain: none (rigid), one (two-mass: drive | table side) or two
    /// (three-mass: motor | screw | table; DC motor with screw inertia > 0 only).
    pub n_links: usize,
    /// The links, first `n_links` used.
    pub links: [Link; 2],
    /// Spatial modulation of the motor-side friction levels (position of the motor side).
    pub motor_modulation: Modulation,
    /// Spatial modulation of the table friction levels (table position).
    pub table_modulation: Modulation,
    /// Amplifier dynamics (off: `None`, the voltage follows the command instantly).
    pub amplifier: Option<Amplifier>,
}

impl DwellStatic {
    fn validate(&self) -> Result<(), ConfigError> {
        check_range("rise_n", self.rise_n, 0.0, 1e4)?;
        check_positive("time_constant_s", self.time_constant_s, 1e3)?;
        if let Some(dc) = self.slip_distance_m {
            check_range("slip_distance_m", dc, 1e-9, 1e-2)?;
        }
        Ok(())
    }
}

impl StaticMap {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("coulomb_force_n", self.coulomb_force_n, 0.0, 1e5)?;
        check_range(
            "static_force_n",
            self.static_force_n,
            self.coulomb_force_n,
            1e5,
        )?;
        check_range("viscous_n_s_per_m", self.viscous_n_s_per_m, 0.0, 1e7)?;
        check_positive(
            "stribeck_velocity_m_per_s",
            self.stribeck_velocity_m_per_s,
            10.0,
        )?;
        check_range("stribeck_exponent", self.stribeck_exponent, 0.5, 4.0)?;
        check_range("asymmetry", self.asymmetry, -0.9, 0.9)?;
        check_range("viscous_asymmetry", self.viscous_asymmetry, -0.9, 0.9)?;
        if let Some(d) = &self.dwell {
            d.validate().map_err(|e| e.within("dwell"))?;
        }
        if let Some(t) = self.memory_lag_s {
            check_positive("memory_lag_s", t, 1.0)?;
        }
        Ok(())
    }

    /// The motor-shaft Stribeck map of the seed axis reflected to the table through
    /// `r = P/(2πN)` and efficiency `η`: forces `η·T/r`, velocity `ω·r`, viscous `η·b/r²`.
    pub fn from_motor_stribeck(p: &AxisParams) -> Self {
        let r = p.screw.metres_per_motor_radian(&p.gearhead);
        let eta = p.gearhead.efficiency * p.screw.efficiency;
        let f = &p.motor_friction;
        Self {
            static_force_n: eta * f.static_torque_nm / r,
            coulomb_force_n: eta * f.coulomb_torque_nm / r,
            viscous_n_s_per_m: eta * f.viscous_nm_s_per_rad / (r * r),
            stribeck_velocity_m_per_s: f.stribeck_velocity_rad_per_s * r,
            stribeck_exponent: f.stribeck_exponent,
            asymmetry: 0.0,
            viscous_asymmetry: 0.0,
            dwell: None,
            memory_lag_s: None,
        }
    }
}

impl Gms {
    fn validate(&self) -> Result<(), ConfigError> {
        if self.n_elements == 0 || self.n_elements > MAX_GMS_ELEMENTS {
            return Err(ConfigError::new(
                "n_elements",
                self.n_elements,
                format!("an integer in [1, {MAX_GMS_ELEMENTS}]"),
            ));
        }
        let mut sum = 0.0;
        for i in 0..self.n_elements {
            check_range(
                &format!("stiffness_n_per_m[{i}]"),
                self.stiffness_n_per_m[i],
                MIN_PRESLIDING_STIFFNESS_N_PER_M,
                1e12,
            )?;
            check_positive(&format!("weights[{i}]"), self.weights[i], 1.0)?;
            sum += self.weights[i];
        }
        if (sum - 1.0).abs() > 1e-9 {
            return Err(ConfigError::new("weights", sum, "weights summing to 1"));
        }
        check_stribeck_curve(
            self.coulomb_force_n,
            self.static_force_n,
            self.stribeck_velocity_m_per_s,
        )?;
        check_range("viscous_n_s_per_m", self.viscous_n_s_per_m, 0.0, 1e7)?;
        check_range("asymmetry", self.asymmetry, -0.9, 0.9)
    }
}

impl TableDahl {
    /// Validate the law and the asymmetry against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.law.validate()?;
        check_range("asymmetry", self.asymmetry, -0.9, 0.9)
    }
}

/// The Stribeck curve of a dynamic model: Fc in [1e-6, 1e5], Fs in [Fc, 1e5], vs in (0, 10].
fn check_stribeck_curve(fc: f64, fs: f64, vs: f64) -> Result<(), ConfigError> {
    check_range("coulomb_force_n", fc, MIN_COULOMB_FORCE_N, 1e5)?;
    check_range("static_force_n", fs, fc, 1e5)?;
    check_positive("stribeck_velocity_m_per_s", vs, 10.0)
}

impl LuGre {
    fn validate(&self) -> Result<(), ConfigError> {
        check_range(
            "stiffness_n_per_m",
            self.stiffness_n_per_m,
            MIN_PRESLIDING_STIFFNESS_N_PER_M,
            1e12,
        )?;
        check_range("damping_n_s_per_m", self.damping_n_s_per_m, 0.0, 1e7)?;
        check_range("viscous_n_s_per_m", self.viscous_n_s_per_m, 0.0, 1e7)?;
        check_stribeck_curve(
            self.coulomb_force_n,
            self.static_force_n,
            self.stribeck_velocity_m_per_s,
        )?;
        check_range("asymmetry", self.asymmetry, -0.9, 0.9)
    }
}

impl TableFriction {
    /// Validate the parameters of the model (none: nothing to check).
    pub fn validate(&self) -> Result<(), ConfigError> {
        match self {
            Self::None => Ok(()),
            Self::Static(m) => m.validate(),
            Self::Dahl(d) => d.validate(),
            Self::LuGre(l) => l.validate(),
            Self::Gms(g) => g.validate(),
        }
    }
}

impl Modulation {
    /// Validate the terms.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.n_terms > MAX_MODULATION_TERMS {
            return Err(ConfigError::new(
                "n_terms",
                self.n_terms,
                format!("an integer in [0, {MAX_MODULATION_TERMS}]"),
            ));
        }
        let mut sum = 0.0;
        for k in 0..self.n_terms {
            check_range(&format!("amplitude[{k}]"), self.amplitude[k], 0.0, 0.9)?;
            check_positive(
                &format!("wavenumber_rad_per_m[{k}]"),
                self.wavenumber_rad_per_m[k],
                1e9,
            )?;
            check_range(&format!("phase_rad[{k}]"), self.phase_rad[k], -1e6, 1e6)?;
            sum += self.amplitude[k];
        }
        if sum > 0.9 {
            return Err(ConfigError::new(
                "amplitude",
                sum,
                "relative amplitudes summing to at most 0.9",
            ));
        }
        Ok(())
    }
}

impl Link {
    fn validate(&self) -> Result<(), ConfigError> {
        check_positive("stiffness_n_per_m", self.stiffness_n_per_m, 1e12)?;
        check_range("damping_n_s_per_m", self.damping_n_s_per_m, 0.0, 1e8)?;
        check_range("backlash_m", self.backlash_m, 0.0, 1e-2)
    }
}

impl Amplifier {
    fn validate(&self) -> Result<(), ConfigError> {
        check_positive("bandwidth_hz", self.bandwidth_hz, 1e7)?;
        check_positive("slew_v_per_s", self.slew_v_per_s, 1e12)
    }
}

/// The links of a rigid chain (`n_links = 0`: none is used).
const UNUSED_LINKS: [Link; 2] = [Link {
    stiffness_n_per_m: 1.0,
    damping_n_s_per_m: 0.0,
    backlash_m: 0.0,
}; 2];

impl DriveParams {
    /// The seed axis as a component plant: DC motor, rigid chain, motor Stribeck map, Dahl.
    pub fn from_axis(p: &AxisParams) -> Self {
        Self {
            actuator: Actuator::DcMotor {
                motor: p.motor,
                gearhead: p.gearhead,
                screw: p.screw,
            },
            motor_friction: Some(StaticMap::from_motor_stribeck(p)),
            table_friction: TableFriction::Dahl(TableDahl {
                law: p.dahl,
                asymmetry: 0.0,
            }),
            table_mass_kg: p.table.mass_kg,
            external_force_n: p.table.external_force_n,
            n_links: 0,
            links: UNUSED_LINKS,
            motor_modulation: Modulation::default(),
            table_modulation: Modulation::default(),
            amplifier: None,
        }
    }

    /// A force drive (EMPS) as a component plant: `gain_n_per_v` N/V on a drive-side mass
    /// `drive_mass_kg`, rigid chain, `friction` on the table, no motor friction.
    pub fn force_drive(
        gain_n_per_v: f64,
        drive_mass_kg: f64,
        friction: StaticMap,
        table_mass_kg: f64,
        external_force_n: f64,
    ) -> Self {
        Self {
            actuator: Actuator::ForceDrive {
                gain_n_per_v,
                drive_mass_kg,
            },
            motor_friction: None,
            table_friction: TableFriction::Static(friction),
            table_mass_kg,
            external_force_n,
            n_links: 0,
            links: UNUSED_LINKS,
            motor_modulation: Modulation::default(),
            table_modulation: Modulation::default(),
            amplifier: None,
        }
    }

    /// Validate every component; the error names the component and the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        match &self.actuator {
            Actuator::DcMotor {
                motor,
                gearhead,
                screw,
            } => {
                motor.validate().map_err(|e| e.within("motor"))?;
                gearhead.validate().map_err(|e| e.within("gearhead"))?;
                screw.validate().map_err(|e| e.within("screw"))?;
                if self.n_links == 2 && screw.inertia_kg_m2 < MIN_ROTOR_INERTIA_KG_M2 {
                    return Err(ConfigError::new(
                        "screw.inertia_kg_m2",
                        crate::error::format_value(screw.inertia_kg_m2),
                        format!(
                            "at least {MIN_ROTOR_INERTIA_KG_M2:e} for a three-mass chain (the \
                             screw is a mass of its own)"
                        ),
                    ));
                }
            }
            Actuator::ForceDrive {
                gain_n_per_v,
                drive_mass_kg,
            } => {
                check_positive("drive.gain_n_per_v", *gain_n_per_v, 1e5)?;
                check_range("drive.drive_mass_kg", *drive_mass_kg, 0.0, 1e4)?;
                if self.motor_friction.is_some() {
                    return Err(ConfigError::new(
                        "motor_friction",
                        "a static map",
                        "none for a force drive (put the friction on the table)",
                    ));
                }
                if self.n_links > 1 {
                    return Err(ConfigError::new(
                        "n_links",
                        self.n_links,
                        "0 or 1 for a force drive",
                    ));
                }
                if self.n_links == 1 && *drive_mass_kg < MIN_MASS_KG {
                    return Err(ConfigError::new(
                        "drive.drive_mass_kg",
                        crate::error::format_value(*drive_mass_kg),
                        format!("at least {MIN_MASS_KG:e} with a compliant link"),
                    ));
                }
            }
        }
        if let Some(m) = &self.motor_friction {
            m.validate().map_err(|e| e.within("motor_friction"))?;
        }
        self.table_friction
            .validate()
            .map_err(|e| e.within("table_friction"))?;
        check_range("table_mass_kg", self.table_mass_kg, MIN_MASS_KG, 1e4)?;
        check_range("external_force_n", self.external_force_n, -1e4, 1e4)?;
        if self.n_links > 2 {
            return Err(ConfigError::new("n_links", self.n_links, "0, 1 or 2"));
        }
        for k in 0..self.n_links {
            self.links[k]
                .validate()
                .map_err(|e| e.within(&format!("links[{k}]")))?;
        }
        self.motor_modulation
            .validate()
            .map_err(|e| e.within("motor_modulation"))?;
        self.table_modulation
            .validate()
            .map_err(|e| e.within("table_modulation"))?;
        if let Some(a) = &self.amplifier {
            a.validate().map_err(|e| e.within("amplifier"))?;
        }
        Ok(())
    }
}
