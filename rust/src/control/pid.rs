//! The FPGA position PID, bit-exact (docs/controller.md).
use super::fixed::{
    check_exact_width, constant_shape, fits64, narrow, product_shape, shape, sum_shape, Exact,
    Exact64, Format64, FxpFormat,
};
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
    /// The `i64` path ([`Pid::update_narrow`]), when every intermediate of an update with
    /// readings below [`NARROW_INPUT`] in magnitude fits it.
    narrow: Option<Narrow>,
}

/// What the `i64` path of an update needs, precomputed: the formats of the configuration it
/// was built for (an update reads no other field of `cfg`) and the quantised constants.
#[derive(Debug, Clone, Copy)]
struct Narrow {
    /// The formats and anti-windup of `cfg` at construction: the path is taken only while
    /// `cfg` still has them (`cfg` is a public field).
    key: ArithmeticKey,
    measurement: Format64,
    error: Format64,
    term: Format64,
    integrator: Format64,
    output: Format64,
    dac: Format64,
    kp: Exact64,
    ki: Exact64,
    kd: Exact64,
    dac_scale: Exact64,
    out_min: Exact64,
    out_max: Exact64,
}

/// The state an update reads and writes, and the integrator's clamp bounds.
struct NarrowState {
    acc: i64,
    y_prev: Option<i64>,
    acc_min: i64,
    acc_max: i64,
}

