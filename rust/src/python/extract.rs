//! The one mirror of the Python configuration dataclasses: `#[derive(FromPyObject)]` structs
//! read by field name (the field names are the contract) and converted into the core's
//! structs and specs.
use crate::control::{CascadeConfig, OutputStage};
use crate::error::ConfigError as CoreConfigError;
use crate::integrate::IntegratorOptions;
use crate::model::{
    AxisParams, BallScrew, DahlFriction, DwellStatic, Gearhead, Gms, LuGre, Motor, StaticMap,
    StribeckFriction, Table, TableDahl, TableFriction, MAX_GMS_ELEMENTS,
};
use crate::sim::{
    BacklashSpec, ComplianceSpec, ControllerSpec, EffectsSpec, EncoderErrorsSpec, EncoderSpec,
    ForceDriveSpec, FrictionModifiersSpec, FxpSpec, Interferometer, PidSpec, PlantSpec,
    PositionFrictionSpec, StochasticSpec, SystemSpec,
};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::Borrowed;

/// An enum of configuration classes extracted by the Python class name when it is one of
/// its variants' (so that an error inside keeps its field path), else as the first variant
/// that extracts (duck typing); a `TypeError` when none does.
macro_rules! config_enum {
    ($name:ident: $($variant:ident($ty:ty) = $class:literal),+ $(,)?) => {
        impl<'a, 'py> FromPyObject<'a, 'py> for $name {
            type Error = PyErr;

            fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
                let class = obj.get_type().name()?.to_string();
                $(
                    if class == $class {
                        return obj.extract::<$ty>().map(Self::$variant);
                    }
                )+
                $(
                    if let Ok(v) = obj.extract::<$ty>() {
                        return Ok(Self::$variant(v));
                    }
                )+
                Err(PyTypeError::new_err(concat!("expected one of" $(, " ", $class)+)))
            }
        }
    };
}

#[derive(FromPyObject)]
pub(crate) struct PyFxp {
    pub(crate) signed: bool,
    pub(crate) word_bits: u32,
    pub(crate) int_bits: i32,
    pub(crate) rounding: String,
    pub(crate) overflow: String,
}

#[derive(FromPyObject)]
pub(crate) struct PyMotor {
    pub(crate) resistance_ohm: f64,
    pub(crate) inductance_h: f64,
    pub(crate) torque_constant_nm_per_a: f64,
    pub(crate) back_emf_v_s_per_rad: f64,
    pub(crate) rotor_inertia_kg_m2: f64,
    pub(crate) quasi_static_current: bool,
}

