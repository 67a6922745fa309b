//! Bindings only: extract the Python dataclasses into core structs, release the GIL while
//! computing, hand the results back as numpy arrays. No physics here.
#![allow(missing_docs)]

use crate::control::{
    AntiWindup, Encoder, FxpFormat, OutputStage, Overflow, Pid, PidConfig, Rounding,
};
use crate::error::{ConfigError as CoreConfigError, SimError};
use crate::integrate::{IntegratorOptions, Stats};
use crate::model::{AxisParams, BallScrew, DahlFriction, Gearhead, Motor, StribeckFriction, Table};
use crate::sim::{run_closed_loop, run_open_loop, ClosedLoopConfig};
use numpy::{IntoPyArray, PyReadonlyArray1};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

create_exception!(
    _core,
    ConfigError,
    PyValueError,
    "A configuration value outside its valid range (names the field, the value and the range)."
);
create_exception!(
    _core,
    SimulationError,
    PyRuntimeError,
    "A numerical failure during a simulation (carries the time `t_s` and the `state`)."
);

fn config_err(e: CoreConfigError) -> PyErr {
    Python::attach(|py| {
        let err = ConfigError::new_err(e.to_string());
        let v = err.value(py);
        let _ = v.setattr("field", e.field.clone());
        let _ = v.setattr("value", e.value.clone());
        let _ = v.setattr("expected", e.expected.clone());
        err
    })
}

fn sim_err(e: SimError) -> PyErr {
    let (t, state) = match &e {
        SimError::Config(c) => return config_err(c.clone()),
        SimError::StepSizeTooSmall { t_s, state, .. }
        | SimError::SingularMatrix { t_s, state }
        | SimError::NonFinite { t_s, state }
        | SimError::TooManySteps { t_s, state, .. } => (*t_s, state.clone()),
        SimError::Interrupted { t_s } => (*t_s, Vec::new()),
    };
    Python::attach(|py| {
        let err = SimulationError::new_err(e.to_string());
        let v = err.value(py);
        let _ = v.setattr("t_s", t);
        let _ = v.setattr("state", state);
        err
    })
}

fn with_prefix(prefix: &str) -> impl Fn(CoreConfigError) -> PyErr + '_ {
    move |e| config_err(e.within(prefix))
}

#[derive(FromPyObject)]
struct PyFxp {
    signed: bool,
    word_bits: u32,
    int_bits: i32,
    rounding: String,
    overflow: String,
}

