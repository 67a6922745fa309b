//! The FPGA position PID, bit-exact (docs/controller.md).
use super::fixed::{check_exact_width, narrow, product_shape, shape, sum_shape, Exact, FxpFormat};
use crate::error::{check_positive, ConfigError};
use std::cmp::Ordering;

/// Integrator anti-windup.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AntiWindup {
    /// The integrator always integrates.
    None,
    /// The integrator is clamped to the output range.
    Clamp,
    /// The integrator is frozen while the output would leave the range in the direction the
    /// increment pushes (conditional integration).
    Conditional,
}

/// Configuration of the FPGA loop: gains, fixed-point formats, output range, units, timing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PidConfig {
    /// Proportional gain, output units per count.
    pub kp: f64,
    /// Integral gain, output units per count and sample.
    pub ki: f64,
    /// Derivative gain (on the measurement, damping sign), output units per count of motion
    /// per sample.
    pub kd: f64,
    /// Format of the three gains.
    pub gain_format: FxpFormat,
    /// Format of the encoder reading (the counter register).
    pub measurement_format: FxpFormat,
    /// Format of the error and of the measurement difference.
    pub error_format: FxpFormat,
    /// Format of the P and D terms.
    pub term_format: FxpFormat,
    /// Format of the integrator.
    pub integrator_format: FxpFormat,
    /// Format of the controller output.
    pub output_format: FxpFormat,
    /// Format of the DAC code (I16 for a 16-bit AO).
    pub dac_format: FxpFormat,
    /// Format of the constant that scales output units to DAC LSB.
    pub dac_scale_format: FxpFormat,
    /// Lower end of the output range, output units.
    pub output_min: f64,
    /// Upper end of the output range, output units.
    pub output_max: f64,
    /// Anti-windup option.
    pub anti_windup: AntiWindup,
    /// Volts at the amplifier input per output unit, in (0, 100].
    pub output_unit_v: f64,
    /// Volts per DAC LSB, in (0, 1].
    pub dac_lsb_v: f64,
    /// FPGA clock, Hz, in (0, 1e10].
    pub clock_hz: f64,
    /// Clock ticks per control sample, in [1, 2^40].
    pub ticks_per_sample: u64,
    /// Ticks from the sampling instant to the analog output update, in [0, ticks_per_sample).
    pub latency_ticks: u64,
}

/// Flag bits recorded with every sample.
pub mod flags {
    /// The error overflowed its format.
    pub const E_OVERFLOW: u32 = 1;
    /// The P term overflowed.
    pub const P_OVERFLOW: u32 = 2;
    /// The D term (or the measurement difference) overflowed.
    pub const D_OVERFLOW: u32 = 4;
    /// The candidate integrator overflowed its format.
    pub const I_OVERFLOW: u32 = 8;
    /// The output sum overflowed the output format.
    pub const U_OVERFLOW: u32 = 16;
    /// The output was clamped to the output range.
    pub const U_SATURATED: u32 = 32;
    /// The DAC code overflowed (saturated or wrapped).
    pub const DAC_OVERFLOW: u32 = 64;
    /// Anti-windup acted on the integrator.
    pub const INTEGRATOR_HELD: u32 = 128;
    /// The amplifier limited the motor voltage.
    pub const AMPLIFIER_SATURATED: u32 = 256;
    /// The measurement overflowed the counter format.
    pub const Y_OVERFLOW: u32 = 512;
}

/// Everything one controller update computed (raw values in their formats).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PidOutput {
    /// Error, raw in `error_format`.
    pub e: i64,
    /// P term, raw in `term_format`.
    pub p: i64,
    /// Integrator after the update, raw in `integrator_format`.
    pub i: i64,
    /// D term, raw in `term_format`.
    pub d: i64,
    /// Output after the range clamp, raw in `output_format`.
    pub u: i64,
    /// DAC code, raw in `dac_format`.
    pub code: i64,
    /// Flag bits ([`flags`]).
    pub flags: u32,
}

/// The running controller.
#[derive(Debug, Clone)]
pub struct Pid {
    /// Its configuration.
    pub cfg: PidConfig,
    kp: Exact,
    ki: Exact,
    kd: Exact,
    dac_scale: Exact,
    out_min: Exact,
    out_max: Exact,
    acc_min: i64,
    acc_max: i64,
    acc: i64,
    y_prev: Option<i64>,
    memo: Option<Memo>,
}

/// The last update: its inputs (configuration, readings, state before) and its result (output,
/// state after). The update is a pure function of those inputs, so an update with the same
/// inputs (a settled loop: zero error, no motion) returns the stored result.
#[derive(Debug, Clone, Copy)]
struct Memo {
    cfg: PidConfig,
    r_counts: i64,
    y_counts: i64,
    acc: i64,
    y_prev: Option<i64>,
    out: PidOutput,
    acc_after: i64,
    y_prev_after: Option<i64>,
}

