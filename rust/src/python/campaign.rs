//! Campaigns: many seeded trials of one cycle on a local pool, stopped and watched through
//! the [`CampaignControl`] passed to the call (one per campaign, nothing shared between the
//! campaigns of a process).
use super::arrays::campaign_dict;
use super::errors::{config_err, extract_config};
use super::extract::PySystem;
use crate::error::ConfigError as CoreConfigError;
use crate::sim::{build_system, run_campaign, Campaign};
use numpy::PyReadonlyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Stop request and progress of one campaign: pass it to every `campaign_run` call of the
/// campaign; `request_stop()` from any thread stops its trials within 256 control samples
/// (they end `INTERRUPTED`, the ones not started `NOT_STARTED`), and `progress` counts the
/// trials finished (completed, failed or not started).
#[pyclass(frozen, module = "nanostage._core", name = "CampaignControl")]
#[derive(Default)]
pub(crate) struct CampaignControl {
    stop: AtomicBool,
    progress: AtomicUsize,
}

#[pymethods]
impl CampaignControl {
    #[new]
    fn new() -> Self {
        Self::default()
    }

    /// Ask the campaign's running and remaining trials to stop.
    fn request_stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    /// Whether a stop has been requested.
    #[getter]
    fn stop_requested(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Trials finished so far.
    #[getter]
    fn progress(&self) -> usize {
        self.progress.load(Ordering::Relaxed)
    }
}

/// Run trials `trial_start..trial_stop` of one cycle on a local pool of `threads` threads,
/// without the GIL. Trial i has seed `stream_seed(seed, i)`. Returns a dict: `position_m`
/// and `encoder_m` (float64, shape (n_trials, n_measure), NaN for failed trials), `status`
/// (int8, shape (n_trials,)), and for the trials that did not complete `failed_trial`
/// (uint64), `failed_t_s` (float64), `failed_message` and `failed_state` (lists).
#[pyfunction]
#[pyo3(signature = (system, reference_m, measure_index, trial_start, trial_stop, seed, threads, *, control=None))]
fn campaign_run<'py>(
    py: Python<'py>,
    system: &Bound<'py, PyAny>,
    reference_m: PyReadonlyArray1<'py, f64>,
    measure_index: PyReadonlyArray1<'py, i64>,
    trial_start: u64,
    trial_stop: u64,
    seed: u64,
    threads: usize,
    control: Option<&Bound<'py, CampaignControl>>,
) -> PyResult<Bound<'py, PyDict>> {
    let system: PySystem = extract_config(system, "system", "", "a System")?;
    let reference: Vec<f64> = reference_m.as_array().to_vec();
    let x0 = reference.first().copied().unwrap_or(0.0);
    let spec = system.to_spec().map_err(config_err)?;
    let cfg = build_system(&spec, seed, x0).map_err(config_err)?;
    let fresh = CampaignControl::default();
    let control = control.map_or(&fresh, |c| c.get());
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
                Some(&control.stop),
                Some(&control.progress),
            )
        })
        .map_err(config_err)?;
    campaign_dict(py, out)
}

/// Add [`CampaignControl`] and `campaign_run` to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<CampaignControl>()?;
    m.add_function(wrap_pyfunction!(campaign_run, m)?)?;
    Ok(())
}
