//! Physical parameters of the axis, in SI units with units in the names. Each field's doc
//! states its valid range; `validate()` enforces exactly those ranges.
use crate::error::{check_positive, check_range, ConfigError};

/// DC motor (armature circuit and rotor).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motor {
    /// Terminal resistance R, Ω, in (0, 1e3].
    pub resistance_ohm: f64,
    /// Rotor inductance L, H, in (0, 1]. Unused when `quasi_static_current`.
    pub inductance_h: f64,
    /// Torque constant k_t, N·m/A, in (0, 10].
    pub torque_constant_nm_per_a: f64,
    /// Back-EMF constant k_e, V·s/rad, in (0, 10].
    pub back_emf_v_s_per_rad: f64,
    /// Rotor inertia J_m, kg·m², in (0, 1].
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
    /// Stribeck velocity ωs, rad/s, in (0, 1e5].
    pub stribeck_velocity_rad_per_s: f64,
    /// Stribeck exponent δ, in [0.5, 4].
    pub stribeck_exponent: f64,
}

/// Gearhead between motor and screw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gearhead {
    /// Reduction ratio N (motor turns per output turn), in [1, 1e4].
    pub ratio: f64,
    /// Efficiency η_g, in (0, 1].
    pub efficiency: f64,
}

/// Ball screw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BallScrew {
    /// Lead P, m per screw revolution, in (0, 0.1].
    pub lead_m: f64,
    /// Efficiency η_s, in (0, 1].
    pub efficiency: f64,
    /// Screw shaft inertia J_s, kg·m², in [0, 1].
    pub inertia_kg_m2: f64,
}

/// The moving table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Table {
    /// Moving mass m, kg, in (0, 1e4].
    pub mass_kg: f64,
    /// Constant external force opposing +x, N, in [−1e4, 1e4].
    pub external_force_n: f64,
}

/// Dahl friction on the mechanical (table) side:
/// `dF/dt = σ·v·|1 − F/Fc·sgn v|^n·sgn(1 − F/Fc·sgn v)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DahlFriction {
    /// Coulomb force Fc, N, in (0, 1e5].
    pub coulomb_force_n: f64,
    /// Rest stiffness σ (slope of force vs displacement at F = 0), N/m, in (0, 1e12].
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
        check_positive("resistance_ohm", self.resistance_ohm, 1e3)?;
        check_positive("inductance_h", self.inductance_h, 1.0)?;
        check_positive(
            "torque_constant_nm_per_a",
            self.torque_constant_nm_per_a,
            10.0,
        )?;
        check_positive("back_emf_v_s_per_rad", self.back_emf_v_s_per_rad, 10.0)?;
        check_positive("rotor_inertia_kg_m2", self.rotor_inertia_kg_m2, 1.0)
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
        check_positive(
            "stribeck_velocity_rad_per_s",
            self.stribeck_velocity_rad_per_s,
            1e5,
        )?;
        check_range("stribeck_exponent", self.stribeck_exponent, 0.5, 4.0)
    }
}

impl Gearhead {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("ratio", self.ratio, 1.0, 1e4)?;
        check_positive("efficiency", self.efficiency, 1.0)
    }
}

impl BallScrew {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("lead_m", self.lead_m, 0.1)?;
        check_positive("efficiency", self.efficiency, 1.0)?;
        check_range("inertia_kg_m2", self.inertia_kg_m2, 0.0, 1.0)
    }
}

impl Table {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("mass_kg", self.mass_kg, 1e4)?;
        check_range("external_force_n", self.external_force_n, -1e4, 1e4)
    }
}

impl DahlFriction {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("coulomb_force_n", self.coulomb_force_n, 1e5)?;
        check_positive("stiffness_n_per_m", self.stiffness_n_per_m, 1e12)?;
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
