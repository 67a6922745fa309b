//! Physical parameters of the axis, in SI units with units in the names. Each field's doc
//! states its valid range; `validate()` enforces exactly those ranges.
use crate::error::{check_positive, check_range, ConfigError};

/// Smallest motor terminal resistance, Ω (see [`Motor::resistance_ohm`]).
pub const MIN_RESISTANCE_OHM: f64 = 1e-3;
/// Smallest motor inductance, H (see [`Motor::inductance_h`]).
pub const MIN_INDUCTANCE_H: f64 = 1e-9;
/// Smallest rotor inertia, kg·m² (see [`Motor::rotor_inertia_kg_m2`]).
pub const MIN_ROTOR_INERTIA_KG_M2: f64 = 1e-12;
/// Smallest moving mass of a table or a drive side, kg (see [`Table::mass_kg`]).
pub const MIN_MASS_KG: f64 = 1e-6;
/// Smallest efficiency of a gearhead or a screw (see [`Gearhead::efficiency`]).
pub const MIN_EFFICIENCY: f64 = 1e-3;
/// Smallest screw lead, m (see [`BallScrew::lead_m`]).
pub const MIN_LEAD_M: f64 = 1e-5;
/// Smallest Stribeck velocity of the motor-shaft friction, rad/s (see
/// [`StribeckFriction::stribeck_velocity_rad_per_s`]).
pub const MIN_STRIBECK_VELOCITY_RAD_PER_S: f64 = 1e-3;
/// Smallest Coulomb force of a dynamic friction model (Dahl, LuGre, GMS), N (see
/// [`DahlFriction::coulomb_force_n`]).
pub const MIN_COULOMB_FORCE_N: f64 = 1e-6;
/// Smallest presliding (bristle, element) stiffness of a dynamic friction model, N/m (see
/// [`DahlFriction::stiffness_n_per_m`]).
pub const MIN_PRESLIDING_STIFFNESS_N_PER_M: f64 = 1e-3;

/// DC motor (armature circuit and rotor).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motor {
    /// Terminal resistance R, Ω, in [1e-3, 1e3]. The lower bound, 1 mΩ, is below the winding
    /// and brush resistance of any DC motor (large servo motors have tens of mΩ); it keeps
    /// the stalled current u/R and the electrical rate R/L finite (a resistance of 5e-324 Ω
    /// makes u/R infinite and the current NaN).
    pub resistance_ohm: f64,
    /// Rotor inductance L, H, in [1e-9, 1]. The lower bound, 1 nH, is the inductance of about
    /// a millimetre of wire, far below any winding; it keeps di/dt = (u − R·i − k_e·ω)/L
    /// finite. Unused when `quasi_static_current`.
    pub inductance_h: f64,
    /// Torque constant k_t, N·m/A, in (0, 10].
    pub torque_constant_nm_per_a: f64,
    /// Back-EMF constant k_e, V·s/rad, in (0, 10].
    pub back_emf_v_s_per_rad: f64,
    /// Rotor inertia J_m, kg·m², in [1e-12, 1]. The lower bound is a hundredth of the
    /// smallest micromotor rotors (about 1e-10 kg·m²); with a compliant drive train the rotor
    /// is a mass of its own, and a subnormal inertia made its state NaN.
    pub rotor_inertia_kg_m2: f64,
    /// Treat the electrical pole as infinitely fast: i = (u − k_e·ω)/R.
    pub quasi_static_current: bool,
}

