//! The seed closed loop: Table 1 steps settle; runs are deterministic; interruption works.
#[path = "support/presets.rs"]
mod presets;
use nanostage::sim::run_closed_loop;
use nanostage::SimError;
use presets::seed_closed_loop;
use std::sync::atomic::AtomicBool;

fn step_ref(step: f64, n: usize) -> Vec<f64> {
    (0..n).map(|k| if k >= 10 { step } else { 0.0 }).collect()
}

#[test]
fn table1_steps_settle_within_one_count() {
    for (step, n) in [(100e-6, 1000), (500e-6, 1000), (1e-3, 1000), (10e-3, 2000)] {
        let tr = run_closed_loop(&seed_closed_loop(step), &step_ref(step, n), None).unwrap();
        let err = tr.reference_counts[n - 1] - tr.encoder_counts[n - 1];
        assert!(err.abs() <= 1, "step {step}: final error {err} counts");
        let peak = tr.position_m.iter().copied().fold(f64::MIN, f64::max);
        assert!(peak > step, "step {step}: no overshoot");
        assert!(peak < 1.6 * step, "step {step}: overshoot {}", peak - step);
    }
}

#[test]
fn runs_are_bit_identical() {
    let cfg = seed_closed_loop(1e-3);
    let r = step_ref(1e-3, 500);
    let a = run_closed_loop(&cfg, &r, None).unwrap();
    let b = run_closed_loop(&cfg, &r, None).unwrap();
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.position_m), bits(&b.position_m));
    assert_eq!(a.dac_code, b.dac_code);
    assert_eq!(a.stats, b.stats);
}

#[test]
fn a_set_stop_flag_interrupts() {
    let stop = AtomicBool::new(true);
    let err =
        run_closed_loop(&seed_closed_loop(1e-3), &step_ref(1e-3, 100), Some(&stop)).unwrap_err();
    assert!(matches!(err, SimError::Interrupted { .. }));
}

#[test]
fn empty_or_nan_reference_is_a_config_error() {
    let cfg = seed_closed_loop(1e-3);
    assert!(matches!(
        run_closed_loop(&cfg, &[], None),
        Err(SimError::Config(_))
    ));
    match run_closed_loop(&cfg, &[0.0, f64::NAN], None) {
        Err(SimError::Config(e)) => assert_eq!(e.field, "reference_m[1]"),
        other => panic!("{other:?}"),
    }
}

/// The seed model file against SEED.md's numbers (written out here, not read from the file).
#[test]
fn the_seed_file_is_the_papers_axis() {
    let c = seed_closed_loop(1e-3);
    assert_eq!(c.axis.gearhead.ratio, 19.0);
    assert_eq!(c.axis.screw.lead_m, 2e-3);
    assert_eq!(c.axis.dahl.coulomb_force_n, 30.4);
    assert_eq!(c.axis.dahl.stiffness_n_per_m, 75e6); // 75 N/µm
    assert_eq!(c.axis.dahl.exponent, 1.0);
    assert_eq!(c.encoder.count_m, 100e-9);
    assert_eq!(c.output.amplifier_limit_v, 6.0);
    assert_eq!(c.pid.ticks_per_sample as f64 / c.pid.clock_hz, 1e-3);
    for (step, gains) in [
        (100e-6, (450.0, 2.0, 40.0)),
        (500e-6, (450.0, 2.0, 40.0)),
        (1e-3, (450.0, 5.0, 10.0)),
        (10e-3, (450.0, 5.0, 25.0)),
    ] {
        assert_eq!(presets::table1_gains(step), gains, "Table 1 at {step} m");
        let p = seed_closed_loop(step).pid;
        assert_eq!((p.kp, p.ki, p.kd), gains);
    }
}