impl Narrow {
    /// [`Pid::update`] with every exact intermediate in `i64` ([`Exact64`]); the same result
    /// bit for bit when `narrow_cfg` is the configuration and both readings are below
    /// [`NARROW_INPUT`] in magnitude (every value then fits in 62 bits, so no operation
    /// wraps, and [`FxpFormat::requantize64`] equals [`FxpFormat::requantize`]).
    fn update(&self, st: &mut NarrowState, r_counts: i64, y_counts: i64) -> PidOutput {
        let n = self;
        use flags::*;
        let (kp, ki, kd, dac_scale, out_min, out_max) =
            (n.kp, n.ki, n.kd, n.dac_scale, n.out_min, n.out_max);
        let mut fl = 0u32;
        let (y, o) = n.measurement.requantize(Exact64::int(y_counts));
        fl |= if o { Y_OVERFLOW } else { 0 };
        let y_ex = n.measurement.exact(y);
        let y_prev = st.y_prev.unwrap_or(y);
        let (e, o) = n
            .error
            .requantize(Exact64::int(r_counts).add_exact(y_ex.neg_exact()));
        fl |= if o { E_OVERFLOW } else { 0 };
        let (dy, o) = n
            .error
            .requantize(y_ex.add_exact(n.measurement.exact(y_prev).neg_exact()));
        fl |= if o { D_OVERFLOW } else { 0 };
        let e_ex = n.error.exact(e);
        let (p, o) = n.term.requantize(kp.mul_exact(e_ex));
        fl |= if o { P_OVERFLOW } else { 0 };
        let (d, o) = n
            .term
            .requantize(kd.mul_exact(n.error.exact(dy)).neg_exact());
        fl |= if o { D_OVERFLOW } else { 0 };
        let inc = ki.mul_exact(e_ex);
        let (cand, o) = n
            .integrator
            .requantize(n.integrator.exact(st.acc).add_exact(inc));
        fl |= if o { I_OVERFLOW } else { 0 };
        let p_ex = n.term.exact(p);
        let d_ex = n.term.exact(d);
        let cand_ex = n.integrator.exact(cand);
        let acc = match n.key.anti_windup {
            AntiWindup::None => cand,
            AntiWindup::Clamp => {
                if cand > st.acc_max {
                    fl |= INTEGRATOR_HELD;
                    st.acc_max
                } else if cand < st.acc_min {
                    fl |= INTEGRATOR_HELD;
                    st.acc_min
                } else {
                    cand
                }
            }
            AntiWindup::Conditional => {
                let trial = p_ex.add_exact(cand_ex).add_exact(d_ex);
                let zero = Exact64::int(0);
                let above = trial.cmp_value(out_max) == Ordering::Greater
                    && inc.cmp_value(zero) == Ordering::Greater;
                let below = trial.cmp_value(out_min) == Ordering::Less
                    && inc.cmp_value(zero) == Ordering::Less;
                if above || below {
                    fl |= INTEGRATOR_HELD;
                    st.acc
                } else {
                    cand
                }
            }
        };
        st.acc = acc;
        st.y_prev = Some(y);
        let sum = p_ex.add_exact(n.integrator.exact(acc)).add_exact(d_ex);
        let (mut u, o) = n.output.requantize(sum);
        fl |= if o { U_OVERFLOW } else { 0 };
        let u_ex = n.output.exact(u);
        if u_ex.cmp_value(out_max) == Ordering::Greater {
            u = out_max.raw;
            fl |= U_SATURATED;
        } else if u_ex.cmp_value(out_min) == Ordering::Less {
            u = out_min.raw;
            fl |= U_SATURATED;
        }
        let (code, o) = n.dac.requantize(n.output.exact(u).mul_exact(dac_scale));
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

/// The fields of a [`PidConfig`] that [`Pid::update`] reads (the gains, output range and DAC
/// scale are quantised at construction).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct ArithmeticKey {
    measurement: FxpFormat,
    error: FxpFormat,
    term: FxpFormat,
    integrator: FxpFormat,
    output: FxpFormat,
    dac: FxpFormat,
    anti_windup: AntiWindup,
}

impl ArithmeticKey {
    #[inline]
    fn of(c: &PidConfig) -> Self {
        Self {
            measurement: c.measurement_format,
            error: c.error_format,
            term: c.term_format,
            integrator: c.integrator_format,
            output: c.output_format,
            dac: c.dac_format,
            anti_windup: c.anti_windup,
        }
    }
}

/// Readings (reference and measurement, counts) below this magnitude may take the `i64` path
/// (2^40 counts: far beyond any validated position with any count size the loop can use).
const NARROW_INPUT: i64 = 1 << 40;

/// The last update: its inputs (configuration, readings, state before) and its result (output,
/// state after). The update is a pure function of those inputs, so an update with the same
/// inputs (a settled loop: zero error, no motion) returns the stored result.
#[derive(Debug, Clone, Copy)]
struct Memo {
    /// The fields of `cfg` the update read (it reads no other; the rest is quantised at
    /// construction).
    key: ArithmeticKey,
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
        let narrow = narrow_fits(&cfg, [kp, ki, kd], dac_scale, out_min, out_max).then(|| Narrow {
            key: ArithmeticKey::of(&cfg),
            measurement: cfg.measurement_format.narrow64(),
            error: cfg.error_format.narrow64(),
            term: cfg.term_format.narrow64(),
            integrator: cfg.integrator_format.narrow64(),
            output: cfg.output_format.narrow64(),
            dac: cfg.dac_format.narrow64(),
            kp: to64(kp),
            ki: to64(ki),
            kd: to64(kd),
            dac_scale: to64(dac_scale),
            out_min: to64(out_min),
            out_max: to64(out_max),
        });
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
            narrow,
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
                && m.key == ArithmeticKey::of(&self.cfg)
            {
                self.acc = m.acc_after;
                self.y_prev = m.y_prev_after;
                return m.out;
            }
        }
        let (acc, y_prev) = (self.acc, self.y_prev);
        let key = ArithmeticKey::of(&self.cfg);
        let out = match &self.narrow {
            Some(n)
                if r_counts.unsigned_abs() < NARROW_INPUT.unsigned_abs()
                    && y_counts.unsigned_abs() < NARROW_INPUT.unsigned_abs()
                    && n.key == key =>
            {
                let mut st = NarrowState {
                    acc: self.acc,
                    y_prev: self.y_prev,
                    acc_min: self.acc_min,
                    acc_max: self.acc_max,
                };
                let out = n.update(&mut st, r_counts, y_counts);
                (self.acc, self.y_prev) = (st.acc, st.y_prev);
                out
            }
            _ => self.update(r_counts, y_counts),
        };
        self.memo = Some(Memo {
            key,
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

/// A constant known to fit in `i64` (checked by [`narrow_fits`] before the narrow path runs;
/// 0 otherwise, never used then).
fn to64(x: Exact) -> Exact64 {
    Exact64 {
        raw: i64::try_from(x.raw).unwrap_or(0),
        frac: x.frac,
    }
}

/// Whether every exact intermediate of an update fits the `i64` path ([`fits64`]) when both
/// readings are below [`NARROW_INPUT`] in magnitude: the shapes [`PidConfig::validate`]
/// bounds, with the readings' magnitude instead of any `i64`, the gains and the DAC scale as
/// the constants they are, and the output as clamped to its range.
fn narrow_fits(
    cfg: &PidConfig,
    gains: [Exact; 3],
    dac_scale: Exact,
    out_min: Exact,
    out_max: Exact,
) -> bool {
    let input = (41, 0); // |r|, |y| < 2^40
    let y = shape(&cfg.measurement_format);
    let err = shape(&cfg.error_format);
    let term = shape(&cfg.term_format);
    let integ = shape(&cfg.integrator_format);
    let out = shape(&cfg.output_format);
    // The three gains share the gain format's fraction bits.
    let gain = gains
        .iter()
        .map(|g| constant_shape(*g))
        .fold(constant_shape(gains[0]), |a, g| (a.0.max(g.0), a.1));
    let clamped = {
        let a = constant_shape(out_min);
        let b = constant_shape(out_max);
        (a.0.max(b.0), a.1)
    };
    let prod = {
        let (gi, gf) = gain;
        (gi.saturating_add(err.0), gf.saturating_add(err.1))
    };
    let sum3 = sum_shape(&[term, integ, term]);
    let dac = {
        let s = constant_shape(dac_scale);
        (clamped.0.saturating_add(s.0), clamped.1.saturating_add(s.1))
    };
    let values = [
        input,
        y,
        sum_shape(&[input, y]),
        sum_shape(&[y, y]),
        err,
        gain,
        prod,
        sum_shape(&[integ, prod]),
        sum3,
        sum_shape(&[sum3, out]),
        sum_shape(&[prod, input]),
        sum_shape(&[out, out]),
        clamped,
        dac,
    ];
    fits64(&values)
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

#[cfg(test)]
mod tests {
    use super::{AntiWindup, Pid, PidConfig, NARROW_INPUT};
    use crate::control::fixed::{FxpFormat, Overflow, Rounding};
    use crate::presets::seed_pid;

    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
        fn int(&mut self, lo: i64, hi: i64) -> i64 {
            let span = hi.wrapping_sub(lo) as u64 + 1;
            lo.wrapping_add(self.below(span) as i64)
        }
    }

    fn format(rng: &mut Rng, max_word: u32) -> FxpFormat {
        let signed = rng.below(2) == 0;
        let word_bits =
            1 + rng.below(u64::from(if signed { max_word } else { max_word - 1 })) as u32;
        let frac = rng.int(-8, i64::from(max_word) / 2) as i32;
        FxpFormat {
            signed,
            word_bits,
            int_bits: word_bits as i32 - frac,
            rounding: [Rounding::Truncate, Rounding::HalfUp, Rounding::HalfEven]
                [rng.below(3) as usize],
            overflow: [Overflow::Saturate, Overflow::Wrap][rng.below(2) as usize],
        }
    }

    /// A value around the representable range of `fmt` (sometimes outside it).
    fn value(rng: &mut Rng, fmt: &FxpFormat) -> f64 {
        let lo = fmt.raw_min() as f64 * (-f64::from(fmt.frac_bits())).exp2();
        let hi = fmt.raw_max() as f64 * (-f64::from(fmt.frac_bits())).exp2();
        let u = rng.below(1 << 20) as f64 / f64::from(1 << 20);
        let x = lo + (hi - lo) * u;
        x * [1.0, 0.5, 1e-3, 1e-6][rng.below(4) as usize]
    }

    /// A reading: mostly small, sometimes near the narrow path's limit or beyond it.
    fn reading(rng: &mut Rng) -> i64 {
        match rng.below(8) {
            0 => {
                rng.int(NARROW_INPUT - 3, NARROW_INPUT + 3) * if rng.below(2) == 0 { 1 } else { -1 }
            }
            1 => rng.int(-(1 << 62), 1 << 62),
            2 => rng.int(-(1 << 31), 1 << 31),
            _ => rng.int(-3000, 3000),
        }
    }

    /// The `i64` path gives the `i128` path's output, integrator and measurement memory, bit
    /// for bit, over random formats (up to 64 bits, so that some configurations fit the narrow
    /// path only just and some do not), gains, output ranges and readings.
    #[test]
    fn narrow_path_equals_the_exact_path() {
        let mut rng = Rng(0x2545_f491_4f6c_dd1d);
        let mut configs = 0;
        let mut narrow_updates = 0;
        for case in 0..4000 {
            let max_word = [24, 32, 64][case % 3];
            let mut cfg: PidConfig = seed_pid(450.0, 5.0, 25.0);
            cfg.gain_format = format(&mut rng, max_word.min(32));
            cfg.measurement_format = format(&mut rng, max_word);
            cfg.error_format = format(&mut rng, max_word);
            cfg.term_format = format(&mut rng, max_word);
            cfg.integrator_format = format(&mut rng, max_word);
            cfg.output_format = format(&mut rng, max_word);
            cfg.dac_format = format(&mut rng, max_word.min(32));
            cfg.dac_scale_format = format(&mut rng, 24);
            cfg.anti_windup =
                [AntiWindup::None, AntiWindup::Clamp, AntiWindup::Conditional][(case / 3) % 3];
            cfg.kp = value(&mut rng, &cfg.gain_format);
            cfg.ki = value(&mut rng, &cfg.gain_format);
            cfg.kd = value(&mut rng, &cfg.gain_format);
            let a = value(&mut rng, &cfg.output_format);
            let b = value(&mut rng, &cfg.output_format);
            (cfg.output_min, cfg.output_max) = (a.min(b), a.max(b));
            cfg.output_unit_v = 1e-4 * (1 + rng.below(1000)) as f64;
            cfg.dac_lsb_v = 1e-4 * (1 + rng.below(1000)) as f64;
            let Ok(mut fast) = Pid::new(cfg) else {
                continue;
            };
            configs += 1;
            let mut wide = fast.clone();
            wide.narrow = None;
            for _ in 0..40 {
                let (r, y) = (reading(&mut rng), reading(&mut rng));
                if fast.narrow.is_some()
                    && r.unsigned_abs() < NARROW_INPUT.unsigned_abs()
                    && y.unsigned_abs() < NARROW_INPUT.unsigned_abs()
                {
                    narrow_updates += 1;
                }
                let (of, ow) = (fast.step(r, y), wide.step(r, y));
                assert_eq!(of, ow, "{cfg:?} r {r} y {y}");
                assert_eq!((fast.acc, fast.y_prev), (wide.acc, wide.y_prev), "{cfg:?}");
            }
        }
        assert!(configs > 2500, "{configs}");
        assert!(narrow_updates > 40_000, "{narrow_updates}");
    }

    /// The narrow path is left when a format of the public `cfg` changes after construction
    /// (the update then follows the new format, as the exact path does).
    #[test]
    fn changed_formats_leave_the_narrow_path() {
        let mut pid = Pid::new(seed_pid(450.0, 5.0, 25.0)).unwrap_or_else(|e| panic!("{e}"));
        assert!(pid.narrow.is_some());
        let mut wide = pid.clone();
        wide.narrow = None;
        for p in [&mut pid, &mut wide] {
            p.cfg.error_format.word_bits = 4;
            p.cfg.error_format.int_bits = 4;
        }
        for (r, y) in [(0, 0), (100, 3), (-50, 7), (9, 9)] {
            assert_eq!(pid.step(r, y), wide.step(r, y));
        }
    }
}
