//! Open-loop runs: a voltage (and force) series held sample by sample on the rigid seed plant
//! or on the component plant of a configuration.
use super::closed_loop::ExtendedConfig;
use super::plant::AnyPlant;
use super::trace::{check_samples, check_series, DriveOpenLoopTrace, OpenLoopTrace};
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Rodas4, POLL_EVERY_SAMPLES};
use crate::model::{Axis, AxisParams, Inputs, Mode, Plant};

/// Drive the plant alone with `voltage_v[k]` held on [k·T, (k+1)·T).
pub fn run_open_loop(
    axis: &AxisParams,
    integrator: &IntegratorOptions,
    voltage_v: &[f64],
    sample_period_s: f64,
) -> Result<OpenLoopTrace, SimError> {
    run_open_loop_polled(axis, integrator, voltage_v, sample_period_s, &mut || false)
}

/// [`run_open_loop`] asking `poll` every [`POLL_EVERY_SAMPLES`] samples whether to stop
/// (true: [`SimError::Interrupted`]).
pub fn run_open_loop_polled(
    axis: &AxisParams,
    integrator: &IntegratorOptions,
    voltage_v: &[f64],
    sample_period_s: f64,
    poll: &mut dyn FnMut() -> bool,
) -> Result<OpenLoopTrace, SimError> {
    crate::error::check_positive("sample_period_s", sample_period_s, 10.0)?;
    check_samples(voltage_v.len())?;
    if let Some((k, v)) = voltage_v.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(ConfigError::new(format!("voltage_v[{k}]"), v, "a finite voltage").into());
    }
    let axis = Axis::new(*axis).map_err(|e| e.within("plant"))?;
    let integ = Rodas4::new(*integrator).map_err(|e| e.within("integrator"))?;
    let mut plant = Plant::new(axis, integ);
    let n = voltage_v.len();
    let mut tr = OpenLoopTrace::default();
    let record = |plant: &Plant, t: f64, u: f64, tr: &mut OpenLoopTrace| {
        let current = plant.current(u);
        if !current.is_finite() {
            return Err(SimError::NonFinite {
                t_s: t,
                state: plant.y.iter().copied().collect(),
            });
        }
        tr.time_s.push(t);
        tr.position_m.push(plant.y[0]);
        tr.velocity_m_per_s.push(plant.y[1]);
        tr.dahl_force_n.push(plant.y[2]);
        tr.current_a.push(current);
        tr.stuck.push(plant.mode == Mode::Stuck);
        Ok(())
    };
    for (k, &u) in voltage_v.iter().enumerate() {
        let t0 = k as f64 * sample_period_s;
        if k % POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: t0 });
        }
        record(&plant, t0, u, &mut tr)?;
        plant.advance_polled(u, t0, (k + 1) as f64 * sample_period_s, poll)?;
    }
    record(
        &plant,
        n as f64 * sample_period_s,
        voltage_v[n - 1],
        &mut tr,
    )?;
    tr.stats = plant.integrator.stats;
    Ok(tr)
}

/// Drive the component plant of `cfg` alone: `voltage_v[k]` (actuator command) and
/// `force_n[k]` (empty: none) held on `[k·T, (k+1)·T)`. Starts at rest at 0, the drive
/// side of a dead band at `cfg.initial_flank`.
pub fn run_drive_open_loop(
    cfg: &ExtendedConfig,
    voltage_v: &[f64],
    force_n: &[f64],
    sample_period_s: f64,
) -> Result<DriveOpenLoopTrace, SimError> {
    run_drive_open_loop_polled(cfg, voltage_v, force_n, sample_period_s, &mut || false)
}

/// [`run_drive_open_loop`] asking `poll` every [`POLL_EVERY_SAMPLES`] samples whether to
/// stop (true: [`SimError::Interrupted`]).
pub fn run_drive_open_loop_polled(
    cfg: &ExtendedConfig,
    voltage_v: &[f64],
    force_n: &[f64],
    sample_period_s: f64,
    poll: &mut dyn FnMut() -> bool,
) -> Result<DriveOpenLoopTrace, SimError> {
    crate::error::check_positive("sample_period_s", sample_period_s, 10.0)?;
    let n = voltage_v.len();
    check_samples(n)?;
    check_series("voltage_v", voltage_v, n)?;
    check_series("force_n", force_n, n)?;
    let mut plant = AnyPlant::component(&cfg.drive, cfg.integrator)?;
    plant.set_position(0.0, cfg.initial_flank);
    let mut tr = DriveOpenLoopTrace::default();
    let record = |plant: &AnyPlant, t: f64, inp: &Inputs, tr: &mut DriveOpenLoopTrace| {
        let (x_t, x_m, v_t, _, f_m, f_t, stuck) = plant.observe(inp);
        plant.check_finite(t, &[x_t, x_m, v_t, f_m, f_t])?;
        tr.time_s.push(t);
        tr.position_m.push(x_t);
        tr.motor_position_m.push(x_m);
        tr.velocity_m_per_s.push(v_t);
        tr.motor_friction_force_n.push(f_m);
        tr.table_friction_force_n.push(f_t);
        tr.stuck.push(stuck);
        Ok::<(), SimError>(())
    };
    let mut inp = Inputs::voltage(0.0);
    for (k, &u_v) in voltage_v.iter().enumerate() {
        inp = Inputs {
            u_v,
            force_n: force_n.get(k).copied().unwrap_or(0.0),
            friction_scale: 1.0,
        };
        let t0 = k as f64 * sample_period_s;
        if k % POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: t0 });
        }
        record(&plant, t0, &inp, &mut tr)?;
        plant.advance(&inp, t0, (k + 1) as f64 * sample_period_s, poll)?;
    }
    record(&plant, n as f64 * sample_period_s, &inp, &mut tr)?;
    tr.stats = plant.stats();
    Ok(tr)
}
