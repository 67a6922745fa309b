//! Fixed-point semantics, exhaustively over i16 inputs against a plain i64 model, and PID
//! basics. (The bit-exact PID check against an independent Python model is in tests/.)
use nanostage::control::fixed::Exact;
use nanostage::control::{AntiWindup, FxpFormat, Overflow, Pid, Rounding};
#[path = "support/presets.rs"]
mod presets;
use presets::seed_pid;

fn model(raw: i64, s: u32, mode: Rounding) -> i64 {
    let d = 1i64 << s;
    let fl = raw.div_euclid(d);
    let rem = raw.rem_euclid(d);
    match mode {
        Rounding::Truncate => fl,
        Rounding::HalfUp => {
            if 2 * rem >= d {
                fl + 1
            } else {
                fl
            }
        }
        Rounding::HalfEven => {
            if 2 * rem > d || (2 * rem == d && fl % 2 != 0) {
                fl + 1
            } else {
                fl
            }
        }
    }
}

#[test]
fn requantize_every_i16_in_every_mode() {
    for rounding in [Rounding::Truncate, Rounding::HalfUp, Rounding::HalfEven] {
        for overflow in [Overflow::Saturate, Overflow::Wrap] {
            for signed in [true, false] {
                let fmt = FxpFormat {
                    signed,
                    word_bits: 8,
                    int_bits: 5,
                    rounding,
                    overflow,
                };
                let (lo, hi) = if signed { (-128i64, 127i64) } else { (0, 255) };
                for raw in i16::MIN..=i16::MAX {
                    // Input has 8 fraction bits; the format has 3: drop 5 bits.
                    let got = fmt.requantize(Exact {
                        raw: i128::from(raw),
                        frac: 8,
                    });
                    let q = model(i64::from(raw), 5, rounding);
                    let want = if q < lo || q > hi {
                        match overflow {
                            Overflow::Saturate => (if q < lo { lo } else { hi }, true),
                            Overflow::Wrap => {
                                let m = q.rem_euclid(256);
                                (if signed && m > 127 { m - 256 } else { m }, true)
                            }
                        }
                    } else {
                        (q, false)
                    };
                    assert_eq!(got, want, "raw {raw} {fmt:?}");
                }
            }
        }
    }
}

#[test]
fn seed_pid_terms_are_exact_integers() {
    let mut pid = Pid::new(seed_pid(450.0, 2.0, 40.0)).unwrap();
    let o = pid.step(0, 0);
    assert_eq!((o.e, o.p, o.i, o.d, o.u, o.code), (0, 0, 0, 0, 0, 0));
    // 100 counts of error: P = 450·100 = 45000 units, I = 2·100, D = 0 (no motion yet).
    let o = pid.step(100, 0);
    let c = pid.cfg;
    assert_eq!(c.term_format.to_f64(o.p), 45_000.0);
    assert_eq!(c.integrator_format.to_f64(o.i), 200.0);
    assert_eq!(o.d, 0);
    assert_eq!(c.output_format.to_f64(o.u), 45_200.0);
    // Measurement moves by 3 counts: D = −40·3.
    let o = pid.step(100, 3);
    assert_eq!(c.term_format.to_f64(o.d), -120.0);
}

#[test]
fn conditional_integration_freezes_when_saturated() {
    let mut cfg = seed_pid(450.0, 5.0, 0.0);
    cfg.anti_windup = AntiWindup::Conditional;
    let mut pid = Pid::new(cfg).unwrap();
    let first = pid.step(1_000, 0); // 450 000 units ≫ 60 000: saturated
    let again = pid.step(1_000, 0);
    assert_eq!(first.i, 0);
    assert_eq!(again.i, 0);
    assert_ne!(again.flags & nanostage::control::flags::U_SATURATED, 0);
    cfg.anti_windup = AntiWindup::None;
    let mut pid = Pid::new(cfg).unwrap();
    pid.step(1_000, 0);
    let o = pid.step(1_000, 0);
    assert_eq!(cfg.integrator_format.to_f64(o.i), 10_000.0);
}

#[test]
fn gain_outside_its_format_is_a_config_error() {
    let cfg = seed_pid(1e9, 2.0, 40.0);
    let err = Pid::new(cfg).unwrap_err();
    assert_eq!(err.field, "kp");
    assert!(err.expected.contains("representable"));
}
