//! The seed axis alone: true stiction (no creep), presliding rest, steady sliding speed.
use nanostage::integrate::IntegratorOptions;
use nanostage::model::{Axis, AxisParams};
#[path = "support/presets.rs"]
mod presets;
use nanostage::sim::run_open_loop;
use presets::seed_axis;

const T: f64 = 1e-3;

fn breakaway_voltage(p: &AxisParams) -> f64 {
    // Stuck with i = u/R: |k_t·u/R| > Ts breaks the motor-shaft stiction.
    p.motor_friction.static_torque_nm * p.motor.resistance_ohm / p.motor.torque_constant_nm_per_a
}

#[test]
fn constant_sub_breakaway_voltage_gives_zero_drift() {
    for quasi in [false, true] {
        let mut p = seed_axis();
        p.motor.quasi_static_current = quasi;
        let u = 0.9 * breakaway_voltage(&p);
        let tr = run_open_loop(&p, &IntegratorOptions::default(), &vec![u; 10_000], T).unwrap();
        assert!(
            tr.position_m.iter().all(|&x| x == 0.0),
            "moved: quasi={quasi}"
        );
        assert!(tr.stuck.iter().all(|&s| s));
    }
}

#[test]
fn presliding_comes_to_rest_and_then_does_not_creep() {
    let p = seed_axis();
    let axis = Axis::new(p).unwrap();
    // Above the motor breakaway but well below full sliding (Ts + r·Fc/η).
    let full = (p.motor_friction.static_torque_nm
        + axis.transmission_m_per_rad * p.dahl.coulomb_force_n / axis.efficiency)
        * p.motor.resistance_ohm
        / p.motor.torque_constant_nm_per_a;
    let u = 0.5 * (breakaway_voltage(&p) + full);
    let tr = run_open_loop(&p, &IntegratorOptions::default(), &vec![u; 10_000], T).unwrap();
    let x5 = tr.position_m[5_000];
    assert!(x5 > 0.0 && x5 < 1e-6, "presliding displacement {x5}");
    for k in 5_000..=10_000 {
        assert_eq!(
            tr.position_m[k].to_bits(),
            x5.to_bits(),
            "creep at sample {k}"
        );
    }
    assert!(tr.stuck[10_000]);
    assert!(tr.dahl_force_n[10_000].abs() < p.dahl.coulomb_force_n);
}

#[test]
fn steady_sliding_speed_matches_the_force_balance() {
    let mut p = seed_axis();
    p.motor.quasi_static_current = false;
    let axis = Axis::new(p).unwrap();
    let u = 4.0;
    let tr = run_open_loop(&p, &IntegratorOptions::default(), &vec![u; 1_000], T).unwrap();
    let v_sim = *tr.velocity_m_per_s.last().unwrap();
    // Independent steady state: z = Fc, i = (u − k_e·w)/R, η(k_t·i − Tf(w))/r = Fc; bisection.
    let r = axis.transmission_m_per_rad;
    let m = p.motor;
    let f = p.motor_friction;
    let balance = |v: f64| {
        let w = v / r;
        let i = (u - m.back_emf_v_s_per_rad * w) / m.resistance_ohm;
        let tf = f.coulomb_torque_nm
            + (f.static_torque_nm - f.coulomb_torque_nm)
                * (-(w / f.stribeck_velocity_rad_per_s).powi(2)).exp()
            + f.viscous_nm_s_per_rad * w;
        axis.efficiency * (m.torque_constant_nm_per_a * i - tf) / r - p.dahl.coulomb_force_n
    };
    let (mut lo, mut hi) = (1e-9, 0.1);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if balance(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let v_ss = 0.5 * (lo + hi);
    assert!(
        ((v_sim - v_ss) / v_ss).abs() < 1e-6,
        "simulated {v_sim} vs analytic {v_ss}"
    );
}

#[test]
fn invalid_plant_names_the_field() {
    let mut p = seed_axis();
    p.table.mass_kg = -1.0;
    let err = Axis::new(p).unwrap_err();
    assert_eq!(err.field, "table.mass_kg");
    p.table.mass_kg = f64::NAN;
    assert_eq!(Axis::new(p).unwrap_err().field, "table.mass_kg");
}
