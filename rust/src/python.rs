//! Bindings only: extract the Python dataclasses into core structs, release the GIL while
//! computing, hand the results back as numpy arrays. No physics here.
//!
//! A value of the wrong Python type anywhere in a configuration is a `ConfigTypeError` (a
//! `ConfigError` and a `TypeError`) naming its field path, the value, its type and the
//! expected type ([`extract_config`]). Long calls poll for Ctrl-C while they run without the
//! GIL ([`SignalPoll`], [`simulate_system_batch`]): SIGINT's `KeyboardInterrupt` stops them
//! within a fraction of a second and is what the call raises.
#![allow(missing_docs)]

use crate::control::CascadeConfig;
use crate::control::{
    AntiWindup, Encoder, FxpFormat, OutputStage, Overflow, Pid, PidConfig, Rounding,
};
use crate::drive::{
    Actuator, Amplifier, DriveParams, DwellStatic, Gms, Link, LuGre, Modulation, Side, StaticMap,
    TableFriction, MAX_GMS_ELEMENTS, MAX_MODULATION_TERMS,
};
use crate::error::{ConfigError as CoreConfigError, SimError};
use crate::integrate::{IntegratorOptions, Stats};
use crate::model::{AxisParams, BallScrew, DahlFriction, Gearhead, Motor, StribeckFriction, Table};
use crate::sim::{
    run_campaign, run_drive_open_loop_polled, run_extended_polled, run_open_loop_polled, Campaign,
    ControllerKind, ExtendedConfig, Interferometer, KnownInputs, Sensors, SpreadDistribution,
    StochasticFriction, Trace,
};
use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray1};
use pyo3::create_exception;
use pyo3::exceptions::{PyAttributeError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyList, PyTuple, PyType};
use pyo3::Borrowed;
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

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
    if let SimError::Config(c) = &e {
        return config_err(c.clone());
    }
    let (t, state) = e.time_and_state();
    Python::attach(|py| {
        let err = SimulationError::new_err(e.to_string());
        let v = err.value(py);
        let _ = v.setattr("t_s", t);
        let _ = v.setattr("state", state);
        err
    })
}

/// The `ConfigTypeError` class: a `ConfigError` that is also a `TypeError` (a value of the
/// wrong Python type), created once per interpreter.
static CONFIG_TYPE_ERROR: PyOnceLock<Py<PyType>> = PyOnceLock::new();

fn config_type_error_class(py: Python<'_>) -> PyResult<&Bound<'_, PyType>> {
    CONFIG_TYPE_ERROR
        .get_or_try_init(py, || {
            let attrs = PyDict::new(py);
            attrs.set_item("__module__", "nanostage._core")?;
            attrs.set_item(
                "__doc__",
                "A configuration value of the wrong type (names the field path, the value, its \
                 type and the expected type); a ConfigError and a TypeError.",
            )?;
            let bases = PyTuple::new(
                py,
                [py.get_type::<ConfigError>(), py.get_type::<PyTypeError>()],
            )?;
            let class = py
                .get_type::<PyType>()
                .call1(("ConfigTypeError", bases, attrs))?
                .cast_into::<PyType>()?;
            Ok::<_, PyErr>(class.unbind())
        })
        .map(|c| c.bind(py))
}

/// `configuration` extracted as `T`. A value of the wrong type anywhere in it (a string or
/// `None` where the core expects a `Motor`, a float, ...) raises `ConfigTypeError` naming the
/// field path (`prefix` + the fields the extraction went through; `arg` when the object
/// itself is wrong), the value, its type and the expected type, e.g.
/// `plant.motor = 'abc' (str) is invalid: expected a Motor`.
fn extract_config<'py, T>(
    configuration: &Bound<'py, PyAny>,
    arg: &str,
    prefix: &str,
    expected: &str,
) -> PyResult<T>
where
    T: for<'a> FromPyObject<'a, 'py>,
{
    configuration.extract::<T>().map_err(|e| {
        let e: PyErr = e.into();
        type_error(configuration, arg, prefix, expected, e)
    })
}

