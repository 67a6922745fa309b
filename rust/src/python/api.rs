//! The entry points of `_core`: extract and validate every input while holding the GIL,
//! compute without it (`py.detach`), hand the results back as numpy arrays. Long calls poll
//! for Ctrl-C while they run ([`SignalPoll`], [`simulate_system_batch`]): SIGINT's
//! `KeyboardInterrupt` stops them within a fraction of a second and is what the call raises.
//! A [`StopFlag`] passed to a call stops it from any thread.
use super::arrays::{optional_series, put_arrays, stats_dict, trace_dict};
use super::errors::{config_err, extract_config, sim_err};
use super::extract::{PyAnyFriction, PyCascade, PyFxp, PyIntegrator, PyPid, PyPlant, PySystem};
use crate::control::{Cascade, Pid};
use crate::error::{ConfigError as CoreConfigError, SimError};
use crate::integrate::IntegratorOptions;
use crate::model::{AxisParams, Modulation};
use crate::sim::{
    build_system, modulation, run_drive_open_loop_polled, run_extended_polled,
    run_open_loop_polled, ExtendedConfig, FxpSpec, KnownInputs, PidSpec, Trace,
};
use numpy::{IntoPyArray, PyReadonlyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

/// A stop request for the runs it is passed to (`stop=`): `request_stop()` from any thread
/// (e.g. a SIGINT handler) makes them end with `SimulationError` ("interrupted at t = ...")
/// within a few control samples.
#[pyclass(frozen, module = "nanostage._core", name = "StopFlag")]
#[derive(Default)]
pub(crate) struct StopFlag {
    flag: Arc<AtomicBool>,
}

#[pymethods]
impl StopFlag {
    #[new]
    fn new() -> Self {
        Self::default()
    }

    /// Ask the runs given this flag to stop.
    fn request_stop(&self) {
        self.flag.store(true, Ordering::Relaxed);
    }

    /// Whether a stop has been requested.
    #[getter]
    fn stop_requested(&self) -> bool {
        self.flag.load(Ordering::Relaxed)
    }
}

/// The shared flag of an optional [`StopFlag`] argument (a fresh one when none is given).
fn stop_of(stop: Option<&Bound<'_, StopFlag>>) -> Arc<AtomicBool> {
    stop.map_or_else(Arc::default, |s| Arc::clone(&s.get().flag))
}

/// A system's run configuration from its Python description.
fn system_config(
    system: &Bound<'_, PyAny>,
    arg: &str,
    prefix: &str,
    seed: u64,
    initial_position_m: f64,
) -> PyResult<ExtendedConfig> {
    let system: PySystem = extract_config(system, arg, prefix, "a System")?;
    let spec = system.to_spec().map_err(config_err)?;
    build_system(&spec, seed, initial_position_m).map_err(config_err)
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

/// Ctrl-C for a run computed without the GIL on the calling thread: the run asks
/// [`Self::poll`] every few control samples; at most every [`SIGNAL_POLL_INTERVAL`] the poll
/// takes the GIL back and runs Python's signal handlers (on the main thread only; elsewhere
/// it stops looking). A handler that raises (SIGINT's `KeyboardInterrupt`) stops the run, and
/// [`Self::finish`] raises that exception instead of the run's result. The
/// call's [`StopFlag`] stops the run too (on any thread).
struct SignalPoll {
    stop: Arc<AtomicBool>,
    last: Instant,
    main_thread: Option<bool>,
    raised: Option<PyErr>,
}

impl SignalPoll {
    fn new(stop: Arc<AtomicBool>) -> Self {
        Self {
            stop,
            last: Instant::now(),
            main_thread: None,
            raised: None,
        }
    }

    /// Whether the run should stop.
    fn poll(&mut self) -> bool {
        if self.raised.is_some() || self.stop.load(Ordering::Relaxed) {
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

/// Run the closed loop of a `System`; returns a dict of per-sample numpy arrays plus `stats`.
#[pyfunction]
#[pyo3(signature = (system, reference_m, force_disturbance_n=None, command_disturbance_v=None, seed=0, initial_position_m=0.0, *, stop=None))]
fn simulate_system<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    reference_m: PyReadonlyArray1<'py, f64>,
    force_disturbance_n: Option<PyReadonlyArray1<'py, f64>>,
    command_disturbance_v: Option<PyReadonlyArray1<'py, f64>>,
    seed: u64,
    initial_position_m: f64,
    stop: Option<&Bound<'py, StopFlag>>,
) -> PyResult<Bound<'py, PyDict>> {
    let cfg = system_config(system, "system", "", seed, initial_position_m)?;
    let reference: Vec<f64> = reference_m.as_array().to_vec();
    let force = optional_series(&force_disturbance_n);
    let command = optional_series(&command_disturbance_v);
    let mut signals = SignalPoll::new(stop_of(stop));
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

/// Run the closed loops of several `System`s at once, in parallel (rayon, on `threads` threads;
/// 0: rayon's default pool) with the GIL released once for the whole batch; returns the
/// dicts of [`simulate_system`] in the order given. Every configuration is checked before any
/// simulation starts; the first failed run (in the order given) raises its error.
///
/// Called from the main thread, the calling thread waits for the batch and looks for
/// pending signals every [`SIGNAL_POLL_INTERVAL`]; a handler that raises (Ctrl-C) sets the
/// batch's stop flag, which every run polls every few control samples, and the call raises
/// that exception once the runs have stopped.
#[pyfunction]
#[pyo3(signature = (systems, references_m, force_disturbances_n, command_disturbances_v, seeds, initial_positions_m, threads=0, *, stop=None))]
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
    stop: Option<&Bound<'py, StopFlag>>,
) -> PyResult<Bound<'py, PyList>> {
    let run_stop = stop_of(stop);
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
        let cfg = system_config(
            &systems[i],
            &format!("systems[{i}]"),
            &format!("systems[{i}]."),
            seeds[i],
            initial_positions_m[i],
        )?;
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
                    &mut || stop.load(Ordering::Relaxed) || run_stop.load(Ordering::Relaxed),
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

/// The rayon pool of `threads` threads for [`simulate_system_batch`], built once per thread
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

#[pyfunction]
#[pyo3(signature = (system, voltage_v, sample_period_s, force_n=None, *, stop=None))]
fn simulate_system_open_loop<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    voltage_v: PyReadonlyArray1<'py, f64>,
    sample_period_s: f64,
    force_n: Option<PyReadonlyArray1<'py, f64>>,
    stop: Option<&Bound<'py, StopFlag>>,
) -> PyResult<Bound<'py, PyDict>> {
    let cfg = system_config(system, "system", "", 0, 0.0)?;
    let u: Vec<f64> = voltage_v.as_array().to_vec();
    let f = optional_series(&force_n);
    let mut signals = SignalPoll::new(stop_of(stop));
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

#[pyfunction]
#[pyo3(signature = (friction, time_s, position_m, velocity_m_per_s, integrator, terms=Vec::new(), *, stop=None))]
fn friction_response<'py>(
    py: Python<'py>,
    friction: &Bound<'py, PyAny>,
    time_s: PyReadonlyArray1<'py, f64>,
    position_m: PyReadonlyArray1<'py, f64>,
    velocity_m_per_s: PyReadonlyArray1<'py, f64>,
    integrator: &Bound<'py, PyAny>,
    terms: Vec<(f64, f64, f64)>,
    stop: Option<&Bound<'py, StopFlag>>,
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
        PyAnyFriction::Dahl(d) => d.to_table(),
    };
    let mut m = Modulation::default();
    modulation(&terms, &mut m).map_err(config_err)?;
    let opts = IntegratorOptions::from(&integrator);
    let (t, x, v) = (
        time_s.as_array().to_vec(),
        position_m.as_array().to_vec(),
        velocity_m_per_s.as_array().to_vec(),
    );
    let mut signals = SignalPoll::new(stop_of(stop));
    let f = py.detach(|| {
        crate::model::friction_response_polled(&tf, &m, &t, &x, &v, &opts, &mut || signals.poll())
    });
    let f = signals.finish(f)?;
    Ok(f.into_pyarray(py).into_any())
}

