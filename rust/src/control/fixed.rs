//! LabVIEW-style fixed-point (FXP) arithmetic, exact in `i128`.
//!
//! A format is ⟨signed, word length, integer word length⟩ plus a rounding and an overflow
//! mode (DOMAIN.md §2.4). A value is `raw · 2^−frac_bits`. Products and sums are first formed
//! exactly ([`Exact`]), then requantised into a format: that is the only place where rounding
//! and overflow happen, and it is named so.
#![deny(clippy::arithmetic_side_effects)]

use crate::error::ConfigError;

/// Rounding when low bits are dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rounding {
    /// Toward minus infinity (drop the bits): LabVIEW "Truncate".
    Truncate,
    /// To nearest, ties upward: LabVIEW "Round-Half-Up".
    HalfUp,
    /// To nearest, ties to even: LabVIEW "Round-Half-Even" (its default).
    HalfEven,
}

/// What happens when a value does not fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overflow {
    /// Clamp to the format's range.
    Saturate,
    /// Keep the low `word_bits` bits (two's complement).
    Wrap,
}

/// A fixed-point format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FxpFormat {
    /// Signed (two's complement) or unsigned.
    pub signed: bool,
    /// Word length in bits: 1..=64 signed, 1..=63 unsigned.
    pub word_bits: u32,
    /// Integer word length (may be negative or exceed the word length); the fraction has
    /// `word_bits − int_bits` bits, which must lie in [−64, 64].
    pub int_bits: i32,
    /// Rounding mode.
    pub rounding: Rounding,
    /// Overflow mode.
    pub overflow: Overflow,
}

/// An exact intermediate value `raw · 2^−frac`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Exact {
    /// Raw integer.
    pub raw: i128,
    /// Fraction bits.
    pub frac: i32,
}

/// Bits an exact intermediate may use (sign included) so that no `i128` operation overflows.
pub const EXACT_BITS: i32 = 126;

impl FxpFormat {
    /// A plain integer format (⟨signed, bits, bits⟩) with the given overflow, rounding
    /// half-even (irrelevant for integers).
    pub const fn integer(signed: bool, bits: u32, overflow: Overflow) -> Self {
        Self {
            signed,
            word_bits: bits,
            int_bits: bits as i32,
            rounding: Rounding::HalfEven,
            overflow,
        }
    }

    /// Fraction bits `word_bits − int_bits`.
    pub fn frac_bits(&self) -> i32 {
        (self.word_bits as i32).wrapping_sub(self.int_bits)
    }

    /// Smallest raw value.
    pub fn raw_min(&self) -> i128 {
        if self.signed {
            (-1i128).wrapping_shl(self.word_bits.wrapping_sub(1))
        } else {
            0
        }
    }

    /// Largest raw value.
    pub fn raw_max(&self) -> i128 {
        let bits = if self.signed {
            self.word_bits.wrapping_sub(1)
        } else {
            self.word_bits
        };
        1i128.wrapping_shl(bits).wrapping_sub(1)
    }

    /// Integer bits (sign included) that an exact value in this format can need.
    fn magnitude_bits(&self) -> i32 {
        self.int_bits.wrapping_add(1)
    }

    /// Check the word length and the fraction-bit range.
    pub fn validate(&self, field: &str) -> Result<(), ConfigError> {
        let max_word = if self.signed { 64 } else { 63 };
        if self.word_bits < 1 || self.word_bits > max_word {
            return Err(ConfigError::new(
                format!("{field}.word_bits"),
                self.word_bits,
                format!(
                    "an integer in [1, {max_word}] for a {} format",
                    if self.signed { "signed" } else { "unsigned" }
                ),
            ));
        }
        let f = self.frac_bits();
        if !(-64..=64).contains(&f) {
            return Err(ConfigError::new(
                format!("{field}.int_bits"),
                self.int_bits,
                format!(
                    "word_bits − int_bits in [−64, 64], i.e. int_bits in [{}, {}]",
                    (self.word_bits as i32).wrapping_sub(64),
                    (self.word_bits as i32).wrapping_add(64)
                ),
            ));
        }
        Ok(())
    }