#[derive(FromPyObject)]
pub(crate) struct PyStribeck {
    pub(crate) static_torque_nm: f64,
    pub(crate) coulomb_torque_nm: f64,
    pub(crate) viscous_nm_s_per_rad: f64,
    pub(crate) stribeck_velocity_rad_per_s: f64,
    pub(crate) stribeck_exponent: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyGearhead {
    pub(crate) ratio: f64,
    pub(crate) efficiency: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyScrew {
    pub(crate) lead_m: f64,
    pub(crate) efficiency: f64,
    pub(crate) inertia_kg_m2: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyTable {
    pub(crate) mass_kg: f64,
    pub(crate) external_force_n: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyDahl {
    pub(crate) coulomb_force_n: f64,
    pub(crate) stiffness_n_per_m: f64,
    pub(crate) exponent: f64,
    pub(crate) asymmetry: f64,
}

impl PyDahl {
    /// The law without its direction asymmetry (the rigid plant's table friction).
    pub(crate) fn law(&self) -> DahlFriction {
        DahlFriction {
            coulomb_force_n: self.coulomb_force_n,
            stiffness_n_per_m: self.stiffness_n_per_m,
            exponent: self.exponent,
        }
    }

    /// The law with its direction asymmetry, as the component plant's table friction.
    pub(crate) fn to_table(&self) -> TableFriction {
        TableFriction::Dahl(TableDahl {
            law: self.law(),
            asymmetry: self.asymmetry,
        })
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyPlant {
    pub(crate) motor: PyMotor,
    pub(crate) motor_friction: PyStribeck,
    pub(crate) gearhead: PyGearhead,
    pub(crate) screw: PyScrew,
    pub(crate) table: PyTable,
    pub(crate) dahl: PyDahl,
}

impl PyPlant {
    /// The plant's parameters that [`AxisParams`] does not hold, checked against their
    /// ranges: the direction asymmetry of the Dahl law, in [−0.9, 0.9]. A system runs a
    /// plant with an asymmetric Dahl law on the component plant (see [`PySystem::to_spec`]).
    pub(crate) fn validate_extra(&self) -> Result<(), CoreConfigError> {
        TableDahl {
            law: self.dahl.law(),
            asymmetry: self.dahl.asymmetry,
        }
        .validate()
        .map_err(|e| e.within("dahl"))
    }
}

impl From<&PyPlant> for AxisParams {
    fn from(p: &PyPlant) -> Self {
        AxisParams {
            motor: Motor {
                resistance_ohm: p.motor.resistance_ohm,
                inductance_h: p.motor.inductance_h,
                torque_constant_nm_per_a: p.motor.torque_constant_nm_per_a,
                back_emf_v_s_per_rad: p.motor.back_emf_v_s_per_rad,
                rotor_inertia_kg_m2: p.motor.rotor_inertia_kg_m2,
                quasi_static_current: p.motor.quasi_static_current,
            },
            motor_friction: StribeckFriction {
                static_torque_nm: p.motor_friction.static_torque_nm,
                coulomb_torque_nm: p.motor_friction.coulomb_torque_nm,
                viscous_nm_s_per_rad: p.motor_friction.viscous_nm_s_per_rad,
                stribeck_velocity_rad_per_s: p.motor_friction.stribeck_velocity_rad_per_s,
                stribeck_exponent: p.motor_friction.stribeck_exponent,
            },
            gearhead: Gearhead {
                ratio: p.gearhead.ratio,
                efficiency: p.gearhead.efficiency,
            },
            screw: BallScrew {
                lead_m: p.screw.lead_m,
                efficiency: p.screw.efficiency,
                inertia_kg_m2: p.screw.inertia_kg_m2,
            },
            table: Table {
                mass_kg: p.table.mass_kg,
                external_force_n: p.table.external_force_n,
            },
            dahl: p.dahl.law(),
        }
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyPid {
    pub(crate) kp: f64,
    pub(crate) ki: f64,
    pub(crate) kd: f64,
    pub(crate) gain_format: PyFxp,
    pub(crate) measurement_format: PyFxp,
    pub(crate) error_format: PyFxp,
    pub(crate) term_format: PyFxp,
    pub(crate) integrator_format: PyFxp,
    pub(crate) output_format: PyFxp,
    pub(crate) dac_format: PyFxp,
    pub(crate) dac_scale_format: PyFxp,
    pub(crate) output_min: f64,
    pub(crate) output_max: f64,
    pub(crate) anti_windup: String,
    pub(crate) output_unit_v: f64,
    pub(crate) dac_lsb_v: f64,
    pub(crate) clock_hz: f64,
    pub(crate) ticks_per_sample: u64,
    pub(crate) latency_ticks: u64,
}

#[derive(FromPyObject)]
pub(crate) struct PyEncoder {
    pub(crate) count_m: f64,
    pub(crate) side: String,
}

#[derive(FromPyObject)]
pub(crate) struct PyOutputStage {
    pub(crate) amplifier_gain: f64,
    pub(crate) amplifier_limit_v: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyIntegrator {
    pub(crate) rtol: f64,
    pub(crate) atol_position_m: f64,
    pub(crate) h_init_s: f64,
    pub(crate) h_min_s: f64,
    pub(crate) h_max_s: f64,
    pub(crate) max_steps: usize,
    pub(crate) max_events: usize,
    pub(crate) event_tol_s: f64,
}

impl From<&PyIntegrator> for IntegratorOptions {
    fn from(o: &PyIntegrator) -> Self {
        IntegratorOptions {
            rtol: o.rtol,
            atol_position_m: o.atol_position_m,
            h_init_s: o.h_init_s,
            h_min_s: o.h_min_s,
            h_max_s: o.h_max_s,
            max_steps: o.max_steps,
            max_events: o.max_events,
            event_tol_s: o.event_tol_s,
        }
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyDwell {
    pub(crate) rise_n: f64,
    pub(crate) time_constant_s: f64,
    pub(crate) slip_distance_m: Option<f64>,
}

impl From<&PyDwell> for DwellStatic {
    fn from(d: &PyDwell) -> Self {
        DwellStatic {
            rise_n: d.rise_n,
            time_constant_s: d.time_constant_s,
            slip_distance_m: d.slip_distance_m,
        }
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyStaticMap {
    pub(crate) static_force_n: f64,
    pub(crate) coulomb_force_n: f64,
    pub(crate) viscous_n_s_per_m: f64,
    pub(crate) stribeck_velocity_m_per_s: f64,
    pub(crate) stribeck_exponent: f64,
    pub(crate) asymmetry: f64,
    pub(crate) viscous_asymmetry: f64,
    pub(crate) dwell: Option<PyDwell>,
    pub(crate) memory_lag_s: Option<f64>,
}

impl From<&PyStaticMap> for StaticMap {
    fn from(m: &PyStaticMap) -> Self {
        StaticMap {
            static_force_n: m.static_force_n,
            coulomb_force_n: m.coulomb_force_n,
            viscous_n_s_per_m: m.viscous_n_s_per_m,
            stribeck_velocity_m_per_s: m.stribeck_velocity_m_per_s,
            stribeck_exponent: m.stribeck_exponent,
            asymmetry: m.asymmetry,
            viscous_asymmetry: m.viscous_asymmetry,
            dwell: m.dwell.as_ref().map(DwellStatic::from),
            memory_lag_s: m.memory_lag_s,
        }
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyLuGre {
    pub(crate) stiffness_n_per_m: f64,
    pub(crate) damping_n_s_per_m: f64,
    pub(crate) viscous_n_s_per_m: f64,
    pub(crate) coulomb_force_n: f64,
    pub(crate) static_force_n: f64,
    pub(crate) stribeck_velocity_m_per_s: f64,
    pub(crate) asymmetry: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyGms {
    pub(crate) stiffness_n_per_m: Vec<f64>,
    pub(crate) weights: Vec<f64>,
    pub(crate) coulomb_force_n: f64,
    pub(crate) static_force_n: f64,
    pub(crate) stribeck_velocity_m_per_s: f64,
    pub(crate) viscous_n_s_per_m: f64,
    pub(crate) asymmetry: f64,
}

pub(crate) enum PyTableFriction {
    Gms(PyGms),
    LuGre(PyLuGre),
    Static(PyStaticMap),
}

config_enum!(PyTableFriction: Gms(PyGms) = "Gms", LuGre(PyLuGre) = "LuGre",
    Static(PyStaticMap) = "StaticFrictionMap");

impl PyTableFriction {
    pub(crate) fn to_core(&self) -> Result<TableFriction, CoreConfigError> {
        Ok(match self {
            Self::Static(m) => TableFriction::Static(m.into()),
            Self::LuGre(l) => TableFriction::LuGre(LuGre {
                stiffness_n_per_m: l.stiffness_n_per_m,
                damping_n_s_per_m: l.damping_n_s_per_m,
                viscous_n_s_per_m: l.viscous_n_s_per_m,
                coulomb_force_n: l.coulomb_force_n,
                static_force_n: l.static_force_n,
                stribeck_velocity_m_per_s: l.stribeck_velocity_m_per_s,
                asymmetry: l.asymmetry,
            }),
            Self::Gms(g) => {
                let n = g.stiffness_n_per_m.len();
                if n == 0 || n > MAX_GMS_ELEMENTS || g.weights.len() != n {
                    return Err(CoreConfigError::new(
                        "table_friction.weights (length)",
                        g.weights.len(),
                        format!(
                            "one weight per element, 1 to {MAX_GMS_ELEMENTS} elements \
                             (stiffness_n_per_m has {n})"
                        ),
                    ));
                }
                let mut k = [1.0; MAX_GMS_ELEMENTS];
                let mut w = [0.0; MAX_GMS_ELEMENTS];
                k[..n].copy_from_slice(&g.stiffness_n_per_m);
                w[..n].copy_from_slice(&g.weights);
                TableFriction::Gms(Gms {
                    n_elements: n,
                    stiffness_n_per_m: k,
                    weights: w,
                    coulomb_force_n: g.coulomb_force_n,
                    static_force_n: g.static_force_n,
                    stribeck_velocity_m_per_s: g.stribeck_velocity_m_per_s,
                    viscous_n_s_per_m: g.viscous_n_s_per_m,
                    asymmetry: g.asymmetry,
                })
            }
        })
    }
}

#[derive(FromPyObject)]
pub(crate) struct PyModifiers {
    pub(crate) asymmetry: f64,
    pub(crate) dwell: Option<PyDwell>,
    pub(crate) memory_lag_s: Option<f64>,
}

#[derive(FromPyObject)]
pub(crate) struct PyPositionFriction {
    pub(crate) side: String,
    pub(crate) terms: Vec<(f64, f64, f64)>,
}

#[derive(FromPyObject)]
pub(crate) struct PyStochastic {
    pub(crate) level_spread: f64,
    pub(crate) distribution: String,
    pub(crate) within_spread: f64,
    pub(crate) correlation_time_s: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyBacklash {
    pub(crate) width_m: f64,
    pub(crate) contact_stiffness_n_per_m: f64,
    pub(crate) damping_n_s_per_m: f64,
    pub(crate) initial_flank: Option<f64>,
}

#[derive(FromPyObject)]
pub(crate) struct PyCompliance {
    pub(crate) stiffness_n_per_m: f64,
    pub(crate) damping_n_s_per_m: f64,
    pub(crate) axial_stiffness_n_per_m: Option<f64>,
    pub(crate) axial_damping_n_s_per_m: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyAmplifier {
    pub(crate) bandwidth_hz: f64,
    pub(crate) slew_v_per_s: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyEncoderErrors {
    pub(crate) cyclic_amplitude_m: f64,
    pub(crate) cyclic_period_m: f64,
    pub(crate) cyclic_phase_rad: f64,
    pub(crate) noise_std_m: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyInterferometer {
    pub(crate) resolution_m: f64,
    pub(crate) noise_std_m: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyEffects {
    pub(crate) table_friction: Option<PyTableFriction>,
    pub(crate) motor_friction: PyModifiers,
    pub(crate) position_friction: Vec<PyPositionFriction>,
    pub(crate) stochastic: Option<PyStochastic>,
    pub(crate) backlash: Option<PyBacklash>,
    pub(crate) compliance: Option<PyCompliance>,
    pub(crate) amplifier: Option<PyAmplifier>,
    pub(crate) encoder_errors: Option<PyEncoderErrors>,
    pub(crate) interferometer: Option<PyInterferometer>,
    pub(crate) sensor_delay_samples: usize,
    pub(crate) computation_delay_samples: usize,
    pub(crate) jitter_s: f64,
}

#[derive(FromPyObject)]
pub(crate) struct PyForcePlant {
    pub(crate) drive_gain_n_per_v: f64,
    pub(crate) mass_kg: f64,
    pub(crate) friction: PyStaticMap,
    pub(crate) external_force_n: f64,
    pub(crate) drive_mass_kg: f64,
}

pub(crate) enum PyAnyPlant {
    Seed(PyPlant),
    Force(PyForcePlant),
}

config_enum!(PyAnyPlant: Seed(PyPlant) = "Plant", Force(PyForcePlant) = "ForceDrivePlant");

#[derive(FromPyObject)]
pub(crate) struct PyCascade {
    pub(crate) kp_per_s: f64,
    pub(crate) kv_v_s_per_m: f64,
    pub(crate) sample_period_s: f64,
    pub(crate) saturation_v: f64,
}

#[allow(clippy::large_enum_variant)] // extracted once per call
pub(crate) enum PyAnyController {
    Fpga(PyPid),
    Cascade(PyCascade),
}

config_enum!(PyAnyController: Fpga(PyPid) = "FpgaPid", Cascade(PyCascade) = "CascadeController");

#[derive(FromPyObject)]
pub(crate) struct PySystem {
    pub(crate) plant: PyAnyPlant,
    pub(crate) controller: PyAnyController,
    pub(crate) encoder: PyEncoder,
    pub(crate) output_stage: PyOutputStage,
    pub(crate) integrator: PyIntegrator,
    pub(crate) effects: PyEffects,
}
pub(crate) enum PyAnyFriction {
    Table(PyTableFriction),
    Dahl(PyDahl),
}

config_enum!(PyAnyFriction: Table(PyTableFriction) = "Gms", Table(PyTableFriction) = "LuGre",
    Table(PyTableFriction) = "StaticFrictionMap", Dahl(PyDahl) = "DahlFriction");

impl From<&PyFxp> for FxpSpec {
    fn from(f: &PyFxp) -> Self {
        FxpSpec {
            signed: f.signed,
            word_bits: f.word_bits,
            int_bits: f.int_bits,
            rounding: f.rounding.clone(),
            overflow: f.overflow.clone(),
        }
    }
}

impl From<&PyPid> for PidSpec {
    fn from(p: &PyPid) -> Self {
        PidSpec {
            kp: p.kp,
            ki: p.ki,
            kd: p.kd,
            gain_format: (&p.gain_format).into(),
            measurement_format: (&p.measurement_format).into(),
            error_format: (&p.error_format).into(),
            term_format: (&p.term_format).into(),
            integrator_format: (&p.integrator_format).into(),
            output_format: (&p.output_format).into(),
            dac_format: (&p.dac_format).into(),
            dac_scale_format: (&p.dac_scale_format).into(),
            output_min: p.output_min,
            output_max: p.output_max,
            anti_windup: p.anti_windup.clone(),
            output_unit_v: p.output_unit_v,
            dac_lsb_v: p.dac_lsb_v,
            clock_hz: p.clock_hz,
            ticks_per_sample: p.ticks_per_sample,
            latency_ticks: p.latency_ticks,
        }
    }
}

impl From<&PyCascade> for CascadeConfig {
    fn from(c: &PyCascade) -> Self {
        CascadeConfig {
            kp_per_s: c.kp_per_s,
            kv_v_s_per_m: c.kv_v_s_per_m,
            sample_period_s: c.sample_period_s,
            saturation_v: c.saturation_v,
        }
    }
}

impl PySystem {
    /// The core's description of the system (the table friction checked for its shape).
    /// A seed plant whose Dahl law has a direction asymmetry (which [`AxisParams`] does not
    /// hold) and no table friction in the effects gets that law as the effects' table
    /// friction: the run is then on the component plant, which has the asymmetry.
    pub(crate) fn to_spec(&self) -> Result<SystemSpec, CoreConfigError> {
        let fx = &self.effects;
        let plant_table = match &self.plant {
            PyAnyPlant::Seed(p) if p.dahl.asymmetry != 0.0 => {
                p.validate_extra().map_err(|e| e.within("plant"))?;
                Some(p.dahl.to_table())
            }
            _ => None,
        };
        Ok(SystemSpec {
            plant: match &self.plant {
                PyAnyPlant::Seed(p) => PlantSpec::Rigid(p.into()),
                PyAnyPlant::Force(f) => PlantSpec::ForceDrive(ForceDriveSpec {
                    drive_gain_n_per_v: f.drive_gain_n_per_v,
                    mass_kg: f.mass_kg,
                    friction: (&f.friction).into(),
                    external_force_n: f.external_force_n,
                    drive_mass_kg: f.drive_mass_kg,
                }),
            },
            controller: match &self.controller {
                PyAnyController::Fpga(p) => ControllerSpec::Fpga(p.into()),
                PyAnyController::Cascade(c) => ControllerSpec::Cascade(c.into()),
            },
            encoder: EncoderSpec {
                count_m: self.encoder.count_m,
                side: self.encoder.side.clone(),
            },
            output_stage: OutputStage {
                amplifier_gain: self.output_stage.amplifier_gain,
                amplifier_limit_v: self.output_stage.amplifier_limit_v,
            },
            integrator: (&self.integrator).into(),
            effects: EffectsSpec {
                table_friction: match &fx.table_friction {
                    Some(tf) => Some(tf.to_core()?),
                    None => plant_table,
                },
                motor_friction: FrictionModifiersSpec {
                    asymmetry: fx.motor_friction.asymmetry,
                    dwell: fx.motor_friction.dwell.as_ref().map(DwellStatic::from),
                    memory_lag_s: fx.motor_friction.memory_lag_s,
                },
                position_friction: fx
                    .position_friction
                    .iter()
                    .map(|p| PositionFrictionSpec {
                        side: p.side.clone(),
                        terms: p.terms.clone(),
                    })
                    .collect(),
                stochastic: fx.stochastic.as_ref().map(|s| StochasticSpec {
                    level_spread: s.level_spread,
                    distribution: s.distribution.clone(),
                    within_spread: s.within_spread,
                    correlation_time_s: s.correlation_time_s,
                }),
                backlash: fx.backlash.as_ref().map(|b| BacklashSpec {
                    width_m: b.width_m,
                    contact_stiffness_n_per_m: b.contact_stiffness_n_per_m,
                    damping_n_s_per_m: b.damping_n_s_per_m,
                    initial_flank: b.initial_flank.unwrap_or(0.0),
                }),
                compliance: fx.compliance.as_ref().map(|c| ComplianceSpec {
                    stiffness_n_per_m: c.stiffness_n_per_m,
                    damping_n_s_per_m: c.damping_n_s_per_m,
                    axial_stiffness_n_per_m: c.axial_stiffness_n_per_m,
                    axial_damping_n_s_per_m: c.axial_damping_n_s_per_m,
                }),
                amplifier: fx.amplifier.as_ref().map(|a| crate::model::Amplifier {
                    bandwidth_hz: a.bandwidth_hz,
                    slew_v_per_s: a.slew_v_per_s,
                }),
                encoder_errors: fx.encoder_errors.as_ref().map(|e| EncoderErrorsSpec {
                    cyclic_amplitude_m: e.cyclic_amplitude_m,
                    cyclic_period_m: e.cyclic_period_m,
                    cyclic_phase_rad: e.cyclic_phase_rad,
                    noise_std_m: e.noise_std_m,
                }),
                interferometer: fx.interferometer.as_ref().map(|i| Interferometer {
                    resolution_m: i.resolution_m,
                    noise_std_m: i.noise_std_m,
                }),
                sensor_delay_samples: fx.sensor_delay_samples,
                computation_delay_samples: fx.computation_delay_samples,
                jitter_s: fx.jitter_s,
            },
        })
    }
}