impl PyFxp {
    fn to_core(&self, field: &str) -> Result<FxpFormat, CoreConfigError> {
        let rounding = match self.rounding.as_str() {
            "truncate" => Rounding::Truncate,
            "half_up" => Rounding::HalfUp,
            "half_even" => Rounding::HalfEven,
            other => {
                return Err(CoreConfigError::new(
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
                return Err(CoreConfigError::new(
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

#[derive(FromPyObject)]
struct PyMotor {
    resistance_ohm: f64,
    inductance_h: f64,
    torque_constant_nm_per_a: f64,
    back_emf_v_s_per_rad: f64,
    rotor_inertia_kg_m2: f64,
    quasi_static_current: bool,
}

#[derive(FromPyObject)]
struct PyStribeck {
    static_torque_nm: f64,
    coulomb_torque_nm: f64,
    viscous_nm_s_per_rad: f64,
    stribeck_velocity_rad_per_s: f64,
    stribeck_exponent: f64,
}

#[derive(FromPyObject)]
struct PyGearhead {
    ratio: f64,
    efficiency: f64,
}

#[derive(FromPyObject)]
struct PyScrew {
    lead_m: f64,
    efficiency: f64,
    inertia_kg_m2: f64,
}

#[derive(FromPyObject)]
struct PyTable {
    mass_kg: f64,
    external_force_n: f64,
}

#[derive(FromPyObject)]
struct PyDahl {
    coulomb_force_n: f64,
    stiffness_n_per_m: f64,
    exponent: f64,
}

#[derive(FromPyObject)]
struct PyPlant {
    motor: PyMotor,
    motor_friction: PyStribeck,
    gearhead: PyGearhead,
    screw: PyScrew,
    table: PyTable,
    dahl: PyDahl,
}

impl From<PyPlant> for AxisParams {
    fn from(p: PyPlant) -> Self {
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
            dahl: DahlFriction {
                coulomb_force_n: p.dahl.coulomb_force_n,
                stiffness_n_per_m: p.dahl.stiffness_n_per_m,
                exponent: p.dahl.exponent,
            },
        }
    }
}

#[derive(FromPyObject)]
struct PyPid {
    kp: f64,
    ki: f64,
    kd: f64,
    gain_format: PyFxp,
    measurement_format: PyFxp,
    error_format: PyFxp,
    term_format: PyFxp,
    integrator_format: PyFxp,
    output_format: PyFxp,
    dac_format: PyFxp,
    dac_scale_format: PyFxp,
    output_min: f64,
    output_max: f64,
    anti_windup: String,
    output_unit_v: f64,
    dac_lsb_v: f64,
    clock_hz: f64,
    ticks_per_sample: u64,
    latency_ticks: u64,
}

impl PyPid {
    fn to_core(&self) -> Result<PidConfig, CoreConfigError> {
        let anti_windup = match self.anti_windup.as_str() {
            "none" => AntiWindup::None,
            "clamp" => AntiWindup::Clamp,
            "conditional" => AntiWindup::Conditional,
            other => {
                return Err(CoreConfigError::new(
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

#[derive(FromPyObject)]
struct PyEncoder {
    count_m: f64,
}

#[derive(FromPyObject)]
struct PyOutputStage {
    amplifier_gain: f64,
    amplifier_limit_v: f64,
}

#[derive(FromPyObject)]
struct PyIntegrator {
    rtol: f64,
    atol_position_m: f64,
    h_init_s: f64,
    h_min_s: f64,
    h_max_s: f64,
    max_steps: usize,
    event_tol_s: f64,
}

impl From<PyIntegrator> for IntegratorOptions {
    fn from(o: PyIntegrator) -> Self {
        IntegratorOptions {
            rtol: o.rtol,
            atol_position_m: o.atol_position_m,
            h_init_s: o.h_init_s,
            h_min_s: o.h_min_s,
            h_max_s: o.h_max_s,
            max_steps: o.max_steps,
            event_tol_s: o.event_tol_s,
        }
    }
}

#[derive(FromPyObject)]
struct PySystem {
    plant: PyPlant,
    controller: PyPid,
    encoder: PyEncoder,
    output_stage: PyOutputStage,
    integrator: PyIntegrator,
}

fn stats_dict<'py>(py: Python<'py>, s: &Stats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("n_rhs", s.n_rhs)?;
    d.set_item("n_jac", s.n_jac)?;
    d.set_item("n_lu", s.n_lu)?;
    d.set_item("n_accepted", s.n_accepted)?;
    d.set_item("n_rejected", s.n_rejected)?;
    d.set_item("n_events", s.n_events)?;
    Ok(d)
}

/// Run the closed loop; returns a dict of per-sample numpy arrays plus `stats`.
#[pyfunction]
fn simulate_closed_loop<'py>(
    py: Python<'py>,
    system: PySystem,
    reference_m: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyDict>> {
    let pid = system
        .controller
        .to_core()
        .map_err(with_prefix("controller"))?;
    let cfg = ClosedLoopConfig {
        axis: system.plant.into(),
        pid,
        encoder: Encoder {
            count_m: system.encoder.count_m,
        },
        output: OutputStage {
            amplifier_gain: system.output_stage.amplifier_gain,
            amplifier_limit_v: system.output_stage.amplifier_limit_v,
        },
        integrator: system.integrator.into(),
    };
    cfg.validate().map_err(config_err)?;
    let reference: Vec<f64> = reference_m.as_array().to_vec();
    let tr = py
        .detach(|| run_closed_loop(&cfg, &reference, None))
        .map_err(sim_err)?;
    let d = PyDict::new(py);
    d.set_item("stats", stats_dict(py, &tr.stats)?)?;
    d.set_item("time_s", tr.time_s.into_pyarray(py))?;
    d.set_item("reference_m", tr.reference_m.into_pyarray(py))?;
    d.set_item("reference_counts", tr.reference_counts.into_pyarray(py))?;
    d.set_item("position_m", tr.position_m.into_pyarray(py))?;
    d.set_item("velocity_m_per_s", tr.velocity_m_per_s.into_pyarray(py))?;
    d.set_item("encoder_counts", tr.encoder_counts.into_pyarray(py))?;
    d.set_item("current_a", tr.current_a.into_pyarray(py))?;
    d.set_item("motor_voltage_v", tr.motor_voltage_v.into_pyarray(py))?;
    d.set_item("command", tr.command.into_pyarray(py))?;
    d.set_item("dac_code", tr.dac_code.into_pyarray(py))?;
    d.set_item("error_counts", tr.error.into_pyarray(py))?;
    d.set_item("p_term", tr.p_term.into_pyarray(py))?;
    d.set_item("i_term", tr.i_term.into_pyarray(py))?;
    d.set_item("d_term", tr.d_term.into_pyarray(py))?;
    d.set_item("flags", tr.flags.into_pyarray(py))?;
    d.set_item(
        "motor_friction_force_n",
        tr.motor_friction_force_n.into_pyarray(py),
    )?;
    d.set_item("dahl_force_n", tr.dahl_force_n.into_pyarray(py))?;
    d.set_item("stuck", tr.stuck.into_pyarray(py))?;
    Ok(d)
}

/// Drive the plant alone with a held voltage per sample.
#[pyfunction]
fn simulate_open_loop<'py>(
    py: Python<'py>,
    plant: PyPlant,
    integrator: PyIntegrator,
    voltage_v: PyReadonlyArray1<'py, f64>,
    sample_period_s: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let axis: AxisParams = plant.into();
    let opts: IntegratorOptions = integrator.into();
    let u: Vec<f64> = voltage_v.as_array().to_vec();
    let tr = py
        .detach(|| run_open_loop(&axis, &opts, &u, sample_period_s))
        .map_err(sim_err)?;
    let d = PyDict::new(py);
    d.set_item("stats", stats_dict(py, &tr.stats)?)?;
    d.set_item("time_s", tr.time_s.into_pyarray(py))?;
    d.set_item("position_m", tr.position_m.into_pyarray(py))?;
    d.set_item("velocity_m_per_s", tr.velocity_m_per_s.into_pyarray(py))?;
    d.set_item("dahl_force_n", tr.dahl_force_n.into_pyarray(py))?;
    d.set_item("current_a", tr.current_a.into_pyarray(py))?;
    d.set_item("stuck", tr.stuck.into_pyarray(py))?;
    Ok(d)
}

/// Run the controller alone on given reference and measurement counts (bit-exact check).
#[pyfunction]
fn pid_run<'py>(
    py: Python<'py>,
    controller: PyPid,
    reference_counts: PyReadonlyArray1<'py, i64>,
    measured_counts: PyReadonlyArray1<'py, i64>,
) -> PyResult<Bound<'py, PyDict>> {
    let cfg = controller.to_core().map_err(config_err)?;
    let r = reference_counts.as_array();
    let y = measured_counts.as_array();
    if r.len() != y.len() {
        return Err(config_err(CoreConfigError::new(
            "measured_counts (length)",
            y.len(),
            format!("the length of reference_counts = {}", r.len()),
        )));
    }
    let mut pid = Pid::new(cfg).map_err(config_err)?;
    let n = r.len();
    let mut cols: [Vec<i64>; 6] = Default::default();
    let mut fl = Vec::with_capacity(n);
    for (rk, yk) in r.iter().zip(y.iter()) {
        let o = pid.step(*rk, *yk);
        for (c, v) in cols.iter_mut().zip([o.e, o.p, o.i, o.d, o.u, o.code]) {
            c.push(v);
        }
        fl.push(o.flags);
    }
    let d = PyDict::new(py);
    for (name, c) in ["e", "p", "i", "d", "u", "code"].into_iter().zip(cols) {
        d.set_item(name, c.into_pyarray(py))?;
    }
    d.set_item("flags", fl.into_pyarray(py))?;
    let (kp, ki, kd) = pid.raw_gains();
    d.set_item("raw_gains", (kp, ki, kd))?;
    Ok(d)
}

/// Requantise raw integers with `frac_in` fraction bits into `fmt`; returns (raw, overflow).
#[pyfunction]
fn fxp_requantize<'py>(
    py: Python<'py>,
    raw: PyReadonlyArray1<'py, i64>,
    frac_in: i32,
    fmt: PyFxp,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let f = fmt.to_core("fmt").map_err(config_err)?;
    if !(-64..=128).contains(&frac_in) {
        return Err(config_err(CoreConfigError::new(
            "frac_in",
            frac_in,
            "an integer in [-64, 128]",
        )));
    }
    let (mut out, mut ov) = (Vec::new(), Vec::new());
    for &v in raw.as_array().iter() {
        let (r, o) = f.requantize(crate::control::fixed::Exact {
            raw: i128::from(v),
            frac: frac_in,
        });
        out.push(r);
        ov.push(o);
    }
    Ok((
        out.into_pyarray(py).into_any(),
        ov.into_pyarray(py).into_any(),
    ))
}

/// The seed preset's numbers as nested dicts (one source for Rust and Python).
#[pyfunction]
fn seed_values(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let c = crate::presets::seed_closed_loop(1e-3);
    let a = c.axis;
    let d = PyDict::new(py);
    let block = |pairs: &[(&str, f64)]| -> PyResult<Bound<'_, PyDict>> {
        let b = PyDict::new(py);
        for (k, v) in pairs {
            b.set_item(*k, *v)?;
        }
        Ok(b)
    };
    let motor = block(&[
        ("resistance_ohm", a.motor.resistance_ohm),
        ("inductance_h", a.motor.inductance_h),
        ("torque_constant_nm_per_a", a.motor.torque_constant_nm_per_a),
        ("back_emf_v_s_per_rad", a.motor.back_emf_v_s_per_rad),
        ("rotor_inertia_kg_m2", a.motor.rotor_inertia_kg_m2),
    ])?;
    motor.set_item("quasi_static_current", a.motor.quasi_static_current)?;
    d.set_item("motor", motor)?;
    d.set_item(
        "motor_friction",
        block(&[
            ("static_torque_nm", a.motor_friction.static_torque_nm),
            ("coulomb_torque_nm", a.motor_friction.coulomb_torque_nm),
            (
                "viscous_nm_s_per_rad",
                a.motor_friction.viscous_nm_s_per_rad,
            ),
            (
                "stribeck_velocity_rad_per_s",
                a.motor_friction.stribeck_velocity_rad_per_s,
            ),
            ("stribeck_exponent", a.motor_friction.stribeck_exponent),
        ])?,
    )?;
    d.set_item(
        "gearhead",
        block(&[
            ("ratio", a.gearhead.ratio),
            ("efficiency", a.gearhead.efficiency),
        ])?,
    )?;
    d.set_item(
        "screw",
        block(&[
            ("lead_m", a.screw.lead_m),
            ("efficiency", a.screw.efficiency),
            ("inertia_kg_m2", a.screw.inertia_kg_m2),
        ])?,
    )?;
    d.set_item(
        "table",
        block(&[
            ("mass_kg", a.table.mass_kg),
            ("external_force_n", a.table.external_force_n),
        ])?,
    )?;
    d.set_item(
        "dahl",
        block(&[
            ("coulomb_force_n", a.dahl.coulomb_force_n),
            ("stiffness_n_per_m", a.dahl.stiffness_n_per_m),
            ("exponent", a.dahl.exponent),
        ])?,
    )?;
    d.set_item("encoder", block(&[("count_m", c.encoder.count_m)])?)?;
    d.set_item(
        "output_stage",
        block(&[
            ("amplifier_gain", c.output.amplifier_gain),
            ("amplifier_limit_v", c.output.amplifier_limit_v),
        ])?,
    )?;
    let p = c.pid;
    let fmt = |f: &FxpFormat| -> PyResult<Bound<'_, PyDict>> {
        let b = PyDict::new(py);
        b.set_item("signed", f.signed)?;
        b.set_item("word_bits", f.word_bits)?;
        b.set_item("int_bits", f.int_bits)?;
        b.set_item(
            "rounding",
            match f.rounding {
                Rounding::Truncate => "truncate",
                Rounding::HalfUp => "half_up",
                Rounding::HalfEven => "half_even",
            },
        )?;
        b.set_item(
            "overflow",
            match f.overflow {
                Overflow::Saturate => "saturate",
                Overflow::Wrap => "wrap",
            },
        )?;
        Ok(b)
    };
    let ctl = PyDict::new(py);
    for (k, f) in [
        ("gain_format", &p.gain_format),
        ("measurement_format", &p.measurement_format),
        ("error_format", &p.error_format),
        ("term_format", &p.term_format),
        ("integrator_format", &p.integrator_format),
        ("output_format", &p.output_format),
        ("dac_format", &p.dac_format),
        ("dac_scale_format", &p.dac_scale_format),
    ] {
        ctl.set_item(k, fmt(f)?)?;
    }
    ctl.set_item("output_min", p.output_min)?;
    ctl.set_item("output_max", p.output_max)?;
    ctl.set_item(
        "anti_windup",
        match p.anti_windup {
            AntiWindup::None => "none",
            AntiWindup::Clamp => "clamp",
            AntiWindup::Conditional => "conditional",
        },
    )?;
    ctl.set_item("output_unit_v", p.output_unit_v)?;
    ctl.set_item("dac_lsb_v", p.dac_lsb_v)?;
    ctl.set_item("clock_hz", p.clock_hz)?;
    ctl.set_item("ticks_per_sample", p.ticks_per_sample)?;
    ctl.set_item("latency_ticks", p.latency_ticks)?;
    d.set_item("controller", ctl)?;
    let o = c.integrator;
    let integ = block(&[
        ("rtol", o.rtol),
        ("atol_position_m", o.atol_position_m),
        ("h_init_s", o.h_init_s),
        ("h_min_s", o.h_min_s),
        ("h_max_s", o.h_max_s),
        ("event_tol_s", o.event_tol_s),
    ])?;
    integ.set_item("max_steps", o.max_steps)?;
    d.set_item("integrator", integ)?;
    let gains = PyDict::new(py);
    for step in [100e-6, 500e-6, 1e-3, 10e-3] {
        gains.set_item(step, crate::presets::table1_gains(step))?;
    }
    d.set_item("table1_gains", gains)?;
    Ok(d)
}

/// Validate a plant (raises ConfigError naming the field).
#[pyfunction]
fn validate_plant(plant: PyPlant) -> PyResult<()> {
    AxisParams::from(plant).validate().map_err(config_err)
}

/// Validate a controller, including the quantisation of gains and range into their formats.
#[pyfunction]
fn validate_controller(controller: PyPid) -> PyResult<()> {
    let cfg = controller.to_core().map_err(config_err)?;
    Pid::new(cfg).map(|_| ()).map_err(config_err)
}

/// Validate integrator options.
#[pyfunction]
fn validate_integrator(integrator: PyIntegrator) -> PyResult<()> {
    IntegratorOptions::from(integrator)
        .validate()
        .map_err(config_err)
}

/// Validate an encoder and an output stage.
#[pyfunction]
fn validate_io(encoder: PyEncoder, output_stage: PyOutputStage) -> PyResult<()> {
    Encoder {
        count_m: encoder.count_m,
    }
    .validate()
    .map_err(with_prefix("encoder"))?;
    OutputStage {
        amplifier_gain: output_stage.amplifier_gain,
        amplifier_limit_v: output_stage.amplifier_limit_v,
    }
    .validate()
    .map_err(with_prefix("output_stage"))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("ConfigError", py.get_type::<ConfigError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add_function(wrap_pyfunction!(simulate_closed_loop, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_open_loop, m)?)?;
    m.add_function(wrap_pyfunction!(pid_run, m)?)?;
    m.add_function(wrap_pyfunction!(fxp_requantize, m)?)?;
    m.add_function(wrap_pyfunction!(seed_values, m)?)?;
    m.add_function(wrap_pyfunction!(validate_plant, m)?)?;
    m.add_function(wrap_pyfunction!(validate_controller, m)?)?;
    m.add_function(wrap_pyfunction!(validate_integrator, m)?)?;
    m.add_function(wrap_pyfunction!(validate_io, m)?)?;
    Ok(())
}