/// Validate a whole `System` (raises ConfigError naming the field).
#[pyfunction]
fn validate_system(system: &Bound<'_, PyAny>) -> PyResult<()> {
    system_config(system, "system", "", 0, 0.0).map(|_| ())
}

/// Drive the plant alone with a held voltage per sample.
#[pyfunction]
#[pyo3(signature = (plant, integrator, voltage_v, sample_period_s, *, stop=None))]
fn simulate_open_loop<'py>(
    py: Python<'py>,
    plant: &Bound<'py, PyAny>,
    integrator: &Bound<'py, PyAny>,
    voltage_v: PyReadonlyArray1<'py, f64>,
    sample_period_s: f64,
    stop: Option<&Bound<'py, StopFlag>>,
) -> PyResult<Bound<'py, PyDict>> {
    let plant: PyPlant = extract_config(plant, "plant", "", "a Plant")?;
    let integrator: PyIntegrator =
        extract_config(integrator, "integrator", "", "an IntegratorOptions")?;
    if plant.dahl.asymmetry != 0.0 {
        // The rigid plant has no direction asymmetry of its Dahl law.
        return Err(config_err(CoreConfigError::new(
            "plant.dahl.asymmetry",
            crate::error::format_value(plant.dahl.asymmetry),
            "0 for the rigid plant alone (simulate_plant); nanostage.simulate_open_loop of a \
             System runs the asymmetric law",
        )));
    }
    let axis = AxisParams::from(&plant);
    let opts = IntegratorOptions::from(&integrator);
    let u: Vec<f64> = voltage_v.as_array().to_vec();
    let mut signals = SignalPoll::new(stop_of(stop));
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
    let cfg = PidSpec::from(&controller).to_core().map_err(config_err)?;
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
    let mut c = Cascade::new((&controller).into()).map_err(config_err)?;
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
    let f = FxpSpec::from(&fmt).to_core("fmt").map_err(config_err)?;
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