impl PidConfig {
    /// Check every field (formats, ranges, exact-width bounds, timing).
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, f) in [
            ("gain_format", &self.gain_format),
            ("measurement_format", &self.measurement_format),
            ("error_format", &self.error_format),
            ("term_format", &self.term_format),
            ("integrator_format", &self.integrator_format),
            ("output_format", &self.output_format),
            ("dac_format", &self.dac_format),
            ("dac_scale_format", &self.dac_scale_format),
        ] {
            f.validate(name)?;
        }
        check_positive("output_unit_v", self.output_unit_v, 100.0)?;
        check_positive("dac_lsb_v", self.dac_lsb_v, 1.0)?;
        check_positive("clock_hz", self.clock_hz, 1e10)?;
        if self.ticks_per_sample < 1 || self.ticks_per_sample > (1u64 << 40) {
            return Err(ConfigError::new(
                "ticks_per_sample",
                self.ticks_per_sample,
                "an integer in [1, 2^40]",
            ));
        }
        if self.latency_ticks >= self.ticks_per_sample {
            return Err(ConfigError::new(
                "latency_ticks",
                self.latency_ticks,
                format!(
                    "an integer in [0, ticks_per_sample = {})",
                    self.ticks_per_sample
                ),
            ));
        }
        let y = shape(&self.measurement_format);
        let int64 = (65, 0);
        let diff = sum_shape(&[int64, y]);
        check_exact_width("error_format (r − y)", diff.0, diff.1)?;
        let dy = sum_shape(&[y, y]);
        check_exact_width("measurement_format (y − y_prev)", dy.0, dy.1)?;
        let prod = product_shape(&self.gain_format, &self.error_format);
        check_exact_width("gain_format × error_format", prod.0, prod.1)?;
        let acc = sum_shape(&[shape(&self.integrator_format), prod]);
        check_exact_width("integrator_format + ki·e", acc.0, acc.1)?;
        let t = shape(&self.term_format);
        let u = sum_shape(&[t, shape(&self.integrator_format), t]);
        check_exact_width("term_format + integrator_format + term_format", u.0, u.1)?;
        let dac = product_shape(&self.output_format, &self.dac_scale_format);
        check_exact_width("output_format × dac_scale_format", dac.0, dac.1)?;
        Ok(())
    }
}

impl Pid {
    /// Quantise gains, range and DAC scale into their formats; errors name the field.
    pub fn new(cfg: PidConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let gf = cfg.gain_format;
        let kp = gf.exact(gf.from_f64("kp", cfg.kp)?);
        let ki = gf.exact(gf.from_f64("ki", cfg.ki)?);
        let kd = gf.exact(gf.from_f64("kd", cfg.kd)?);
        let of = cfg.output_format;
        let out_min = of.exact(of.from_f64("output_min", cfg.output_min)?);
        let out_max = of.exact(of.from_f64("output_max", cfg.output_max)?);
        if out_min.cmp_value(out_max) == Ordering::Greater {
            return Err(ConfigError::new(
                "output_max",
                cfg.output_max,
                format!("at least output_min = {}", cfg.output_min),
            ));
        }
        // Integrator clamp bounds: the output range rounded inward to the integrator's grid.
        let acc_min = bound_in(out_min, &cfg.integrator_format, true);
        let acc_max = bound_in(out_max, &cfg.integrator_format, false);
        if cfg.anti_windup == AntiWindup::Clamp && acc_min > acc_max {
            return Err(ConfigError::new(
                "integrator_format",
                format!("{:?}", cfg.integrator_format),
                "a format holding at least one value inside [output_min, output_max] (clamp anti-windup)",
            ));
        }
        let sf = cfg.dac_scale_format;
        let scale = cfg.output_unit_v / cfg.dac_lsb_v;
        let dac_scale = sf.exact(sf.from_f64("dac_scale (output_unit_v / dac_lsb_v)", scale)?);
        Ok(Self {
            cfg,
            kp,
            ki,
            kd,
            dac_scale,
            out_min,
            out_max,
            acc_min,
            acc_max,
            acc: 0,
            y_prev: None,
            memo: None,
        })
    }

    /// Raw gains (kp, ki, kd) in `gain_format`, as quantised.
    pub fn raw_gains(&self) -> (i64, i64, i64) {
        (
            i64::try_from(self.kp.raw).unwrap_or(0),
            i64::try_from(self.ki.raw).unwrap_or(0),
            i64::try_from(self.kd.raw).unwrap_or(0),
        )
    }

    /// Reset: zero integrator; the next sample initialises the previous measurement.
    pub fn reset(&mut self) {
        self.acc = 0;
        self.y_prev = None;
    }