/// The `ConfigTypeError` of a failed extraction `err` of `root` (see [`extract_config`]):
/// the derived extractions wrap an error in a field as "failed to extract field S.f" with the
/// inner error as its cause, so the cause chain gives the field path; walking `root` along it
/// gives the value, and the dataclass annotation of its field the expected type.
fn type_error(
    root: &Bound<'_, PyAny>,
    arg: &str,
    prefix: &str,
    expected: &str,
    err: PyErr,
) -> PyErr {
    let py = root.py();
    let mut names: Vec<String> = Vec::new();
    let mut cur = err;
    loop {
        let msg = cur.value(py).to_string();
        let Some(field) = msg.strip_prefix("failed to extract field ") else {
            break;
        };
        names.push(field.rsplit('.').next().unwrap_or(field).to_owned());
        match cur.cause(py) {
            Some(c) => cur = c,
            None => break,
        }
    }
    // Walk the object along the path as far as it goes.
    let mut value = root.clone();
    let mut parent: Option<(Bound<'_, PyAny>, &str)> = None;
    let mut walked: Vec<&str> = Vec::new();
    for name in &names {
        match value.getattr(name.as_str()) {
            Ok(v) => {
                parent = Some((value, name.as_str()));
                value = v;
                walked.push(name.as_str());
            }
            Err(_) => break,
        }
    }
    let field = if walked.is_empty() {
        arg.to_owned()
    } else {
        format!("{prefix}{}", walked.join("."))
    };
    let mut want = match &parent {
        Some((p, name)) => annotation(p, name).unwrap_or_else(|| "another type".to_owned()),
        None => expected.to_owned(),
    };
    // Say why when the innermost error is not about the type (e.g. a negative count).
    let inner = cur.value(py).to_string();
    let about_type =
        cur.is_instance_of::<PyAttributeError>(py) || cur.is_instance_of::<PyTypeError>(py);
    if !about_type && !inner.is_empty() {
        want = format!("{want} ({})", inner.lines().next().unwrap_or(&inner));
    }
    let mut shown = value
        .repr()
        .map_or_else(|_| "<unprintable>".to_owned(), |r| r.to_string());
    if shown.chars().count() > 80 {
        shown = shown.chars().take(77).collect::<String>() + "...";
    }
    let type_name = value
        .get_type()
        .name()
        .map_or_else(|_| "?".to_owned(), |n| n.to_string());
    let shown = format!("{shown} ({type_name})");
    let message = format!("{field} = {shown} is invalid: expected {want}");
    let made = config_type_error_class(py).and_then(|class| {
        let err = PyErr::from_type(class.clone(), message.clone());
        let v = err.value(py);
        v.setattr("field", field.clone())?;
        v.setattr("value", shown.clone())?;
        v.setattr("expected", want.clone())?;
        Ok(err)
    });
    made.unwrap_or_else(|e| e)
}

/// The expected type of field `name` of the dataclass `parent`, from its annotation:
/// "a Motor", "a float", "one of Plant, ForceDrivePlant".
fn annotation(parent: &Bound<'_, PyAny>, name: &str) -> Option<String> {
    let py = parent.py();
    let fields = py
        .import("dataclasses")
        .ok()?
        .call_method1("fields", (parent,))
        .ok()?;
    for f in fields.try_iter().ok()? {
        let f = f.ok()?;
        if f.getattr("name").ok()?.extract::<String>().ok()? != name {
            continue;
        }
        if let Some(choices) = literal_choices(parent, name) {
            return Some(format!("one of {choices}"));
        }
        let t = f.getattr("type").ok()?;
        let text = match t.extract::<String>() {
            Ok(s) => s,
            Err(_) => t
                .getattr("__name__")
                .and_then(|n| n.extract::<String>())
                .or_else(|_| t.str().map(|s| s.to_string()))
                .ok()?,
        };
        let parts: Vec<&str> = text.split('|').map(str::trim).collect();
        return Some(if parts.len() == 1 {
            let article = if text.starts_with(['A', 'E', 'I', 'O', 'U', 'a', 'e', 'i', 'o', 'u']) {
                "an"
            } else {
                "a"
            };
            format!("{article} {text}")
        } else {
            format!("one of {}", parts.join(", "))
        });
    }
    None
}

/// The choices of field `name` of `parent` when its annotation is a `Literal` (also through
/// an alias such as `AntiWindup`): `'none', 'clamp', 'conditional'`.
fn literal_choices(parent: &Bound<'_, PyAny>, name: &str) -> Option<String> {
    let typing = parent.py().import("typing").ok()?;
    let hint = typing
        .call_method1("get_type_hints", (parent.get_type(),))
        .ok()?
        .get_item(name)
        .ok()?;
    let origin = typing.call_method1("get_origin", (&hint,)).ok()?;
    if !origin.is(&typing.getattr("Literal").ok()?) {
        return None;
    }
    let args = typing.call_method1("get_args", (&hint,)).ok()?;
    let shown: Vec<String> = args
        .try_iter()
        .ok()?
        .filter_map(|a| a.ok()?.repr().ok().map(|r| r.to_string()))
        .collect();
    Some(shown.join(", "))
}

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

/// Wall-clock time between two looks for pending signals during a long call (the look takes
/// the GIL back; it never changes a result).
const SIGNAL_POLL_INTERVAL: Duration = Duration::from_millis(50);

/// Whether the calling thread is Python's main thread (the only one that runs signal
/// handlers).
fn is_main_thread(py: Python<'_>) -> bool {
    let check = || -> PyResult<bool> {
        let threading = py.import("threading")?;
        let current = threading.call_method0("current_thread")?;
        Ok(current.is(&threading.call_method0("main_thread")?))
    };
    check().unwrap_or(false)
}

/// Stop flag of every single run and batch of this process (campaigns have their own), set
/// from Python (`nanostage.simulate.stop_on_interrupt`) so that a Ctrl-C seen by the main
/// thread also stops the runs of other threads; they end with `SimulationError`
/// ("interrupted at t = ...").
static RUN_STOP: AtomicBool = AtomicBool::new(false);

/// Ask every running single run and batch of this process to stop (within a few control
/// samples).
#[pyfunction]
fn runs_request_stop() {
    RUN_STOP.store(true, Ordering::Relaxed);
}

/// Clear the stop flag of [`runs_request_stop`].
#[pyfunction]
fn runs_reset() {
    RUN_STOP.store(false, Ordering::Relaxed);
}

/// Whether a stop of the runs has been requested since the last reset.
#[pyfunction]
fn runs_stop_requested() -> bool {
    RUN_STOP.load(Ordering::Relaxed)
}

/// Ctrl-C for a run computed without the GIL on the calling thread: the run asks
/// [`Self::poll`] every few control samples; at most every [`SIGNAL_POLL_INTERVAL`] the poll
/// takes the GIL back and runs Python's signal handlers (on the main thread only; elsewhere
/// it stops looking). A handler that raises (SIGINT's `KeyboardInterrupt`) stops the run, and
/// [`Self::finish`] raises that exception instead of the run's result. The process-wide
/// [`RUN_STOP`] flag stops the run too (on any thread).
struct SignalPoll {
    last: Instant,
    main_thread: Option<bool>,
    raised: Option<PyErr>,
}

impl SignalPoll {
    fn new() -> Self {
        Self {
            last: Instant::now(),
            main_thread: None,
            raised: None,
        }
    }

    /// Whether the run should stop.
    fn poll(&mut self) -> bool {
        if self.raised.is_some() || RUN_STOP.load(Ordering::Relaxed) {
            return true;
        }
        if self.main_thread == Some(false) || self.last.elapsed() < SIGNAL_POLL_INTERVAL {
            return false;
        }
        self.last = Instant::now();
        Python::attach(|py| {
            let main = *self.main_thread.get_or_insert_with(|| is_main_thread(py));
            if main {
                if let Err(e) = py.check_signals() {
                    self.raised = Some(e);
                }
            }
        });
        self.raised.is_some()
    }

    /// The run's result, or the exception a signal handler raised during it.
    fn finish<T>(self, result: Result<T, SimError>) -> PyResult<T> {
        match self.raised {
            Some(e) => Err(e),
            None => result.map_err(sim_err),
        }
    }
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
    side: String,
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
    max_events: usize,
    event_tol_s: f64,
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
struct PyDwell {
    rise_n: f64,
    time_constant_s: f64,
}

impl From<&PyDwell> for DwellStatic {
    fn from(d: &PyDwell) -> Self {
        DwellStatic {
            rise_n: d.rise_n,
            time_constant_s: d.time_constant_s,
        }
    }
}

#[derive(FromPyObject)]
struct PyStaticMap {
    static_force_n: f64,
    coulomb_force_n: f64,
    viscous_n_s_per_m: f64,
    stribeck_velocity_m_per_s: f64,
    stribeck_exponent: f64,
    asymmetry: f64,
    viscous_asymmetry: f64,
    dwell: Option<PyDwell>,
    memory_lag_s: Option<f64>,
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
struct PyLuGre {
    stiffness_n_per_m: f64,
    damping_n_s_per_m: f64,
    viscous_n_s_per_m: f64,
    coulomb_force_n: f64,
    static_force_n: f64,
    stribeck_velocity_m_per_s: f64,
}

#[derive(FromPyObject)]
struct PyGms {
    stiffness_n_per_m: Vec<f64>,
    weights: Vec<f64>,
    coulomb_force_n: f64,
    static_force_n: f64,
    stribeck_velocity_m_per_s: f64,
    viscous_n_s_per_m: f64,
}

enum PyTableFriction {
    Gms(PyGms),
    LuGre(PyLuGre),
    Static(PyStaticMap),
}

config_enum!(PyTableFriction: Gms(PyGms) = "Gms", LuGre(PyLuGre) = "LuGre",
    Static(PyStaticMap) = "StaticFrictionMap");

impl PyTableFriction {
    fn to_core(&self) -> Result<TableFriction, CoreConfigError> {
        Ok(match self {
            Self::Static(m) => TableFriction::Static(m.into()),
            Self::LuGre(l) => TableFriction::LuGre(LuGre {
                stiffness_n_per_m: l.stiffness_n_per_m,
                damping_n_s_per_m: l.damping_n_s_per_m,
                viscous_n_s_per_m: l.viscous_n_s_per_m,
                coulomb_force_n: l.coulomb_force_n,
                static_force_n: l.static_force_n,
                stribeck_velocity_m_per_s: l.stribeck_velocity_m_per_s,
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
                })
            }
        })
    }
}

#[derive(FromPyObject)]
struct PyModifiers {
    asymmetry: f64,
    dwell: Option<PyDwell>,
    memory_lag_s: Option<f64>,
}

#[derive(FromPyObject)]
struct PyPositionFriction {
    side: String,
    terms: Vec<(f64, f64, f64)>,
}

#[derive(FromPyObject)]
struct PyStochastic {
    level_spread: f64,
    distribution: String,
    within_spread: f64,
    correlation_time_s: f64,
}

#[derive(FromPyObject)]
struct PyBacklash {
    width_m: f64,
    contact_stiffness_n_per_m: f64,
    damping_n_s_per_m: f64,
}

#[derive(FromPyObject)]
struct PyCompliance {
    stiffness_n_per_m: f64,
    damping_n_s_per_m: f64,
    axial_stiffness_n_per_m: Option<f64>,
    axial_damping_n_s_per_m: f64,
}

#[derive(FromPyObject)]
struct PyAmplifier {
    bandwidth_hz: f64,
    slew_v_per_s: f64,
}

#[derive(FromPyObject)]
struct PyEncoderErrors {
    cyclic_amplitude_m: f64,
    cyclic_period_m: f64,
    cyclic_phase_rad: f64,
    noise_std_m: f64,
}

#[derive(FromPyObject)]
struct PyInterferometer {
    resolution_m: f64,
    noise_std_m: f64,
}

#[derive(FromPyObject)]
struct PyEffects {
    table_friction: Option<PyTableFriction>,
    motor_friction: PyModifiers,
    position_friction: Vec<PyPositionFriction>,
    stochastic: Option<PyStochastic>,
    backlash: Option<PyBacklash>,
    compliance: Option<PyCompliance>,
    amplifier: Option<PyAmplifier>,
    encoder_errors: Option<PyEncoderErrors>,
    interferometer: Option<PyInterferometer>,
    sensor_delay_samples: usize,
    computation_delay_samples: usize,
    jitter_s: f64,
}

#[derive(FromPyObject)]
struct PyForcePlant {
    drive_gain_n_per_v: f64,
    mass_kg: f64,
    friction: PyStaticMap,
    external_force_n: f64,
    drive_mass_kg: f64,
}

enum PyAnyPlant {
    Seed(PyPlant),
    Force(PyForcePlant),
}

config_enum!(PyAnyPlant: Seed(PyPlant) = "Plant", Force(PyForcePlant) = "ForceDrivePlant");

#[derive(FromPyObject)]
struct PyCascade {
    kp_per_s: f64,
    kv_v_s_per_m: f64,
    sample_period_s: f64,
    saturation_v: f64,
}

#[allow(clippy::large_enum_variant)] // extracted once per call
enum PyAnyController {
    Fpga(PyPid),
    Cascade(PyCascade),
}

config_enum!(PyAnyController: Fpga(PyPid) = "FpgaPid", Cascade(PyCascade) = "CascadeController");

#[derive(FromPyObject)]
struct PySystem {
    plant: PyAnyPlant,
    controller: PyAnyController,
    encoder: PyEncoder,
    output_stage: PyOutputStage,
    integrator: PyIntegrator,
    effects: PyEffects,
}

fn side(field: &str, s: &str) -> Result<Side, CoreConfigError> {
    match s {
        "motor" => Ok(Side::Motor),
        "table" => Ok(Side::Table),
        other => Err(CoreConfigError::new(
            field,
            format!("{other:?}"),
            "one of 'motor', 'table'",
        )),
    }
}

fn modulation(terms: &[(f64, f64, f64)], into: &mut Modulation) -> Result<(), CoreConfigError> {
    let start = into.n_terms;
    if start + terms.len() > MAX_MODULATION_TERMS {
        return Err(CoreConfigError::new(
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

/// Build the core configuration of a `System` (all validation happens in the core).
fn build_system(
    sys: &PySystem,
    seed: u64,
    initial_position_m: f64,
) -> Result<ExtendedConfig, CoreConfigError> {
    let fx = &sys.effects;
    let (mut drive, axis) = match &sys.plant {
        PyAnyPlant::Seed(p) => {
            let axis = AxisParams::from(p);
            (DriveParams::from_axis(&axis), Some(axis))
        }
        PyAnyPlant::Force(f) => {
            let mut d = DriveParams::from_axis(&crate::presets::seed_axis());
            d.actuator = Actuator::ForceDrive {
                gain_n_per_v: f.drive_gain_n_per_v,
                drive_mass_kg: f.drive_mass_kg,
            };
            d.motor_friction = None;
            d.table_friction = TableFriction::Static((&f.friction).into());
            d.table_mass_kg = f.mass_kg;
            d.external_force_n = f.external_force_n;
            (d, None)
        }
    };
    if let Some(tf) = &fx.table_friction {
        drive.table_friction = tf.to_core()?;
    }
    if let Some(m) = drive.motor_friction.as_mut() {
        m.asymmetry = fx.motor_friction.asymmetry;
        m.dwell = fx.motor_friction.dwell.as_ref().map(DwellStatic::from);
        m.memory_lag_s = fx.motor_friction.memory_lag_s;
    } else if fx.motor_friction.asymmetry != 0.0
        || fx.motor_friction.dwell.is_some()
        || fx.motor_friction.memory_lag_s.is_some()
    {
        return Err(CoreConfigError::new(
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
    drive.amplifier = fx.amplifier.as_ref().map(|a| Amplifier {
        bandwidth_hz: a.bandwidth_hz,
        slew_v_per_s: a.slew_v_per_s,
    });
    let controller = match &sys.controller {
        PyAnyController::Fpga(p) => ControllerKind::Fpga {
            pid: p.to_core().map_err(|e| e.within("controller"))?,
            output: OutputStage {
                amplifier_gain: sys.output_stage.amplifier_gain,
                amplifier_limit_v: sys.output_stage.amplifier_limit_v,
            },
        },
        PyAnyController::Cascade(c) => ControllerKind::Cascade(CascadeConfig {
            kp_per_s: c.kp_per_s,
            kv_v_s_per_m: c.kv_v_s_per_m,
            sample_period_s: c.sample_period_s,
            saturation_v: c.saturation_v,
        }),
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
        interferometer: fx.interferometer.as_ref().map(|i| Interferometer {
            resolution_m: i.resolution_m,
            noise_std_m: i.noise_std_m,
        }),
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
                    return Err(CoreConfigError::new(
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
        integrator: (&sys.integrator).into(),
        initial_position_m,
    };
    cfg.validate()?;
    Ok(cfg)
}

fn optional_series(a: &Option<PyReadonlyArray1<'_, f64>>) -> Vec<f64> {
    a.as_ref().map_or_else(Vec::new, |a| a.as_array().to_vec())
}

/// Move the named `Vec` fields of `tr` into the dict `d` as numpy arrays under their names.
macro_rules! put_arrays {
    ($d:ident, $py:ident, $tr:ident; $($f:ident),+ $(,)?) => {
        $( $d.set_item(stringify!($f), $tr.$f.into_pyarray($py))?; )+
    };
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

/// Run the closed loop of a `System`; returns a dict of per-sample numpy arrays plus `stats`.
#[pyfunction]
#[pyo3(signature = (system, reference_m, force_disturbance_n=None, command_disturbance_v=None, seed=0, initial_position_m=0.0))]
fn simulate_system<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    reference_m: PyReadonlyArray1<'py, f64>,
    force_disturbance_n: Option<PyReadonlyArray1<'py, f64>>,
    command_disturbance_v: Option<PyReadonlyArray1<'py, f64>>,
    seed: u64,
    initial_position_m: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let system: PySystem = extract_config(system, "system", "", "a System")?;
    let cfg = build_system(&system, seed, initial_position_m).map_err(config_err)?;
    let reference: Vec<f64> = reference_m.as_array().to_vec();
    let force = optional_series(&force_disturbance_n);
    let command = optional_series(&command_disturbance_v);
    let mut signals = SignalPoll::new();
    let tr = py.detach(|| {
        run_extended_polled(
            &cfg,
            &reference,
            KnownInputs {
                force_n: &force,
                command_v: &command,
            },
            &mut || signals.poll(),
        )
    });
    trace_dict(py, signals.finish(tr)?)
}

/// Run the closed loops of several `System`s at once, in parallel (rayon, `threads` workers;
/// 0: rayon's default pool) with the GIL released once for the whole batch; returns the
/// dicts of [`simulate_system`] in the order given. Every configuration is checked before any
/// simulation starts; the first failed run (in the order given) raises its error.
///
/// Called from the main thread, the calling thread waits for the batch and looks for
/// pending signals every [`SIGNAL_POLL_INTERVAL`]; a handler that raises (Ctrl-C) sets the
/// batch's stop flag, which every run polls every few control samples, and the call raises
/// that exception once the runs have stopped.
#[pyfunction]
#[pyo3(signature = (systems, references_m, force_disturbances_n, command_disturbances_v, seeds, initial_positions_m, threads=0))]
#[allow(clippy::too_many_arguments)]
fn simulate_system_batch<'py>(
    py: Python<'py>,
    systems: Vec<Bound<'py, PyAny>>,
    references_m: Vec<PyReadonlyArray1<'py, f64>>,
    force_disturbances_n: Vec<Option<PyReadonlyArray1<'py, f64>>>,
    command_disturbances_v: Vec<Option<PyReadonlyArray1<'py, f64>>>,
    seeds: Vec<u64>,
    initial_positions_m: Vec<f64>,
    threads: usize,
) -> PyResult<Bound<'py, PyList>> {
    let n = systems.len();
    for (name, len) in [
        ("references_m", references_m.len()),
        ("force_disturbances_n", force_disturbances_n.len()),
        ("command_disturbances_v", command_disturbances_v.len()),
        ("seeds", seeds.len()),
        ("initial_positions_m", initial_positions_m.len()),
    ] {
        if len != n {
            return Err(PyValueError::new_err(format!(
                "{name} has {len} entries; expected one per system ({n})"
            )));
        }
    }
    let mut jobs = Vec::with_capacity(n);
    for i in 0..n {
        let system: PySystem = extract_config(
            &systems[i],
            &format!("systems[{i}]"),
            &format!("systems[{i}]."),
            "a System",
        )?;
        let cfg = build_system(&system, seeds[i], initial_positions_m[i]).map_err(config_err)?;
        jobs.push((
            cfg,
            references_m[i].as_array().to_vec(),
            optional_series(&force_disturbances_n[i]),
            optional_series(&command_disturbances_v[i]),
        ));
    }
    let stop = AtomicBool::new(false);
    let run = || -> Vec<Result<Trace, SimError>> {
        jobs.par_iter()
            .map(|(cfg, r, f, c)| {
                run_extended_polled(
                    cfg,
                    r,
                    KnownInputs {
                        force_n: f,
                        command_v: c,
                    },
                    &mut || stop.load(Ordering::Relaxed) || RUN_STOP.load(Ordering::Relaxed),
                )
            })
            .collect()
    };
    let pool = batch_pool(threads);
    let watch = is_main_thread(py);
    let mut raised: Option<PyErr> = None;
    let results = py.detach(|| {
        if !watch {
            return match &pool {
                Some(pool) => pool.install(run),
                None => run(),
            };
        }
        // The runs go to the pool as one job; this thread waits for it and looks for pending
        // signals meanwhile (no thread of its own: a batch is called thousands of times).
        let mut results = None;
        let (done, finished) = mpsc::channel();
        macro_rules! wait_in {
            ($($in_place_scope:tt)+) => {
                $($in_place_scope)+(|scope| {
                    let out = &mut results;
                    scope.spawn(move |_| {
                        *out = Some(run());
                        // Nothing to tell if the receiver is gone.
                        let _ = done.send(());
                    });
                    loop {
                        match finished.recv_timeout(SIGNAL_POLL_INTERVAL) {
                            Err(mpsc::RecvTimeoutError::Timeout) if raised.is_none() => {
                                if let Err(e) = Python::attach(|py| py.check_signals()) {
                                    stop.store(true, Ordering::Relaxed);
                                    raised = Some(e);
                                }
                            }
                            Err(mpsc::RecvTimeoutError::Timeout) => {}
                            Ok(()) | Err(mpsc::RecvTimeoutError::Disconnected) => break,
                        }
                    }
                })
            };
        }
        match &pool {
            Some(pool) => wait_in!(pool.in_place_scope),
            None => wait_in!(rayon::in_place_scope),
        }
        results.unwrap_or_default()
    });
    if let Some(e) = raised {
        return Err(e);
    }
    let out = PyList::empty(py);
    for r in results {
        out.append(trace_dict(py, r.map_err(sim_err)?)?)?;
    }
    Ok(out)
}

/// The rayon pool of `threads` workers for [`simulate_system_batch`], built once per thread
/// count and kept (the diagnosis calls the batch thousands of times); `None` for 0 (rayon's
/// default pool) or if a pool cannot be built (the batch then runs on the default pool).
fn batch_pool(threads: usize) -> Option<Arc<rayon::ThreadPool>> {
    static POOLS: Mutex<Vec<(usize, Arc<rayon::ThreadPool>)>> = Mutex::new(Vec::new());
    if threads == 0 {
        return None;
    }
    let mut pools = POOLS.lock().ok()?;
    if let Some((_, p)) = pools.iter().find(|(n, _)| *n == threads) {
        return Some(Arc::clone(p));
    }
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .ok()?,
    );
    pools.push((threads, Arc::clone(&pool)));
    Some(pool)
}

fn trace_dict(py: Python<'_>, tr: Trace) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("stats", stats_dict(py, &tr.stats)?)?;
    put_arrays!(d, py, tr;
        time_s, reference_m, reference_counts, position_m, motor_position_m,
        velocity_m_per_s, encoder_counts, current_a, motor_voltage_v, command, dac_code,
        p_term, i_term, d_term, flags, motor_friction_force_n, table_friction_force_n,
        stuck, interferometer_m);
    d.set_item("error_counts", tr.error.into_pyarray(py))?;
    Ok(d)
}

/// Drive the component plant of a `System` alone (actuator command and force per sample).
#[pyfunction]
#[pyo3(signature = (system, voltage_v, sample_period_s, force_n=None))]
fn simulate_system_open_loop<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    voltage_v: PyReadonlyArray1<'py, f64>,
    sample_period_s: f64,
    force_n: Option<PyReadonlyArray1<'py, f64>>,
) -> PyResult<Bound<'py, PyDict>> {
    let system: PySystem = extract_config(system, "system", "", "a System")?;
    let cfg = build_system(&system, 0, 0.0).map_err(config_err)?;
    let u: Vec<f64> = voltage_v.as_array().to_vec();
    let f = optional_series(&force_n);
    let mut signals = SignalPoll::new();
    let tr = py.detach(|| {
        run_drive_open_loop_polled(&cfg, &u, &f, sample_period_s, &mut || signals.poll())
    });
    let tr = signals.finish(tr)?;
    let d = PyDict::new(py);
    d.set_item("stats", stats_dict(py, &tr.stats)?)?;
    put_arrays!(d, py, tr;
        time_s, position_m, motor_position_m, velocity_m_per_s, motor_friction_force_n,
        table_friction_force_n, stuck);
    Ok(d)
}

enum PyAnyFriction {
    Table(PyTableFriction),
    Dahl(PyDahl),
}

config_enum!(PyAnyFriction: Table(PyTableFriction) = "Gms", Table(PyTableFriction) = "LuGre",
    Table(PyTableFriction) = "StaticFrictionMap", Dahl(PyDahl) = "DahlFriction");

/// The force of one friction component along a prescribed motion.
#[pyfunction]
#[pyo3(signature = (friction, time_s, position_m, velocity_m_per_s, integrator, terms=Vec::new()))]
fn friction_response<'py>(
    py: Python<'py>,
    friction: &Bound<'py, PyAny>,
    time_s: PyReadonlyArray1<'py, f64>,
    position_m: PyReadonlyArray1<'py, f64>,
    velocity_m_per_s: PyReadonlyArray1<'py, f64>,
    integrator: &Bound<'py, PyAny>,
    terms: Vec<(f64, f64, f64)>,
) -> PyResult<Bound<'py, PyAny>> {
    let friction: PyAnyFriction = extract_config(
        friction,
        "friction",
        "",
        "one of DahlFriction, StaticFrictionMap, LuGre, Gms",
    )?;
    let integrator: PyIntegrator =
        extract_config(integrator, "integrator", "", "an IntegratorOptions")?;
    let tf = match &friction {
        PyAnyFriction::Table(t) => t.to_core().map_err(config_err)?,
        PyAnyFriction::Dahl(d) => TableFriction::Dahl(DahlFriction {
            coulomb_force_n: d.coulomb_force_n,
            stiffness_n_per_m: d.stiffness_n_per_m,
            exponent: d.exponent,
        }),
    };
    let mut m = Modulation::default();
    modulation(&terms, &mut m).map_err(config_err)?;
    let opts = IntegratorOptions::from(&integrator);
    let (t, x, v) = (
        time_s.as_array().to_vec(),
        position_m.as_array().to_vec(),
        velocity_m_per_s.as_array().to_vec(),
    );
    let mut signals = SignalPoll::new();
    let f = py.detach(|| {
        crate::drive::friction_response_polled(&tf, &m, &t, &x, &v, &opts, &mut || signals.poll())
    });
    let f = signals.finish(f)?;
    Ok(f.into_pyarray(py).into_any())
}

/// Validate a whole `System` (raises ConfigError naming the field).
#[pyfunction]
fn validate_system(system: &Bound<'_, PyAny>) -> PyResult<()> {
    let system: PySystem = extract_config(system, "system", "", "a System")?;
    build_system(&system, 0, 0.0)
        .map(|_| ())
        .map_err(config_err)
}

/// Drive the plant alone with a held voltage per sample.
#[pyfunction]
fn simulate_open_loop<'py>(
    py: Python<'py>,
    plant: &Bound<'py, PyAny>,
    integrator: &Bound<'py, PyAny>,
    voltage_v: PyReadonlyArray1<'py, f64>,
    sample_period_s: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let plant: PyPlant = extract_config(plant, "plant", "", "a Plant")?;
    let integrator: PyIntegrator =
        extract_config(integrator, "integrator", "", "an IntegratorOptions")?;
    let axis = AxisParams::from(&plant);
    let opts = IntegratorOptions::from(&integrator);
    let u: Vec<f64> = voltage_v.as_array().to_vec();
    let mut signals = SignalPoll::new();
    let tr = py
        .detach(|| run_open_loop_polled(&axis, &opts, &u, sample_period_s, &mut || signals.poll()));
    let tr = signals.finish(tr)?;
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
    controller: &Bound<'py, PyAny>,
    reference_counts: PyReadonlyArray1<'py, i64>,
    measured_counts: PyReadonlyArray1<'py, i64>,
) -> PyResult<Bound<'py, PyDict>> {
    let controller: PyPid = extract_config(controller, "controller", "", "an FpgaPid")?;
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

/// Run the cascade controller alone on given reference and measured positions (m).
#[pyfunction]
fn cascade_run<'py>(
    py: Python<'py>,
    controller: &Bound<'py, PyAny>,
    reference_m: PyReadonlyArray1<'py, f64>,
    position_m: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let controller: PyCascade =
        extract_config(controller, "controller", "", "a CascadeController")?;
    let cfg = CascadeConfig {
        kp_per_s: controller.kp_per_s,
        kv_v_s_per_m: controller.kv_v_s_per_m,
        sample_period_s: controller.sample_period_s,
        saturation_v: controller.saturation_v,
    };
    let mut c = crate::control::Cascade::new(cfg).map_err(config_err)?;
    let r = reference_m.as_array();
    let y = position_m.as_array();
    if r.len() != y.len() {
        return Err(config_err(CoreConfigError::new(
            "position_m (length)",
            y.len(),
            format!("the length of reference_m = {}", r.len()),
        )));
    }
    let u: Vec<f64> = r
        .iter()
        .zip(y.iter())
        .map(|(a, b)| c.step(*a, *b).0)
        .collect();
    Ok(u.into_pyarray(py).into_any())
}

/// Requantise raw integers with `frac_in` fraction bits into `fmt`; returns (raw, overflow).
#[pyfunction]
fn fxp_requantize<'py>(
    py: Python<'py>,
    raw: PyReadonlyArray1<'py, i64>,
    frac_in: i32,
    fmt: &Bound<'py, PyAny>,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let fmt: PyFxp = extract_config(fmt, "fmt", "", "an Fxp")?;
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
    integ.set_item("max_events", o.max_events)?;
    d.set_item("integrator", integ)?;
    let gains = PyDict::new(py);
    for step in [100e-6, 500e-6, 1e-3, 10e-3] {
        gains.set_item(step, crate::presets::table1_gains(step))?;
    }
    d.set_item("table1_gains", gains)?;
    Ok(d)
}

/// Stop flag of the campaigns of this process (set from Python on Ctrl-C).
static CAMPAIGN_STOP: AtomicBool = AtomicBool::new(false);
/// Finished trials of the campaigns of this process since the last reset.
static CAMPAIGN_PROGRESS: AtomicUsize = AtomicUsize::new(0);

/// Ask the running campaigns of this process to stop (within 256 control samples).
#[pyfunction]
fn campaign_request_stop() {
    CAMPAIGN_STOP.store(true, Ordering::Relaxed);
}

/// Clear the stop flag and the progress counter (before a new campaign).
#[pyfunction]
fn campaign_reset() {
    CAMPAIGN_STOP.store(false, Ordering::Relaxed);
    CAMPAIGN_PROGRESS.store(0, Ordering::Relaxed);
}

/// Whether a stop has been requested since the last reset.
#[pyfunction]
fn campaign_stop_requested() -> bool {
    CAMPAIGN_STOP.load(Ordering::Relaxed)
}

/// Trials finished (completed, failed or not started) since the last reset.
#[pyfunction]
fn campaign_progress() -> usize {
    CAMPAIGN_PROGRESS.load(Ordering::Relaxed)
}

/// Run trials `trial_start..trial_stop` of one cycle on a local pool of `threads` threads,
/// without the GIL. Trial i has seed `stream_seed(seed, i)`. Returns a dict: `position_m`
/// and `encoder_m` (float64, shape (n_trials, n_measure), NaN for failed trials), `status`
/// (int8, shape (n_trials,)), and for the trials that did not complete `failed_trial`
/// (uint64), `failed_t_s` (float64), `failed_message` and `failed_state` (lists).
#[pyfunction]
#[pyo3(signature = (system, reference_m, measure_index, trial_start, trial_stop, seed, threads))]
fn campaign_run<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    reference_m: PyReadonlyArray1<'py, f64>,
    measure_index: PyReadonlyArray1<'py, i64>,
    trial_start: u64,
    trial_stop: u64,
    seed: u64,
    threads: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let system: PySystem = extract_config(system, "system", "", "a System")?;
    let reference: Vec<f64> = reference_m.as_array().to_vec();
    let x0 = reference.first().copied().unwrap_or(0.0);
    let cfg = build_system(&system, seed, x0).map_err(config_err)?;
    let idx = measure_index
        .as_array()
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            usize::try_from(i).map_err(|_| {
                config_err(CoreConfigError::new(
                    format!("measure_index[{k}]"),
                    i,
                    "a non-negative sample index",
                ))
            })
        })
        .collect::<PyResult<Vec<usize>>>()?;
    let campaign = Campaign {
        config: &cfg,
        reference_m: &reference,
        measure_index: &idx,
    };
    let out = py
        .detach(|| {
            run_campaign(
                &campaign,
                seed,
                trial_start,
                trial_stop,
                threads,
                Some(&CAMPAIGN_STOP),
                Some(&CAMPAIGN_PROGRESS),
            )
        })
        .map_err(config_err)?;
    let (n, m) = (out.n_trials(), out.n_measure);
    let d = PyDict::new(py);
    d.set_item(
        "position_m",
        out.position_m.into_pyarray(py).reshape([n, m])?,
    )?;
    d.set_item("encoder_m", out.encoder_m.into_pyarray(py).reshape([n, m])?)?;
    let status: Vec<i8> = out.status.iter().map(|&s| s as i8).collect();
    d.set_item("status", status.into_pyarray(py))?;
    let trial: Vec<u64> = out.failures.iter().map(|f| f.trial).collect();
    let t_s: Vec<f64> = out.failures.iter().map(|f| f.t_s).collect();
    d.set_item("failed_trial", trial.into_pyarray(py))?;
    d.set_item("failed_t_s", t_s.into_pyarray(py))?;
    let (messages, states): (Vec<String>, Vec<Vec<f64>>) = out
        .failures
        .into_iter()
        .map(|f| (f.message, f.state))
        .unzip();
    d.set_item("failed_message", messages)?;
    d.set_item("failed_state", states)?;
    Ok(d)
}

