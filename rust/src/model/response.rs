//! A friction component driven along a prescribed motion: the force it produces for a
//! measured (time, position, velocity) record. Used by the friction identification and by
//! the tests of each model's physics. Between samples the velocity and position are
//! interpolated linearly; the internal states are integrated by RODAS4.
use super::component::Drive;
use super::component_params::{Modulation, TableFriction};
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, OdeSystem, Rodas4, SegmentEnd};
use nalgebra::{SMatrix, SVector};

/// Internal states plus time and the memory lag: [t, w, z_1..z_8].
const N: usize = 10;

struct Prescribed<'a> {
    friction: &'a TableFriction,
    modulation: &'a Modulation,
    t0: f64,
    dt: f64,
    x: (f64, f64),
    v: (f64, f64),
    lag_s: Option<f64>,
}

impl Prescribed<'_> {
    fn motion(&self, t: f64) -> (f64, f64) {
        let a = ((t - self.t0) / self.dt).clamp(0.0, 1.0);
        (
            self.x.0 + a * (self.x.1 - self.x.0),
            self.v.0 + a * (self.v.1 - self.v.0),
        )
    }
}

impl OdeSystem<N> for Prescribed<'_> {
    fn rhs(&self, y: &SVector<f64, N>, dy: &mut SVector<f64, N>) {
        dy.fill(0.0);
        let (x, v) = self.motion(y[0]);
        dy[0] = 1.0;
        if let Some(tau) = self.lag_s {
            dy[1] = (v - y[1]) / tau;
        }
        let s = Drive::modulation_factor(self.modulation, x);
        let n = self.friction.n_states();
        let d = v.signum() * f64::from(u8::from(v != 0.0));
        let mut rates = [0.0; 8];
        self.friction
            .dynamic(&y.as_slice()[2..2 + n], v, d, s, Some(&mut rates[..n]));
        for i in 0..n {
            dy[2 + i] = rates[i];
        }
    }

    fn jacobian(&self, y: &SVector<f64, N>, jac: &mut SMatrix<f64, N, N>) {
        let mut f0 = SVector::<f64, N>::zeros();
        let mut f1 = SVector::<f64, N>::zeros();
        self.rhs(y, &mut f0);
        let mut yp = *y;
        for c in 1..N {
            let h = 1e-7 * yp[c].abs().max(1e-9);
            let keep = yp[c];
            yp[c] = keep + h;
            self.rhs(&yp, &mut f1);
            yp[c] = keep;
            for r in 0..N {
                jac[(r, c)] = (f1[r] - f0[r]) / h;
            }
        }
        for r in 0..N {
            jac[(r, 0)] = 0.0;
        }
    }
}

/// The force of `friction` (with its spatial `modulation`) along the prescribed motion,
/// one value per sample, starting from relaxed internal states (z = 0). Static maps return
/// their sliding force (0 where v = 0; with `memory_lag_s` the Stribeck term follows the
/// lagged velocity).
pub fn friction_response(
    friction: &TableFriction,
    modulation: &Modulation,
    time_s: &[f64],
    position_m: &[f64],
    velocity_m_per_s: &[f64],
    options: &IntegratorOptions,
) -> Result<Vec<f64>, SimError> {
    friction_response_polled(
        friction,
        modulation,
        time_s,
        position_m,
        velocity_m_per_s,
        options,
        &mut || false,
    )
}

/// [`friction_response`] asking `poll` every `POLL_EVERY_SAMPLES` samples whether to stop
/// (true: [`SimError::Interrupted`]). A force that is not finite is
/// [`SimError::NonFinite`].
pub fn friction_response_polled(
    friction: &TableFriction,
    modulation: &Modulation,
    time_s: &[f64],
    position_m: &[f64],
    velocity_m_per_s: &[f64],
    options: &IntegratorOptions,
    poll: &mut dyn FnMut() -> bool,
) -> Result<Vec<f64>, SimError> {
    let n = time_s.len();
    if position_m.len() != n || velocity_m_per_s.len() != n || n == 0 {
        return Err(ConfigError::new(
            "position_m, velocity_m_per_s (length)",
            format!("{}, {}", position_m.len(), velocity_m_per_s.len()),
            format!("both equal to the length of time_s = {n} (> 0)"),
        )
        .into());
    }
    for (name, arr) in [
        ("time_s", time_s),
        ("position_m", position_m),
        ("velocity_m_per_s", velocity_m_per_s),
    ] {
        if let Some((k, v)) = arr.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(ConfigError::new(format!("{name}[{k}]"), v, "a finite number").into());
        }
    }
    if let Some(k) = (1..n).find(|&k| time_s[k] <= time_s[k - 1]) {
        return Err(ConfigError::new(
            format!("time_s[{k}]"),
            time_s[k],
            format!(
                "strictly greater than time_s[{}] = {}",
                k - 1,
                time_s[k - 1]
            ),
        )
        .into());
    }
    friction
        .validate()
        .map_err(|e| e.within("table_friction").within("friction"))?;
    modulation
        .validate()
        .map_err(|e| e.within("table_modulation").within("friction"))?;
    let mut integ = Rodas4::<N>::new(*options).map_err(|e| e.within("integrator"))?;
    let lag_s = match friction {
        TableFriction::Static(m) => m.memory_lag_s,
        _ => None,
    };
    let mut atol = SVector::<f64, N>::repeat(options.atol_position_m);
    atol[0] = 1e-9;
    atol[1] = options.atol_position_m * 10.0;
    if let TableFriction::Dahl(d) = friction {
        atol[2] = options.atol_position_m * d.law.stiffness_n_per_m;
    }
    let mut y = SVector::<f64, N>::zeros();
    y[0] = time_s[0];
    y[1] = velocity_m_per_s[0];
    let force = |y: &SVector<f64, N>, k: usize| -> f64 {
        let v = velocity_m_per_s[k];
        let s = Drive::modulation_factor(modulation, position_m[k]);
        let d = v.signum() * f64::from(u8::from(v != 0.0));
        let nz = friction.n_states();
        let dynamic = friction.dynamic(&y.as_slice()[2..2 + nz], v, d, s, None);
        match friction {
            TableFriction::Static(m) if v != 0.0 => {
                let w = if lag_s.is_some() { y[1] } else { v };
                m.sliding_force(v, w, d, s)
            }
            _ => dynamic,
        }
    };
    let finite = |f: f64, k: usize, y: &SVector<f64, N>| {
        if f.is_finite() {
            Ok(f)
        } else {
            Err(SimError::NonFinite {
                t_s: time_s[k],
                state: y.iter().copied().collect(),
            })
        }
    };
    let mut out = Vec::with_capacity(n);
    out.push(finite(force(&y, 0), 0, &y)?);
    for k in 1..n {
        if k % crate::integrate::POLL_EVERY_SAMPLES == 0 && poll() {
            return Err(SimError::Interrupted { t_s: time_s[k] });
        }
        let sys = Prescribed {
            friction,
            modulation,
            t0: time_s[k - 1],
            dt: time_s[k] - time_s[k - 1],
            x: (position_m[k - 1], position_m[k]),
            v: (velocity_m_per_s[k - 1], velocity_m_per_s[k]),
            lag_s,
        };
        match integ.integrate(&sys, time_s[k - 1], time_s[k], &mut y, &atol)? {
            SegmentEnd::Reached | SegmentEnd::Event { .. } => {}
        }
        y[0] = time_s[k];
        out.push(finite(force(&y, k), k, &y)?);
    }
    Ok(out)
}
