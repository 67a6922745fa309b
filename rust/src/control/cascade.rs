//! The cascaded position/velocity controller of a dSPACE-controlled drive (EMPS), in floating
//! point as it runs there:
//! `u(k) = kp·kv·(r(k) − y(k)) − kv·v̂(k)`, `v̂(k) = (q_f(k) − q_f(k−1))/T`,
//! `q_f(k) = (y(k) + y(k−1))/2`, i.e. `v̂(k) = (y(k) − y(k−2))/(2T)`; saturated at ±u_max.
use crate::error::{check_positive, ConfigError};

/// Cascade controller parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CascadeConfig {
    /// Position-loop gain kp, 1/s, in (0, 1e5].
    pub kp_per_s: f64,
    /// Velocity-loop gain kv, V/(m/s), in (0, 1e6].
    pub kv_v_s_per_m: f64,
    /// Sample period T, s, in (0, 1].
    pub sample_period_s: f64,
    /// Output saturation u_max, V, in (0, 1e3].
    pub saturation_v: f64,
}

impl CascadeConfig {
    /// Validate against the documented ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("kp_per_s", self.kp_per_s, 1e5)?;
        check_positive("kv_v_s_per_m", self.kv_v_s_per_m, 1e6)?;
        check_positive("sample_period_s", self.sample_period_s, 1.0)?;
        check_positive("saturation_v", self.saturation_v, 1e3)
    }
}

/// The running controller (remembers the last two measurements).
#[derive(Debug, Clone)]
pub struct Cascade {
    /// Parameters.
    pub cfg: CascadeConfig,
    prev: Option<(f64, f64)>,
}

impl Cascade {
    /// A controller with no history (the first sample fills it with itself).
    pub fn new(cfg: CascadeConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        Ok(Self { cfg, prev: None })
    }

    /// One update from the reference and the measurement, m; returns (saturated output,
    /// whether it saturated).
    pub fn step(&mut self, r_m: f64, y_m: f64) -> (f64, bool) {
        let (y1, y2) = self.prev.unwrap_or((y_m, y_m));
        let c = &self.cfg;
        let v_hat = (y_m - y2) / (2.0 * c.sample_period_s);
        let u = c.kp_per_s * c.kv_v_s_per_m * (r_m - y_m) - c.kv_v_s_per_m * v_hat;
        self.prev = Some((y_m, y1));
        let lim = c.saturation_v;
        (u.clamp(-lim, lim), u.abs() > lim)
    }
}