/// Validate a plant (raises ConfigError naming the field).
#[pyfunction]
fn validate_plant(plant: &Bound<'_, PyAny>) -> PyResult<()> {
    let plant: PyPlant = extract_config(plant, "plant", "", "a Plant")?;
    AxisParams::from(&plant).validate().map_err(config_err)
}

/// Validate a controller, including the quantisation of gains and range into their formats.
#[pyfunction]
fn validate_controller(controller: &Bound<'_, PyAny>) -> PyResult<()> {
    let controller: PyPid = extract_config(controller, "controller", "", "an FpgaPid")?;
    let cfg = controller.to_core().map_err(config_err)?;
    Pid::new(cfg).map(|_| ()).map_err(config_err)
}

/// Validate integrator options.
#[pyfunction]
fn validate_integrator(integrator: &Bound<'_, PyAny>) -> PyResult<()> {
    let integrator: PyIntegrator =
        extract_config(integrator, "integrator", "", "an IntegratorOptions")?;
    IntegratorOptions::from(&integrator)
        .validate()
        .map_err(config_err)
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("ConfigError", py.get_type::<ConfigError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add("ConfigTypeError", config_type_error_class(py)?)?;
    m.add_function(wrap_pyfunction!(simulate_system, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_system_batch, m)?)?;
    m.add_function(wrap_pyfunction!(validate_system, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_system_open_loop, m)?)?;
    m.add_function(wrap_pyfunction!(friction_response, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_open_loop, m)?)?;
    m.add_function(wrap_pyfunction!(pid_run, m)?)?;
    m.add_function(wrap_pyfunction!(cascade_run, m)?)?;
    m.add_function(wrap_pyfunction!(fxp_requantize, m)?)?;
    m.add_function(wrap_pyfunction!(seed_values, m)?)?;
    m.add_function(wrap_pyfunction!(validate_plant, m)?)?;
    m.add_function(wrap_pyfunction!(validate_controller, m)?)?;
    m.add_function(wrap_pyfunction!(validate_integrator, m)?)?;
    m.add_function(wrap_pyfunction!(campaign_run, m)?)?;
    m.add_function(wrap_pyfunction!(campaign_request_stop, m)?)?;
    m.add_function(wrap_pyfunction!(campaign_reset, m)?)?;
    m.add_function(wrap_pyfunction!(campaign_stop_requested, m)?)?;
    m.add_function(wrap_pyfunction!(campaign_progress, m)?)?;
    m.add_function(wrap_pyfunction!(runs_request_stop, m)?)?;
    m.add_function(wrap_pyfunction!(runs_reset, m)?)?;
    m.add_function(wrap_pyfunction!(runs_stop_requested, m)?)?;
    Ok(())
}