    /// Requantise an exact value into this format: round the dropped bits, then handle
    /// overflow. Returns the raw value and whether it overflowed.
    pub fn requantize(&self, x: Exact) -> (i64, bool) {
        let f = self.frac_bits();
        let diff = f.wrapping_sub(x.frac);
        let (value, shift_overflow) = if diff >= 0 {
            let s = diff.unsigned_abs();
            if s >= 127 {
                (0i128, x.raw != 0)
            } else {
                let shifted = x.raw.wrapping_shl(s);
                (shifted, shifted.wrapping_shr(s) != x.raw)
            }
        } else {
            (
                round_shift_right(x.raw, diff.unsigned_abs(), self.rounding),
                false,
            )
        };
        let (lo, hi) = (self.raw_min(), self.raw_max());
        if !shift_overflow && value >= lo && value <= hi {
            return (narrow(value), false);
        }
        let out = match self.overflow {
            Overflow::Saturate => {
                let negative = if shift_overflow {
                    x.raw < 0
                } else {
                    value < lo
                };
                if negative {
                    lo
                } else {
                    hi
                }
            }
            Overflow::Wrap => wrap(value, self.word_bits, self.signed),
        };
        (narrow(out), true)
    }

    /// This format's constants for the `i64` path ([`Format64`]).
    pub fn narrow64(&self) -> Format64 {
        Format64 {
            frac: self.frac_bits(),
            // A format has at most 64 bits (validated), so its range fits in i64.
            lo: narrow(self.raw_min()),
            hi: narrow(self.raw_max()),
            word_bits: self.word_bits,
            signed: self.signed,
            rounding: self.rounding,
            overflow: self.overflow,
        }
    }

    /// The exact value of a raw number in this format.
    pub fn exact(&self, raw: i64) -> Exact {
        Exact {
            raw: i128::from(raw),
            frac: self.frac_bits(),
        }
    }

    /// Convert a real number (host side, e.g. a gain) to raw: nearest, ties to even; an error
    /// naming `field` if it is not finite or outside the format's range.
    pub fn from_f64(&self, field: &str, value: f64) -> Result<i64, ConfigError> {
        let f = self.frac_bits();
        let lo = self.raw_min() as f64 * (-f64::from(f)).exp2();
        let hi = self.raw_max() as f64 * (-f64::from(f)).exp2();
        let scaled = value * f64::from(f).exp2();
        let r = scaled.round_ties_even();
        if !value.is_finite() || r < self.raw_min() as f64 || r > self.raw_max() as f64 {
            return Err(ConfigError::new(
                field,
                value,
                format!(
                    "a value representable in ⟨{},{},{}⟩: [{lo}, {hi}]",
                    if self.signed { "s" } else { "u" },
                    self.word_bits,
                    self.int_bits
                ),
            ));
        }
        // r is an integer within [raw_min, raw_max] ⊂ i64, so the cast is exact.
        #[allow(clippy::cast_possible_truncation)]
        Ok(r as i64)
    }

    /// Value of a raw number as f64 (for recording only).
    pub fn to_f64(&self, raw: i64) -> f64 {
        raw as f64 * (-f64::from(self.frac_bits())).exp2()
    }
}

/// Narrow an `i128` known to fit a ≤ 64-bit format to `i64` (clamped otherwise).
pub(crate) fn narrow(v: i128) -> i64 {
    // Callers only pass values inside a ≤ 64-bit format's range.
    i64::try_from(v).unwrap_or(if v < 0 { i64::MIN } else { i64::MAX })
}

/// Keep the low `bits` bits of `v`, sign-extended when signed.
fn wrap(v: i128, bits: u32, signed: bool) -> i128 {
    let pad = 128u32.wrapping_sub(bits);
    let low = v.wrapping_shl(pad);
    if signed {
        low.wrapping_shr(pad)
    } else {
        ((low as u128).wrapping_shr(pad)) as i128
    }
}

/// [`wrap`] of a value held in `i64` (`bits` ≤ 64): the same low bits.
fn wrap64(v: i64, bits: u32, signed: bool) -> i64 {
    let pad = 64u32.saturating_sub(bits);
    let low = v.wrapping_shl(pad);
    if signed {
        low.wrapping_shr(pad)
    } else {
        ((low as u64).wrapping_shr(pad)) as i64
    }
}

/// [`round_shift_right`] for any `i64`: `raw / 2^s` rounded by `mode`.
fn round_shift_right64(raw: i64, s: u32, mode: Rounding) -> i64 {
    if s >= 64 {
        // |raw| ≤ 2^63 ≤ 2^(s−1): the quotient is in [−1/2, 1/2]; −1/2 (raw = i64::MIN at
        // s = 64) rounds to 0 half-up and half-even, as every other value does.
        return match mode {
            Rounding::Truncate => {
                if raw < 0 {
                    -1
                } else {
                    0
                }
            }
            Rounding::HalfUp | Rounding::HalfEven => 0,
        };
    }
    if s == 0 {
        return raw;
    }
    let q = raw.wrapping_shr(s); // floor
                                 // In [0, 2^s) (as u64: 2^63 does not fit i64 at s = 63).
    let rem = (raw as u64).wrapping_sub((q as u64).wrapping_shl(s));
    let half = 1u64.wrapping_shl(s.wrapping_sub(1));
    match mode {
        Rounding::Truncate => q,
        Rounding::HalfUp => {
            if rem >= half {
                q.wrapping_add(1)
            } else {
                q
            }
        }
        Rounding::HalfEven => {
            if rem > half || (rem == half && (q & 1) == 1) {
                q.wrapping_add(1)
            } else {
                q
            }
        }
    }
}