/// Validate a plant (raises ConfigError naming the field).
#[pyfunction]
fn validate_plant(plant: &Bound<'_, PyAny>) -> PyResult<()> {
    let plant: PyPlant = extract_config(plant, "plant", "", "a Plant")?;
    AxisParams::from(&plant).validate().map_err(config_err)?;
    plant.validate_extra().map_err(config_err)
}

/// Validate a controller, including the quantisation of gains and range into their formats.
#[pyfunction]
fn validate_controller(controller: &Bound<'_, PyAny>) -> PyResult<()> {
    let controller: PyPid = extract_config(controller, "controller", "", "an FpgaPid")?;
    let cfg = PidSpec::from(&controller).to_core().map_err(config_err)?;
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

/// Add the entry points of this file and [`StopFlag`] to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<StopFlag>()?;
    m.add_function(wrap_pyfunction!(simulate_system, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_system_batch, m)?)?;
    m.add_function(wrap_pyfunction!(validate_system, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_system_open_loop, m)?)?;
    m.add_function(wrap_pyfunction!(friction_response, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_open_loop, m)?)?;
    m.add_function(wrap_pyfunction!(pid_run, m)?)?;
    m.add_function(wrap_pyfunction!(cascade_run, m)?)?;
    m.add_function(wrap_pyfunction!(fxp_requantize, m)?)?;
    m.add_function(wrap_pyfunction!(validate_plant, m)?)?;
    m.add_function(wrap_pyfunction!(validate_controller, m)?)?;
    m.add_function(wrap_pyfunction!(validate_integrator, m)?)?;
    Ok(())
}