    /// One control update from the reference and the encoder reading (both in counts).
    pub fn step(&mut self, r_counts: i64, y_counts: i64) -> PidOutput {
        if let Some(m) = &self.memo {
            if m.r_counts == r_counts
                && m.y_counts == y_counts
                && m.acc == self.acc
                && m.y_prev == self.y_prev
                && m.cfg == self.cfg
            {
                self.acc = m.acc_after;
                self.y_prev = m.y_prev_after;
                return m.out;
            }
        }
        let (acc, y_prev) = (self.acc, self.y_prev);
        let out = self.update(r_counts, y_counts);
        self.memo = Some(Memo {
            cfg: self.cfg,
            r_counts,
            y_counts,
            acc,
            y_prev,
            out,
            acc_after: self.acc,
            y_prev_after: self.y_prev,
        });
        out
    }

    fn update(&mut self, r_counts: i64, y_counts: i64) -> PidOutput {
        use flags::*;
        let c = &self.cfg;
        let mut fl = 0u32;
        let (y, o) = c.measurement_format.requantize(Exact::int(y_counts));
        fl |= if o { Y_OVERFLOW } else { 0 };
        let y_ex = c.measurement_format.exact(y);
        let y_prev = self.y_prev.unwrap_or(y);
        let (e, o) = c
            .error_format
            .requantize(Exact::int(r_counts).add_exact(y_ex.neg_exact()));
        fl |= if o { E_OVERFLOW } else { 0 };
        let (dy, o) = c
            .error_format
            .requantize(y_ex.add_exact(c.measurement_format.exact(y_prev).neg_exact()));
        fl |= if o { D_OVERFLOW } else { 0 };
        let e_ex = c.error_format.exact(e);
        let (p, o) = c.term_format.requantize(self.kp.mul_exact(e_ex));
        fl |= if o { P_OVERFLOW } else { 0 };
        let (d, o) = c
            .term_format
            .requantize(self.kd.mul_exact(c.error_format.exact(dy)).neg_exact());
        fl |= if o { D_OVERFLOW } else { 0 };
        let inc = self.ki.mul_exact(e_ex);
        let (cand, o) = c
            .integrator_format
            .requantize(c.integrator_format.exact(self.acc).add_exact(inc));
        fl |= if o { I_OVERFLOW } else { 0 };
        let p_ex = c.term_format.exact(p);
        let d_ex = c.term_format.exact(d);
        let cand_ex = c.integrator_format.exact(cand);
        let acc = match c.anti_windup {
            AntiWindup::None => cand,
            AntiWindup::Clamp => {
                if cand > self.acc_max {
                    fl |= INTEGRATOR_HELD;
                    self.acc_max
                } else if cand < self.acc_min {
                    fl |= INTEGRATOR_HELD;
                    self.acc_min
                } else {
                    cand
                }
            }
            AntiWindup::Conditional => {
                let trial = p_ex.add_exact(cand_ex).add_exact(d_ex);
                let zero = Exact::int(0);
                let above = trial.cmp_value(self.out_max) == Ordering::Greater
                    && inc.cmp_value(zero) == Ordering::Greater;
                let below = trial.cmp_value(self.out_min) == Ordering::Less
                    && inc.cmp_value(zero) == Ordering::Less;
                if above || below {
                    fl |= INTEGRATOR_HELD;
                    self.acc
                } else {
                    cand
                }
            }
        };
        self.acc = acc;
        self.y_prev = Some(y);
        let sum = p_ex
            .add_exact(c.integrator_format.exact(acc))
            .add_exact(d_ex);
        let (mut u, o) = c.output_format.requantize(sum);
        fl |= if o { U_OVERFLOW } else { 0 };
        let u_ex = c.output_format.exact(u);
        if u_ex.cmp_value(self.out_max) == Ordering::Greater {
            u = narrow(self.out_max.raw);
            fl |= U_SATURATED;
        } else if u_ex.cmp_value(self.out_min) == Ordering::Less {
            u = narrow(self.out_min.raw);
            fl |= U_SATURATED;
        }
        let (code, o) = c
            .dac_format
            .requantize(c.output_format.exact(u).mul_exact(self.dac_scale));
        fl |= if o { DAC_OVERFLOW } else { 0 };
        PidOutput {
            e,
            p,
            i: acc,
            d,
            u,
            code,
            flags: fl,
        }
    }
}

/// Raw value of `x` at the fraction bits of `fmt`, rounded up (`up`) or down when bits are
/// dropped, then limited to the format's raw range.
fn bound_in(x: Exact, fmt: &FxpFormat, up: bool) -> i64 {
    let f = fmt.frac_bits();
    let diff = f - x.frac;
    let v = if diff >= 0 {
        let s = diff.unsigned_abs();
        if s >= 126 || (x.raw != 0 && x.raw.unsigned_abs().leading_zeros() <= s + 1) {
            if x.raw < 0 {
                fmt.raw_min()
            } else {
                fmt.raw_max()
            }
        } else {
            x.raw << s
        }
    } else {
        let s = (-diff).unsigned_abs().min(127);
        let q = x.raw >> s; // floor
        if up && (q << s) != x.raw {
            q + 1
        } else {
            q
        }
    };
    narrow(v.clamp(fmt.raw_min(), fmt.raw_max()))
}