/// `raw / 2^s` rounded by `mode`, for |raw| < 2^(EXACT_BITS−1).
fn round_shift_right(raw: i128, s: u32, mode: Rounding) -> i128 {
    if s >= 127 {
        // |raw| < 2^125 < 2^(s−1): the quotient is in (−1, 1) and never a tie.
        return match mode {
            Rounding::Truncate => {
                if raw < 0 {
                    -1
                } else {
                    0
                }
            }
            Rounding::HalfUp | Rounding::HalfEven => 0,
        };
    }
    let q = raw.wrapping_shr(s); // floor
    let rem = raw.wrapping_sub(q.wrapping_shl(s)); // in [0, 2^s)
    if s == 0 {
        return raw;
    }
    let half = 1i128.wrapping_shl(s.wrapping_sub(1));
    match mode {
        Rounding::Truncate => q,
        Rounding::HalfUp => {
            if rem >= half {
                q.wrapping_add(1)
            } else {
                q
            }
        }
        Rounding::HalfEven => {
            if rem > half || (rem == half && (q & 1) == 1) {
                q.wrapping_add(1)
            } else {
                q
            }
        }
    }
}

impl Exact {
    /// An exact integer.
    pub fn int(v: i64) -> Self {
        Self {
            raw: i128::from(v),
            frac: 0,
        }
    }

    /// Exact product (fraction bits add). Callers guarantee the width bound (see
    /// [`check_exact_width`]).
    pub fn mul_exact(self, o: Self) -> Self {
        Self {
            raw: self.raw.wrapping_mul(o.raw),
            frac: self.frac.wrapping_add(o.frac),
        }
    }

    /// Exact negation.
    pub fn neg_exact(self) -> Self {
        Self {
            raw: self.raw.wrapping_neg(),
            frac: self.frac,
        }
    }

    /// Exact sum, aligned to the larger fraction.
    pub fn add_exact(self, o: Self) -> Self {
        let f = self.frac.max(o.frac);
        Self {
            raw: self.align(f).wrapping_add(o.align(f)),
            frac: f,
        }
    }

    /// Raw value at `f` fraction bits (`f ≥ self.frac`).
    fn align(self, f: i32) -> i128 {
        self.raw
            .wrapping_shl(f.wrapping_sub(self.frac).unsigned_abs())
    }

    /// Exact comparison of values.
    pub fn cmp_value(self, o: Self) -> std::cmp::Ordering {
        let f = self.frac.max(o.frac);
        self.align(f).cmp(&o.align(f))
    }
}

/// A validated format's constants for the `i64` path of the PID ([`Exact64`]): fraction
/// bits and raw range precomputed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Format64 {
    frac: i32,
    lo: i64,
    hi: i64,
    word_bits: u32,
    signed: bool,
    rounding: Rounding,
    overflow: Overflow,
}

impl Format64 {
    /// [`FxpFormat::requantize`] of an exact value held in `i64`: the same result and
    /// overflow flag, bit for bit, for every raw value and fraction. Shifts the `i128`
    /// version makes past 63 bits are decided the way it decides them: a left shift of a
    /// nonzero value by 64 or more overflows every format of at most 64 bits (its low 64
    /// bits, which wrapping keeps, are zero); a right shift by 64 or more leaves a quotient in
    /// [−1/2, 1/2].
    #[inline]
    pub fn requantize(&self, x: Exact64) -> (i64, bool) {
        let raw = x.raw;
        let diff = self.frac.wrapping_sub(x.frac);
        let (value, shift_overflow) = if diff >= 0 {
            let s = diff.unsigned_abs();
            if s >= 64 {
                (0i64, raw != 0)
            } else {
                let shifted = raw.wrapping_shl(s);
                (shifted, shifted.wrapping_shr(s) != raw)
            }
        } else {
            (
                round_shift_right64(raw, diff.unsigned_abs(), self.rounding),
                false,
            )
        };
        let (lo, hi) = (self.lo, self.hi);
        if !shift_overflow && value >= lo && value <= hi {
            return (value, false);
        }
        let out = match self.overflow {
            Overflow::Saturate => {
                let negative = if shift_overflow { raw < 0 } else { value < lo };
                if negative {
                    lo
                } else {
                    hi
                }
            }
            Overflow::Wrap => wrap64(value, self.word_bits, self.signed),
        };
        (out, true)
    }