/// Stribeck friction torque on the motor shaft:
/// `T(ω) = [Tc + (Ts − Tc)·exp(−|ω/ωs|^δ)]·sgn ω + b·ω`, with true stiction up to Ts at ω = 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StribeckFriction {
    /// Static (breakaway) torque Ts, N·m, in [Tc, 10].
    pub static_torque_nm: f64,
    /// Coulomb torque Tc, N·m, in [0, 10].
    pub coulomb_torque_nm: f64,
    /// Viscous coefficient b, N·m·s/rad, in [0, 1].
    pub viscous_nm_s_per_rad: f64,
    /// Stribeck velocity ωs, rad/s, in [1e-3, 1e5]. The lower bound, a milliradian per
    /// second at the motor shaft (a sixth of a revolution per hour; 17 nm/s at the table of
    /// the seed axis), is below any measured Stribeck velocity (micrometres to centimetres
    /// per second at the contact). Far below it the drop from `T_s` to `T_c` becomes a step
    /// that the stick/slip logic resolves only by switching modes at ever shorter intervals
    /// (3.8e-20 rad/s: a million events in 80 ms).
    pub stribeck_velocity_rad_per_s: f64,
    /// Stribeck exponent δ, in [0.5, 4].
    pub stribeck_exponent: f64,
}

/// Gearhead between motor and screw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gearhead {
    /// Reduction ratio N (motor turns per output turn), in [1, 1e4].
    pub ratio: f64,
    /// Efficiency η_g, in [1e-3, 1] (below 0.1 % nothing is transmitted; the holding torque
    /// divides by η).
    pub efficiency: f64,
}

/// Ball screw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BallScrew {
    /// Lead P, m per screw revolution, in [1e-5, 0.1] (10 µm per revolution is finer than
    /// any screw; the transmission P/(2πN) divides the reflected inertias).
    pub lead_m: f64,
    /// Efficiency η_s, in [1e-3, 1], as the gearhead's.
    pub efficiency: f64,
    /// Screw shaft inertia J_s, kg·m², in [0, 1] (at least 1e-12 when the screw is a mass of
    /// its own, in a three-mass drive train).
    pub inertia_kg_m2: f64,
}

/// The moving table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Table {
    /// Moving mass m, kg, in [1e-6, 1e4]. A milligram is below any moving table; a
    /// subnormal mass made the acceleration infinite.
    pub mass_kg: f64,
    /// Constant external force opposing +x, N, in [−1e4, 1e4].
    pub external_force_n: f64,
}

/// Dahl friction on the mechanical (table) side:
/// `dF/dt = σ·v·|1 − F/Fc·sgn v|^n·sgn(1 − F/Fc·sgn v)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DahlFriction {
    /// Coulomb force Fc, N, in [1e-6, 1e5]. The lower bound, a micronewton (the weight of
    /// 0.1 mg), is below the friction of any sliding or rolling guide; far below it the
    /// Dahl law's `1 − F/Fc` cannot be resolved (1e-30 N: the slip direction would change
    /// at picosecond intervals and the run would not end).
    pub coulomb_force_n: f64,
    /// Rest stiffness σ (slope of force vs displacement at F = 0), N/m, in [1e-3, 1e12]. The
    /// lower bound, 1 mN/m, is decades below any contact stiffness (a 1 N friction force
    /// would need a kilometre of presliding); it keeps the tolerance of the friction state,
    /// σ times the position tolerance, a normal number.
    pub stiffness_n_per_m: f64,
    /// Shape exponent n, in [0.5, 4].
    pub exponent: f64,
}

/// The whole rigid axis: motor → gearhead → screw → table, friction on both sides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisParams {
    /// Motor.
    pub motor: Motor,
    /// Friction on the motor shaft.
    pub motor_friction: StribeckFriction,
    /// Gearhead.
    pub gearhead: Gearhead,
    /// Ball screw.
    pub screw: BallScrew,
    /// Table.
    pub table: Table,
    /// Friction on the table side.
    pub dahl: DahlFriction,
}

