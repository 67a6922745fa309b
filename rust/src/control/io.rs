//! The only f64 ↔ integer boundary: encoder quantisation and DAC/amplifier output.
use crate::error::{check_positive, ConfigError};

/// Linear incremental encoder on the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Encoder {
    /// Size of one count, m, in (0, 1e-3].
    pub count_m: f64,
}

impl Encoder {
    /// Validate.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("count_m", self.count_m, 1e-3)
    }

    /// Counts read at table position `x_m`: floor(x / count). Positions beyond ±2^62 counts
    /// are clamped (they cannot occur in a validated run; the clamp keeps the cast defined).
    #[allow(clippy::cast_possible_truncation)]
    pub fn read(&self, x_m: f64) -> i64 {
        let c = (x_m / self.count_m).floor();
        c.clamp(-4.6e18, 4.6e18) as i64
    }

    /// The host's conversion of a reference position to counts: nearest, ties to even.
    #[allow(clippy::cast_possible_truncation)]
    pub fn reference_counts(&self, r_m: f64) -> i64 {
        (r_m / self.count_m)
            .round_ties_even()
            .clamp(-4.6e18, 4.6e18) as i64
    }
}

/// Analog output and amplifier: `u = clamp(gain · code · lsb, ±limit)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputStage {
    /// Amplifier gain, V/V, in (0, 100].
    pub amplifier_gain: f64,
    /// Amplifier output limit (the motor's nominal voltage), V, in (0, 1000].
    pub amplifier_limit_v: f64,
}

impl OutputStage {
    /// Validate.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_positive("amplifier_gain", self.amplifier_gain, 100.0)?;
        check_positive("amplifier_limit_v", self.amplifier_limit_v, 1000.0)
    }

    /// Motor voltage for a DAC code, and whether the amplifier limited it.
    pub fn motor_voltage(&self, code: i64, dac_lsb_v: f64) -> (f64, bool) {
        let v = self.amplifier_gain * code as f64 * dac_lsb_v;
        let lim = self.amplifier_limit_v;
        if v > lim {
            (lim, true)
        } else if v < -lim {
            (-lim, true)
        } else {
            (v, false)
        }
    }
}