    /// The exact value of a raw number in this format.
    #[inline]
    pub fn exact(&self, raw: i64) -> Exact64 {
        Exact64 {
            raw,
            frac: self.frac,
        }
    }
}

/// An exact intermediate `raw · 2^−frac` held in `i64`: [`Exact`]'s operations, for callers
/// that have proved (by shape, [`fits64`]) that every value they form fits in 62 bits with
/// its sign, so that each result equals the `i128` one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Exact64 {
    /// Raw integer.
    pub raw: i64,
    /// Fraction bits.
    pub frac: i32,
}

impl Exact64 {
    /// An exact integer.
    #[inline]
    pub fn int(v: i64) -> Self {
        Self { raw: v, frac: 0 }
    }

    /// Exact product (fraction bits add).
    #[inline]
    pub fn mul_exact(self, o: Self) -> Self {
        Self {
            raw: self.raw.wrapping_mul(o.raw),
            frac: self.frac.wrapping_add(o.frac),
        }
    }

    /// Exact negation.
    #[inline]
    pub fn neg_exact(self) -> Self {
        Self {
            raw: self.raw.wrapping_neg(),
            frac: self.frac,
        }
    }

    /// Exact sum, aligned to the larger fraction.
    #[inline]
    pub fn add_exact(self, o: Self) -> Self {
        let f = self.frac.max(o.frac);
        Self {
            raw: self.align(f).wrapping_add(o.align(f)),
            frac: f,
        }
    }

    /// Raw value at `f` fraction bits (`f ≥ self.frac`).
    #[inline]
    fn align(self, f: i32) -> i64 {
        self.raw
            .wrapping_shl(f.wrapping_sub(self.frac).unsigned_abs())
    }

    /// Exact comparison of values.
    #[inline]
    pub fn cmp_value(self, o: Self) -> std::cmp::Ordering {
        let f = self.frac.max(o.frac);
        self.align(f).cmp(&o.align(f))
    }
}

/// Whether values of these shapes (integer bits incl. sign, fraction bits) fit the narrow
/// `i64` path ([`Exact64`]): at most 62 bits each.
pub fn fits64(shapes: &[(i32, i32)]) -> bool {
    shapes.iter().all(|&(i, f)| i.saturating_add(f) <= 62)
}

/// Shape (integer bits incl. sign, fraction bits) of the constant `x`.
pub fn constant_shape(x: Exact) -> (i32, i32) {
    let bits = 128i32.wrapping_sub(x.raw.unsigned_abs().leading_zeros() as i32);
    (bits.wrapping_add(1).wrapping_sub(x.frac), x.frac)
}

/// Check that an exact intermediate of the given shape (integer bits incl. sign, fraction
/// bits) fits in [`EXACT_BITS`].
pub fn check_exact_width(field: &str, int_bits: i32, frac_bits: i32) -> Result<(), ConfigError> {
    let need = int_bits.wrapping_add(frac_bits);
    if need > EXACT_BITS {
        return Err(ConfigError::new(
            field,
            need,
            format!(
                "formats whose exact intermediate fits in {EXACT_BITS} bits (integer bits + fraction bits); \
                 reduce the word lengths or fraction bits"
            ),
        ));
    }
    Ok(())
}

/// Integer bits (incl. sign) and fraction bits of the exact product of two formats.
pub fn product_shape(a: &FxpFormat, b: &FxpFormat) -> (i32, i32) {
    (
        a.magnitude_bits().wrapping_add(b.magnitude_bits()),
        a.frac_bits().wrapping_add(b.frac_bits()),
    )
}

/// Integer bits (incl. sign) and fraction bits of the exact sum of values of these shapes.
pub fn sum_shape(shapes: &[(i32, i32)]) -> (i32, i32) {
    let frac = shapes.iter().map(|s| s.1).max().unwrap_or(0);
    let ints = shapes.iter().map(|s| s.0).max().unwrap_or(0);
    let extra = match shapes.len() {
        0 | 1 => 0,
        2 => 1,
        _ => 2,
    };
    (ints.wrapping_add(extra), frac)
}

/// Shape of a format's values.
pub fn shape(fmt: &FxpFormat) -> (i32, i32) {
    (fmt.magnitude_bits(), fmt.frac_bits())
}