impl Motor {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range(
            "resistance_ohm",
            self.resistance_ohm,
            MIN_RESISTANCE_OHM,
            1e3,
        )?;
        check_range("inductance_h", self.inductance_h, MIN_INDUCTANCE_H, 1.0)?;
        check_positive(
            "torque_constant_nm_per_a",
            self.torque_constant_nm_per_a,
            10.0,
        )?;
        check_positive("back_emf_v_s_per_rad", self.back_emf_v_s_per_rad, 10.0)?;
        check_range(
            "rotor_inertia_kg_m2",
            self.rotor_inertia_kg_m2,
            MIN_ROTOR_INERTIA_KG_M2,
            1.0,
        )
    }
}

impl StribeckFriction {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("coulomb_torque_nm", self.coulomb_torque_nm, 0.0, 10.0)?;
        check_range(
            "static_torque_nm",
            self.static_torque_nm,
            self.coulomb_torque_nm,
            10.0,
        )?;
        check_range("viscous_nm_s_per_rad", self.viscous_nm_s_per_rad, 0.0, 1.0)?;
        check_range(
            "stribeck_velocity_rad_per_s",
            self.stribeck_velocity_rad_per_s,
            MIN_STRIBECK_VELOCITY_RAD_PER_S,
            1e5,
        )?;
        check_range("stribeck_exponent", self.stribeck_exponent, 0.5, 4.0)
    }
}

impl Gearhead {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("ratio", self.ratio, 1.0, 1e4)?;
        check_range("efficiency", self.efficiency, MIN_EFFICIENCY, 1.0)
    }
}

impl BallScrew {
    /// Transmission r = P/(2πN) of this screw behind a gearhead of ratio N: table metres per
    /// motor radian.
    #[inline]
    pub fn metres_per_motor_radian(&self, gearhead: &Gearhead) -> f64 {
        self.lead_m / (2.0 * std::f64::consts::PI * gearhead.ratio)
    }

    /// 2π/P: screw radians per table metre.
    #[inline]
    pub fn screw_radians_per_metre(&self) -> f64 {
        2.0 * std::f64::consts::PI / self.lead_m
    }

    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("lead_m", self.lead_m, MIN_LEAD_M, 0.1)?;
        check_range("efficiency", self.efficiency, MIN_EFFICIENCY, 1.0)?;
        check_range("inertia_kg_m2", self.inertia_kg_m2, 0.0, 1.0)
    }
}

impl Table {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("mass_kg", self.mass_kg, MIN_MASS_KG, 1e4)?;
        check_range("external_force_n", self.external_force_n, -1e4, 1e4)
    }
}

impl DahlFriction {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range(
            "coulomb_force_n",
            self.coulomb_force_n,
            MIN_COULOMB_FORCE_N,
            1e5,
        )?;
        check_range(
            "stiffness_n_per_m",
            self.stiffness_n_per_m,
            MIN_PRESLIDING_STIFFNESS_N_PER_M,
            1e12,
        )?;
        check_range("exponent", self.exponent, 0.5, 4.0)
    }
}

impl AxisParams {
    /// The same axis with every friction level (static and Coulomb torque of the motor's
    /// Stribeck map, Coulomb force of the Dahl model) multiplied by `scale`; viscous terms,
    /// the Stribeck velocity and the Dahl stiffness are unchanged. This is exactly what the
    /// component plant's friction level scale does to the same axis.
    pub fn with_friction_scale(&self, scale: f64) -> Self {
        if scale == 1.0 {
            return *self;
        }
        let mut p = *self;
        p.motor_friction.static_torque_nm *= scale;
        p.motor_friction.coulomb_torque_nm *= scale;
        p.dahl.coulomb_force_n *= scale;
        p
    }

    /// Validate every block; the error names the block and the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.motor.validate().map_err(|e| e.within("motor"))?;
        self.motor_friction
            .validate()
            .map_err(|e| e.within("motor_friction"))?;
        self.gearhead.validate().map_err(|e| e.within("gearhead"))?;
        self.screw.validate().map_err(|e| e.within("screw"))?;
        self.table.validate().map_err(|e| e.within("table"))?;
        self.dahl.validate().map_err(|e| e.within("dahl"))
    }
}
