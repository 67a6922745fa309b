//! Results into numpy arrays and dicts: owned buffers move into arrays without a copy
//! (`into_pyarray`).
use crate::integrate::Stats;
use crate::sim::{CampaignOutput, Trace};
use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray1};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The samples of an optional series (empty: none).
pub(crate) fn optional_series(a: &Option<PyReadonlyArray1<'_, f64>>) -> Vec<f64> {
    a.as_ref().map_or_else(Vec::new, |a| a.as_array().to_vec())
}

/// Move the named `Vec` fields of `tr` into the dict `d` as numpy arrays under their names.
macro_rules! put_arrays {
    ($d:ident, $py:ident, $tr:ident; $($f:ident),+ $(,)?) => {
        $( $d.set_item(stringify!($f), $tr.$f.into_pyarray($py))?; )+
    };
}
pub(crate) use put_arrays;

/// The integrator's work counters as a dict.
pub(crate) fn stats_dict<'py>(py: Python<'py>, s: &Stats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("n_rhs", s.n_rhs)?;
    d.set_item("n_jac", s.n_jac)?;
    d.set_item("n_lu", s.n_lu)?;
    d.set_item("n_accepted", s.n_accepted)?;
    d.set_item("n_rejected", s.n_rejected)?;
    d.set_item("n_events", s.n_events)?;
    Ok(d)
}

/// A closed-loop trace as a dict of per-sample arrays plus `stats`.
pub(crate) fn trace_dict(py: Python<'_>, tr: Trace) -> PyResult<Bound<'_, PyDict>> {
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

/// A campaign's output as a dict (see `campaign_run`).
pub(crate) fn campaign_dict(py: Python<'_>, out: CampaignOutput) -> PyResult<Bound<'_, PyDict>> {
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
